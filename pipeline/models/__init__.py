"""Model classes of SPEC §3 (torch.nn.Module, float64): physics-guided neural networks
(``pgnn``: forward, direct inverse, analytically invertible; physics-only and black-box as
the same classes with one part switched off)."""
