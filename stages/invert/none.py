"""invert.kind=none: no feedforward (feedback only), the reference point for every method."""
import numpy as np


def feedforward(ctx, name, r):
    return np.zeros_like(r)
