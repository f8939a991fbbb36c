"""TPIC on Warp (JAX-MPM Eq. B.2): APIC's P2G; C is the gathered velocity gradient (Eq. 18)."""

from functools import lru_cache
from types import SimpleNamespace

import warp as wp

from .._common.warp import forms
from ..apic import warp as apic


@lru_cache(maxsize=None)
def funcs(dim: int, precision: str):
    A = apic.funcs(dim, precision)
    T = forms(dim, precision).T
    scalar, vec, mat = T.scalar, T.vec, T.mat

    @wp.func
    def g2p(v: vec, vp: vec, vo: vec, B: mat, Gv: mat, fx: vec, inv_dx: scalar, Dinv: mat,
            tp: wp.array(dtype=scalar)):
        return vp, Gv, Gv

    return SimpleNamespace(p2g_momentum=A.p2g_momentum, g2p=g2p)


def make(transfer, dim: int, precision: str):
    return funcs(dim, precision)
