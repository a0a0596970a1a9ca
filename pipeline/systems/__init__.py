"""Simulated plants (SPEC §2): one module per plant, each a :class:`~pipeline.systems.base.System`."""
