"""Quadratic B-spline weights as a Warp ``@wp.func`` (the formulas of ``reference.py``; the kernels'
stencil before shape functions were a choice, unchanged so the default keeps its results)."""
from functools import lru_cache
from types import SimpleNamespace

import warp as wp

from ...backends.warp.types import warp_types


@lru_cache(maxsize=None)
def make(shape, dim: int, precision: str):
    """``weights(fx, lp) -> (W, DW)`` and ``hessian(fx, lp) -> DDW`` (d2N/dx_p^2, cell units), each
    3 x dim matrices; fx in [0.5, 1.5) per axis, lp unused."""
    T = warp_types(dim, precision)
    scalar, vec = T.scalar, T.vec
    wmat = wp.types.matrix((3, dim), scalar)

    @wp.func
    def weights(fx: vec, lp: scalar):
        """W[k, d] = N(fx_d - k), DW[k, d] = N'(fx_d - k) (JAX-MPM Eq. 9)."""
        W = wmat()
        DW = wmat()
        for d in range(dim):
            f = fx[d]
            W[0, d] = scalar(0.5) * (scalar(1.5) - f) * (scalar(1.5) - f)
            W[1, d] = scalar(0.75) - (f - scalar(1.0)) * (f - scalar(1.0))
            W[2, d] = scalar(0.5) * (f - scalar(0.5)) * (f - scalar(0.5))
            DW[0, d] = f - scalar(1.5)
            DW[1, d] = scalar(-2.0) * (f - scalar(1.0))
            DW[2, d] = f - scalar(0.5)
        return W, DW

    @wp.func
    def hessian(fx: vec, lp: scalar):
        """N'' of the three nodes: 1, -2, 1 on every axis."""
        H = wmat()
        for d in range(dim):
            H[0, d] = scalar(1.0)
            H[1, d] = scalar(-2.0)
            H[2, d] = scalar(1.0)
        return H

    return SimpleNamespace(weights=weights, hessian=hessian, wmat=wmat)
