"""Cubic B-spline weights as a Warp ``@wp.func`` (the formulas of ``reference.py``)."""
from functools import lru_cache
from types import SimpleNamespace

import warp as wp

from ...backends.warp.types import warp_types


@lru_cache(maxsize=None)
def make(shape, dim: int, precision: str):
    """``weights(fx, lp) -> (W, DW)`` and ``hessian(fx, lp) -> DDW`` (d2N/dx_p^2, cell units), each
    4 x dim matrices; fx in [1, 2) per axis, lp unused."""
    T = warp_types(dim, precision)
    scalar, vec = T.scalar, T.vec
    wmat = wp.types.matrix((4, dim), scalar)
    OFFS = wp.types.vector(4, scalar)(*[float(k) for k in range(4)])   # node offsets (not OFFS[k]: Warp 1.19)

    @wp.func
    def n(r: scalar):
        """N(r) = |r|^3/2 - r^2 + 2/3 (|r| < 1), (2 - |r|)^3/6 (1 <= |r| < 2), 0 beyond."""
        a = wp.abs(r)
        out = scalar(0.0)
        if a < scalar(1.0):
            out = scalar(0.5) * a * a * a - a * a + scalar(2.0) / scalar(3.0)
        elif a < scalar(2.0):
            out = (scalar(2.0) - a) * (scalar(2.0) - a) * (scalar(2.0) - a) / scalar(6.0)
        return out

    @wp.func
    def dn(r: scalar):
        """dN/dr."""
        a = wp.abs(r)
        out = scalar(0.0)
        if a < scalar(1.0):
            out = scalar(1.5) * r * a - scalar(2.0) * r
        elif a < scalar(2.0):
            out = scalar(-0.5) * (scalar(2.0) - a) * (scalar(2.0) - a) * wp.sign(r)
        return out

    @wp.func
    def ddn(r: scalar):
        """d2N/dr2 = 3|r| - 2 (|r| < 1), 2 - |r| (1 <= |r| < 2), 0 beyond."""
        a = wp.abs(r)
        out = scalar(0.0)
        if a < scalar(1.0):
            out = scalar(3.0) * a - scalar(2.0)
        elif a < scalar(2.0):
            out = scalar(2.0) - a
        return out

    @wp.func
    def weights(fx: vec, lp: scalar):
        W = wmat()
        DW = wmat()
        for d in range(dim):
            for k in range(4):
                r = fx[d] - OFFS[k]
                W[k, d] = n(r)
                DW[k, d] = dn(r)
        return W, DW

    @wp.func
    def hessian(fx: vec, lp: scalar):
        H = wmat()
        for d in range(dim):
            for k in range(4):
                H[k, d] = ddn(fx[d] - OFFS[k])
        return H

    return SimpleNamespace(weights=weights, hessian=hessian, wmat=wmat)
