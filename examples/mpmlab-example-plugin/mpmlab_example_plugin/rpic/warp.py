"""RPIC on Warp: the same math as ``jax.py`` as ``@wp.func``s (mpmlab's kernels close over them)."""
from functools import lru_cache
from types import SimpleNamespace

import warp as wp

from mpmlab.backends.warp.types import warp_types


@lru_cache(maxsize=None)       # one set of functions per (dim, precision): the kernels compile once
def funcs(dim: int, precision: str):
    T = warp_types(dim, precision)
    scalar, vec, mat = T.scalar, T.vec, T.mat

    @wp.func
    def p2g_momentum(m: scalar, V: scalar, v: vec, C: mat, tau: mat, dt: scalar, inv_dx: scalar,
                     Dinv: mat, tp: wp.array(dtype=scalar)):
        # G multiplies the weight gradient in cell units (dx grad w): hence the inv_dx
        return m * v, m * C, dt * (-(V * inv_dx) * tau)

    @wp.func
    def g2p(v: vec, vp: vec, vo: vec, B: mat, Gv: mat, fx: vec, inv_dx: scalar, Dinv: mat,
            tp: wp.array(dtype=scalar)):
        C = ((B - wp.outer(vp, fx)) @ Dinv) * (scalar(1.0) / inv_dx)     # B D^-1 (B in cells: times dx)
        return vp, scalar(0.5) * (C - wp.transpose(C)), Gv

    return SimpleNamespace(p2g_momentum=p2g_momentum, g2p=g2p)


def make(transfer, dim: int, precision: str):
    return funcs(dim, precision)
