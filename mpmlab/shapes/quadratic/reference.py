"""Quadratic B-spline weights in 1-D, written once against an array module (NumPy here, ``jnp`` in
``jax.py``). fx = x_p/dx - base in [0.5, 1.5); node k sits at r = fx - k cells from the particle."""
from __future__ import annotations

import numpy as np


def weights_1d(fx, lp=None, xp=np, axis=-1):
    """(w, dw) of shape [..., 3]: N(fx - k) and dN/dx_p (cells) for k = 0, 1, 2 (JAX-MPM Eq. 9); ``axis``:
    where the node axis goes (JAX: 1, giving [N, 3, D] for fx [N, D] without a transpose)."""
    w = xp.stack([0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2], axis=axis)
    dw = xp.stack([fx - 1.5, -2.0 * (fx - 1.0), fx - 0.5], axis=axis)
    return w, dw
