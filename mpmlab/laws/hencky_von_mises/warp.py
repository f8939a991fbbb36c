"""Warp Hencky + von Mises (NCLaw Eqs. 17-19), built per (dim, precision). The stress and the
return map (spectral maps with safe derivatives) are those of ``hencky_drucker_prager.warp``, plane strain
in 2D as there (``vm_project_ps``)."""

from functools import lru_cache
from types import SimpleNamespace

import warp as wp

from ...backends.warp.linalg import warp_linalg
from ...backends.warp.law_structs import law_types
from ..hencky_drucker_prager.warp import hencky_funcs


@lru_cache(maxsize=None)
def make(law, dim: int, precision: str) -> SimpleNamespace:
    T = law_types(law, dim, precision)
    La = warp_linalg(dim, precision)
    H = hencky_funcs(dim, precision)
    scalar, mat, LawState, Params, Weights = T.scalar, T.mat, T.LawState, T.Params, T.Weights

    if dim == 2:   # plane strain (see the Law)
        @wp.func
        def update(s: LawState, grad_v: mat, dt: scalar, prm: Params, w: Weights):
            out = s
            F, ezz = H.vm_project_ps((wp.identity(dim, scalar) + dt * grad_v) @ s.F, s.eps_zz, prm.E, prm.nu,
                                     prm.yield_stress)
            out.F = F
            out.eps_zz = ezz
            return out

        @wp.func
        def kirchhoff(s: LawState, prm: Params, w: Weights):
            return H.kirchhoff_ps(s.F, s.eps_zz, prm.E, prm.nu)

        return SimpleNamespace(kirchhoff=kirchhoff, update=update)

    @wp.func
    def update(s: LawState, grad_v: mat, dt: scalar, prm: Params, w: Weights):
        out = s
        F = (wp.identity(dim, scalar) + dt * grad_v) @ s.F
        mu, lam = La.lame(prm.E, prm.nu)
        U, sv, V = La.svd_const(F)
        eps = H.logs(sv)
        tr, eps_hat, n = H.trace_split(eps)
        k = prm.yield_stress / (scalar(2.0) * mu)
        if n - k > scalar(0.0):                    # NCLaw Eq. 18: isochoric return (Eq. 19)
            F = H.vm_return(F, U, sv, V, eps, eps_hat, n, k)
        out.F = F
        return out

    @wp.func
    def kirchhoff(s: LawState, prm: Params, w: Weights):
        return H.kirchhoff(s.F, prm.E, prm.nu)

    return SimpleNamespace(kirchhoff=kirchhoff, update=update)
