"""Identification criteria and solvers (SPEC §5): NARX / direct-inverse criteria of [B1]
(``narx``) and the shared Levenberg–Marquardt solver (``lm``)."""
