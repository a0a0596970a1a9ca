"""Feedforward by model inversion (SPEC §6): physics and analytic inversion ([B1] (8), (27),
``analytic``), the direct-inverse PGNN ([B1] (13), ``direct``), Newton inversion ([B1] Alg. 1,
``newton``), and the optimisation/learning-based methods in their own modules."""
