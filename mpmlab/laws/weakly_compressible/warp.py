"""Warp weakly compressible fluid (NCLaw Eqs. 20-21) on the J state, built per (dim, precision)."""

from functools import lru_cache
from types import SimpleNamespace

import warp as wp

from ...backends.warp.law_structs import law_types


@lru_cache(maxsize=None)
def make(law, dim: int, precision: str) -> SimpleNamespace:
    T = law_types(law, dim, precision)
    scalar, mat, LawState, Params, Weights = T.scalar, T.mat, T.LawState, T.Params, T.Weights

    @wp.func
    def kirchhoff(s: LawState, prm: Params, w: Weights):
        return prm.bulk_modulus * s.J * (s.J - scalar(1.0)) * wp.identity(dim, scalar)

    @wp.func
    def update(s: LawState, grad_v: mat, dt: scalar, prm: Params, w: Weights):
        out = s
        out.J = s.J * wp.determinant(wp.identity(dim, scalar) + dt * grad_v)
        return out

    return SimpleNamespace(kirchhoff=kirchhoff, update=update)
