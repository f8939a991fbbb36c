"""uGIMP weights in 1-D (Bardenhagen & Kober 2004, Eq. 35 with a box particle characteristic function),
written once against an array module (NumPy here, ``jnp`` in ``jax.py``). fx = x_p/dx - base in
[0.5, 1.5); node k sits at r = fx - k cells from the particle; lp is the particle's half width in cells
(0 < lp <= 1/2)."""
from __future__ import annotations

import numpy as np


def _s(r, lp, xp):
    """S(r) = 1 - (r^2 + lp^2)/(2 lp) (|r| < lp), 1 - |r| (lp <= |r| <= 1 - lp),
    (1 + lp - |r|)^2 / (4 lp) (1 - lp < |r| < 1 + lp), 0 beyond."""
    a = xp.abs(r)
    inner = 1.0 - (r * r + lp * lp) / (2.0 * lp)
    middle = 1.0 - a
    outer = (1.0 + lp - a) ** 2 / (4.0 * lp)
    return xp.where(a < lp, inner, xp.where(a <= 1.0 - lp, middle, xp.where(a < 1.0 + lp, outer, 0.0 * a)))


def _ds(r, lp, xp):
    """dS/dr."""
    a = xp.abs(r)
    s = xp.sign(r)
    inner = -r / lp
    middle = -s
    outer = -s * (1.0 + lp - a) / (2.0 * lp)
    return xp.where(a < lp, inner, xp.where(a <= 1.0 - lp, middle, xp.where(a < 1.0 + lp, outer, 0.0 * a)))


def weights_1d(fx, lp, xp=np, axis=-1):
    """(w, dw) of shape [..., 3]: S(fx - k) and dS/dx_p (cells) for k = 0, 1, 2; lp broadcasts with fx;
    ``axis``: where the node axis goes."""
    r = xp.stack([fx - k for k in range(3)], axis=axis)
    lp = xp.expand_dims(lp, axis)
    return _s(r, lp, xp), _ds(r, lp, xp)
