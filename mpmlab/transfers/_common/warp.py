"""Warp pieces shared by the built-in schemes (``@wp.func``s; ``AbstractTransfer`` documents the
signatures)."""

from functools import lru_cache
from types import SimpleNamespace

import warp as wp

from ...backends.warp.types import warp_types


@lru_cache(maxsize=None)
def forms(dim: int, precision: str):
    T = warp_types(dim, precision)
    scalar, vec, mat = T.scalar, T.vec, T.mat

    @wp.func
    def gradient_force(V: scalar, tau: mat, inv_dx: scalar):
        """The coefficient of the cell-unit weight gradient in f_i = -sum_p V tau grad w (JAX-MPM Eq. 12)."""
        return -(V * inv_dx) * tau

    @wp.func
    def apic_C(B: mat, vp: vec, fx: vec, inv_dx: scalar, Dinv: mat):
        """C = B_p D_p^-1 (Jiang et al. 2015; JAX-MPM Eq. B.1) with B_p = sum w v_i (x_i - x_p)^T =
        (sum w v_i o^T - v_pic fx^T) dx (o the node offsets in cells; the kernels gather the first term)
        and the shape function's D_p^-1 (``Dinv``; 4/dx^2 I for quadratic B-splines)."""
        return ((B - wp.outer(vp, fx)) @ Dinv) * (scalar(1.0) / inv_dx)

    return SimpleNamespace(gradient_force=gradient_force, apic_C=apic_C, T=T)
