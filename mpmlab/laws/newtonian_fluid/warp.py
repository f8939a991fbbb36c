"""Warp weakly compressible Newtonian fluid (JAX-MPM Eqs. 19-20), built per (dim, precision)."""

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
        return s.J * s.sigma

    @wp.func
    def update(s: LawState, grad_v: mat, dt: scalar, prm: Params, w: Weights):
        c = prm.sound_speed
        mu = prm.viscosity
        rho0 = prm.rest_density
        pmin = prm.min_pressure
        eye = wp.identity(dim, scalar)
        out = s
        J = s.J * wp.determinant(eye + dt * grad_v)
        pres = wp.max(c * c * (rho0 / J - rho0), pmin)          # Eq. 20, rho = rho0 / J; tension cut-off
        D = scalar(0.5) * (grad_v + wp.transpose(grad_v))       # strain rate (Eq. 19 uses D dt: see Law)
        out.J = J
        # 1/3 also in 2D (the paper's deviator)
        out.sigma = -pres * eye + scalar(2.0) * mu * (D - wp.trace(D) / scalar(3.0) * eye)
        return out

    return SimpleNamespace(kirchhoff=kirchhoff, update=update)
