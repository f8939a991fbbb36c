"""Quadratic B-spline weights in 1-D, written once against an array module (NumPy here, ``jnp`` in
``jax.py``). fx = x_p/dx - base in [0.5, 1.5); node k sits at r = fx - k cells from the particle."""
from __future__ import annotations

import numpy as np


def weights_1d(fx, lp=None, xp=np):
    """(w, dw) of shape [..., 3]: N(fx - k) and dN/dx_p (cells) for k = 0, 1, 2 (JAX-MPM Eq. 9)."""
    w = xp.stack([0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2], axis=-1)
    dw = xp.stack([fx - 1.5, -2.0 * (fx - 1.0), fx - 0.5], axis=-1)
    return w, dw
