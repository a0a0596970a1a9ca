"""Feedforward by model inversion (SPEC §6): direct-inverse PGNN, Newton inversion
([B1] Alg. 1) and analytic inversion ([B1] (27))."""
