"""FLIP on Warp (JAX-MPM Eq. 15; force as in Eq. 12). The ratio is ``tp[0]``, a kernel argument."""

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
        return m * v, mat(), mat()

    @wp.func
    def p2g_force(m: scalar, V: scalar, v: vec, C: mat, tau: mat, dt: scalar, inv_dx: scalar,
                  Dinv: mat, tp: wp.array(dtype=scalar)):
        return mat(), F.gradient_force(V, tau, inv_dx)

    @wp.func
    def g2p(v: vec, vp: vec, vo: vec, B: mat, Gv: mat, fx: vec, inv_dx: scalar, Dinv: mat,
            tp: wp.array(dtype=scalar)):
        r = tp[0]
        return r * (v + vp - vo) + (scalar(1.0) - r) * vp, mat(), Gv

    return SimpleNamespace(p2g_momentum=p2g_momentum, p2g_force=p2g_force, g2p=g2p)


def make(transfer, dim: int, precision: str):
    return funcs(dim, precision)
