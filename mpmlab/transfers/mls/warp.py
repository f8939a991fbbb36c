"""MLS-MPM on Warp (Hu et al. 2018; the mpm3d form A = m C - dt V tau D^-1, D^-1 = 4/dx^2 I for
quadratic B-splines, the shape function's ``Dinv`` otherwise)."""

from functools import lru_cache
from types import SimpleNamespace

import warp as wp

from .._common.warp import forms


@lru_cache(maxsize=None)
def funcs(dim: int, precision: str):
    F = forms(dim, precision)
    scalar, vec, mat = F.T.scalar, F.T.vec, F.T.mat

    @wp.func
    def p2g_momentum(m: scalar, V: scalar, v: vec, C: mat, tau: mat, dt: scalar, inv_dx: scalar,
                     Dinv: mat, tp: wp.array(dtype=scalar)):
        A = m * C
        A = A - (V * dt) * (tau @ Dinv)       # Hu et al. 2018: D^-1 = 4/dx^2 I for quadratic B-splines
        return m * v, A, mat()

    @wp.func
    def g2p(v: vec, vp: vec, vo: vec, B: mat, Gv: mat, fx: vec, inv_dx: scalar, Dinv: mat,
            tp: wp.array(dtype=scalar)):
        Cn = F.apic_C(B, vp, fx, inv_dx, Dinv)
        return vp, Cn, Cn

    return SimpleNamespace(p2g_momentum=p2g_momentum, g2p=g2p)


def make(transfer, dim: int, precision: str):
    return funcs(dim, precision)
