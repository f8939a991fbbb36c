"""uGIMP weights as a Warp ``@wp.func`` (the formulas of ``reference.py``; lp = the particle's half
width in cells, a per-particle constant the kernels read from an array)."""
from functools import lru_cache
from types import SimpleNamespace

import warp as wp

from ...backends.warp.types import warp_types


@lru_cache(maxsize=None)
def make(shape, dim: int, precision: str):
    """``weights(fx, lp) -> (W, DW)`` and ``hessian(fx, lp) -> DDW`` (d2S/dx_p^2, cell units), each
    3 x dim matrices; fx in [0.5, 1.5) per axis, 0 < lp <= 1/2."""
    T = warp_types(dim, precision)
    scalar, vec = T.scalar, T.vec
    wmat = wp.types.matrix((3, dim), scalar)
    OFFS = wp.types.vector(3, scalar)(*[float(k) for k in range(3)])   # node offsets (not OFFS[k]: Warp 1.19)

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

    @wp.func
    def weights(fx: vec, lp: scalar):
        W = wmat()
        DW = wmat()
        for d in range(dim):
            for k in range(3):
                r = fx[d] - OFFS[k]
                W[k, d] = s(r, lp)
                DW[k, d] = ds(r, lp)
        return W, DW

    @wp.func
    def hessian(fx: vec, lp: scalar):
        H = wmat()
        for d in range(dim):
            for k in range(3):
                H[k, d] = dds(fx[d] - OFFS[k], lp)
        return H

    return SimpleNamespace(weights=weights, hessian=hessian, wmat=wmat)
