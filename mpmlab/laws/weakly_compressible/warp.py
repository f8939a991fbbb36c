"""Warp weakly compressible fluid (NCLaw Eqs. 20-21) on the J state, built per (dim, precision)."""

from functools import lru_cache
from types import SimpleNamespace

import warp as wp

from ...backends.warp.types import warp_types


@lru_cache(maxsize=None)
def make(dim: int, precision: str) -> SimpleNamespace:
    T = warp_types(dim, precision)
    scalar, mat, LawState = T.scalar, T.mat, T.LawState

    @wp.func
    def kirchhoff(s: LawState, prm: wp.array2d(dtype=scalar), p: int):
        return prm[p, 0] * s.J * (s.J - scalar(1.0)) * wp.identity(dim, scalar)

    @wp.func
    def update(s: LawState, grad_v: mat, dt: scalar, prm: wp.array2d(dtype=scalar), p: int):
        out = s
        out.J = s.J * wp.determinant(wp.identity(dim, scalar) + dt * grad_v)
        return out

    return SimpleNamespace(kirchhoff=kirchhoff, update=update)
