"""Ship the feedforward (issue 12): a law as flat data (:mod:`~pipeline.export.law`), its C99
code (:mod:`~pipeline.export.c_code`), a verified package (:mod:`~pipeline.export.package`) and
an MLflow pyfunc model (:mod:`~pipeline.export.pyfunc`)."""
