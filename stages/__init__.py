"""Pipeline stages: thin functions config -> library -> artifacts (see pipeline/runner.py).

generate -> baseline -> train -> invert -> evaluate, and report over the tracking store.
Method-specific implementations live in ``stages/<stage>/<kind>.py`` and are chosen by the
config (``data.kind``, ``identify.kind``, ``invert.kind``).
"""
