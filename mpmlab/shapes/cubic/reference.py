"""Cubic B-spline weights in 1-D, written once against an array module (NumPy here, ``jnp`` in
``jax.py``). fx = x_p/dx - base in [1, 2); node k sits at r = fx - k cells from the particle."""
from __future__ import annotations

import numpy as np


def _n(r, xp):
    """N(r) = |r|^3/2 - r^2 + 2/3 (|r| < 1), (2 - |r|)^3/6 (1 <= |r| < 2), 0 beyond (Steffen et al. 2008)."""
    a = xp.abs(r)
    inner = 0.5 * a ** 3 - a ** 2 + 2.0 / 3.0
    outer = (2.0 - a) ** 3 / 6.0
    return xp.where(a < 1.0, inner, xp.where(a < 2.0, outer, 0.0 * a))


def _dn(r, xp):
    """dN/dr."""
    a = xp.abs(r)
    s = xp.sign(r)
    inner = 1.5 * r * a - 2.0 * r
    outer = -0.5 * (2.0 - a) ** 2 * s
    return xp.where(a < 1.0, inner, xp.where(a < 2.0, outer, 0.0 * a))


def weights_1d(fx, lp=None, xp=np, axis=-1):
    """(w, dw) of shape [..., 4]: N(fx - k) and dN/dx_p (cells) for k = 0 .. 3; ``axis``: where the node
    axis goes."""
    r = xp.stack([fx - k for k in range(4)], axis=axis)
    return _n(r, xp), _dn(r, xp)
