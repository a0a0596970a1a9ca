"""Learning on the machine, trial by trial, from recordings (issue 50): a campaign folder
(:mod:`pipeline.learn.campaign`), its update laws (:mod:`pipeline.learn.update`), the convergence and
per-trial safety rules (:mod:`pipeline.learn.safety`) and virtual machines behind the same files
(:mod:`pipeline.learn.machine`); the ``pgnn-ff learn`` command is :mod:`pipeline.learn.cli`."""
