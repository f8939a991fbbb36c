"""uGIMP weights as a Warp ``@wp.func`` (the formulas of ``reference.py``; lp = the particle's half
width in cells, a per-particle constant the kernels read from an array)."""
from functools import lru_cache

import warp as wp

from ...backends.warp.types import warp_types
from .._common.warp import separable


@lru_cache(maxsize=None)
def make(shape, dim: int, precision: str):
    """``weights(fx, lp) -> (W, DW)`` and ``hessian(fx, lp) -> DDW`` (d2S/dx_p^2, cell units), each
    3 x dim matrices; fx in [0.5, 1.5) per axis, 0 < lp <= 1/2."""
    scalar = warp_types(dim, precision).scalar

    @wp.func
    def s(r: scalar, lp: scalar):
        """S(r) = 1 - (r^2 + lp^2)/(2 lp) (|r| < lp), 1 - |r| (lp <= |r| <= 1 - lp),
        (1 + lp - |r|)^2 / (4 lp) (1 - lp < |r| < 1 + lp), 0 beyond."""
        a = wp.abs(r)
        out = scalar(0.0)
        if a < lp:
            out = scalar(1.0) - (r * r + lp * lp) / (scalar(2.0) * lp)
        elif a <= scalar(1.0) - lp:
            out = scalar(1.0) - a
        elif a < scalar(1.0) + lp:
            out = (scalar(1.0) + lp - a) * (scalar(1.0) + lp - a) / (scalar(4.0) * lp)
        return out

    @wp.func
    def ds(r: scalar, lp: scalar):
        """dS/dr."""
        a = wp.abs(r)
        out = scalar(0.0)
        if a < lp:
            out = -r / lp
        elif a <= scalar(1.0) - lp:
            out = -wp.sign(r)
        elif a < scalar(1.0) + lp:
            out = -wp.sign(r) * (scalar(1.0) + lp - a) / (scalar(2.0) * lp)
        return out

    @wp.func
    def dds(r: scalar, lp: scalar):
        """d2S/dr2: -1/lp, 0, 1/(2 lp) in the three pieces."""
        a = wp.abs(r)
        out = scalar(0.0)
        if a < lp:
            out = scalar(-1.0) / lp
        elif a <= scalar(1.0) - lp:
            out = scalar(0.0)
        elif a < scalar(1.0) + lp:
            out = scalar(1.0) / (scalar(2.0) * lp)
        return out

    return separable(dim, precision, 3, s, ds, dds)
