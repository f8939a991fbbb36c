"""Warp compressible Neo-Hookean law: ``@wp.func``s built per (dim, precision), which mpmlab's Warp
stepper closes over when it builds its kernels (no branching on a law id inside a kernel)."""
from functools import lru_cache
from types import SimpleNamespace

import warp as wp

from mpmlab.backends.warp import law_types


@lru_cache(maxsize=None)
def make(law, dim: int, precision: str) -> SimpleNamespace:
    T = law_types(law, dim, precision)   # LawState, Params (by name), Weights: from the law's declarations
    scalar, mat, LawState, Params, Weights = T.scalar, T.mat, T.LawState, T.Params, T.Weights

    @wp.func
    def kirchhoff(s: LawState, prm: Params, w: Weights):
        E = prm.E
        nu = prm.nu
        mu = E / (scalar(2.0) * (scalar(1.0) + nu))
        lam = E * nu / ((scalar(1.0) + nu) * (scalar(1.0) - scalar(2.0) * nu))
        logJ = wp.log(wp.abs(wp.determinant(s.F)))
        eye = wp.identity(dim, scalar)
        return mu * (s.F @ wp.transpose(s.F) - eye) + lam * logJ * eye

    @wp.func
    def update(s: LawState, grad_v: mat, dt: scalar, prm: Params, w: Weights):
        out = s
        out.F = (wp.identity(dim, scalar) + dt * grad_v) @ s.F
        return out

    return SimpleNamespace(kirchhoff=kirchhoff, update=update)
