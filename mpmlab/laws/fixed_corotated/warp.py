"""Warp fixed corotated law (NCLaw Eq. 12), built per (dim, precision)."""

from functools import lru_cache
from types import SimpleNamespace

import warp as wp

from ...backends.warp.linalg import warp_linalg
from ...backends.warp.law_structs import law_types


@lru_cache(maxsize=None)
def make(law, dim: int, precision: str) -> SimpleNamespace:
    T = law_types(law, dim, precision)
    La = warp_linalg(dim, precision)
    scalar, mat, LawState, Params, Weights = T.scalar, T.mat, T.LawState, T.Params, T.Weights

    @wp.func
    def kirchhoff(s: LawState, prm: Params, w: Weights):
        mu, lam = La.lame(prm.E, prm.nu)
        U, sig, V = La.svd_const(s.F)
        R = La.polar(s.F, U, sig, V)   # U V^T with a derivative finite at F = I
        J = wp.determinant(s.F)
        return scalar(2.0) * mu * (s.F - R) @ wp.transpose(s.F) + lam * J * (J - scalar(1.0)) * wp.identity(dim, scalar)

    @wp.func
    def update(s: LawState, grad_v: mat, dt: scalar, prm: Params, w: Weights):
        out = s
        out.F = (wp.identity(dim, scalar) + dt * grad_v) @ s.F
        return out

    return SimpleNamespace(kirchhoff=kirchhoff, update=update)
