"""APIC on Warp (Jiang et al. 2015; JAX-MPM Eqs. 12, 18, B.1)."""

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
        return m * v, m * C, dt * F.gradient_force(V, tau, inv_dx)

    @wp.func
    def g2p(v: vec, vp: vec, vo: vec, B: mat, Gv: mat, fx: vec, inv_dx: scalar, Dinv: mat,
            tp: wp.array(dtype=scalar)):
        return vp, F.apic_C(B, vp, fx, inv_dx, Dinv), Gv

    return SimpleNamespace(p2g_momentum=p2g_momentum, g2p=g2p)


def make(transfer, dim: int, precision: str):
    return funcs(dim, precision)
