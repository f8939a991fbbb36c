"""A Warp transfer factory whose g2p returns a vector where the affine field C (a matrix) goes, one that
forgets p2g_force and one written before shape functions were a choice (no ``Dinv`` argument)
(tests/test_transfer_check.py)."""
from types import SimpleNamespace

import warp as wp

from mpmlab.backends.warp.types import warp_types


def make(transfer, dim, precision):
    T = warp_types(dim, precision)
    scalar, vec, mat = T.scalar, T.vec, T.mat

    @wp.func
    def p2g_momentum(m: scalar, V: scalar, v: vec, C: mat, tau: mat, dt: scalar, inv_dx: scalar,
                     Dinv: mat, tp: wp.array(dtype=scalar)):
        return m * v, m * C, -(dt * V * inv_dx) * tau

    @wp.func
    def g2p(v: vec, vp: vec, vo: vec, B: mat, Gv: mat, fx: vec, inv_dx: scalar, Dinv: mat,
            tp: wp.array(dtype=scalar)):
        return vp, vp, Gv

    return SimpleNamespace(p2g_momentum=p2g_momentum, g2p=g2p)


def make_without_force(transfer, dim, precision):
    """A split_force scheme's factory that forgets p2g_force."""
    out = make(transfer, dim, precision)
    return SimpleNamespace(p2g_momentum=out.p2g_momentum, g2p=out.g2p)


def make_without_dinv(transfer, dim, precision):
    """APIC's functions with the signatures of before shape functions (no ``Dinv: mat`` before ``tp``)."""
    T = warp_types(dim, precision)
    scalar, vec, mat = T.scalar, T.vec, T.mat

    @wp.func
    def p2g_momentum(m: scalar, V: scalar, v: vec, C: mat, tau: mat, dt: scalar, inv_dx: scalar,
                     tp: wp.array(dtype=scalar)):
        return m * v, m * C, -(dt * V * inv_dx) * tau

    @wp.func
    def g2p(v: vec, vp: vec, vo: vec, B: mat, Gv: mat, fx: vec, inv_dx: scalar, tp: wp.array(dtype=scalar)):
        return vp, (scalar(4.0) * inv_dx) * (B - wp.outer(vp, fx)), Gv

    return SimpleNamespace(p2g_momentum=p2g_momentum, g2p=g2p)
