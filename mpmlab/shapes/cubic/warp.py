"""Cubic B-spline weights as a Warp ``@wp.func`` (the formulas of ``reference.py``; the per-axis products: ``shapes/_common/warp.py``)."""
from functools import lru_cache

import warp as wp

from ...backends.warp.types import warp_types
from .._common.warp import separable


@lru_cache(maxsize=None)
def make(shape, dim: int, precision: str):
    """``weights(fx, lp) -> (W, DW)`` and ``hessian(fx, lp) -> DDW`` (d2N/dx_p^2, cell units), each
    4 x dim matrices; fx in [1, 2) per axis, lp unused."""
    scalar = warp_types(dim, precision).scalar

    @wp.func
    def n(r: scalar, lp: scalar):
        """N(r) = |r|^3/2 - r^2 + 2/3 (|r| < 1), (2 - |r|)^3/6 (1 <= |r| < 2), 0 beyond."""
        a = wp.abs(r)
        out = scalar(0.0)
        if a < scalar(1.0):
            out = scalar(0.5) * a * a * a - a * a + scalar(2.0) / scalar(3.0)
        elif a < scalar(2.0):
            out = (scalar(2.0) - a) * (scalar(2.0) - a) * (scalar(2.0) - a) / scalar(6.0)
        return out

    @wp.func
    def dn(r: scalar, lp: scalar):
        """dN/dr."""
        a = wp.abs(r)
        out = scalar(0.0)
        if a < scalar(1.0):
            out = scalar(1.5) * r * a - scalar(2.0) * r
        elif a < scalar(2.0):
            out = scalar(-0.5) * (scalar(2.0) - a) * (scalar(2.0) - a) * wp.sign(r)
        return out

    @wp.func
    def ddn(r: scalar, lp: scalar):
        """d2N/dr2 = 3|r| - 2 (|r| < 1), 2 - |r| (1 <= |r| < 2), 0 beyond."""
        a = wp.abs(r)
        out = scalar(0.0)
        if a < scalar(1.0):
            out = scalar(3.0) * a - scalar(2.0)
        elif a < scalar(2.0):
            out = scalar(2.0) - a
        return out

    return separable(dim, precision, 4, n, dn, ddn)
