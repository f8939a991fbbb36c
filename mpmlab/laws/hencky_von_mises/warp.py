"""Warp Hencky + von Mises (NCLaw Eqs. 17-19), built per (dim, precision). The stress and the
return map (spectral maps with safe derivatives) are those of ``hencky_drucker_prager.warp``."""

from functools import lru_cache
from types import SimpleNamespace

import warp as wp

from ...backends.warp.linalg import warp_linalg
from ...backends.warp.types import warp_types
from ..hencky_drucker_prager.warp import hencky_funcs


@lru_cache(maxsize=None)
def make(dim: int, precision: str) -> SimpleNamespace:
    T = warp_types(dim, precision)
    La = warp_linalg(dim, precision)
    H = hencky_funcs(dim, precision)
    scalar, mat, LawState = T.scalar, T.mat, T.LawState

    @wp.func
    def update(s: LawState, grad_v: mat, dt: scalar, prm: wp.array2d(dtype=scalar), p: int):
        out = s
        F = (wp.identity(dim, scalar) + dt * grad_v) @ s.F
        mu, lam = La.lame(prm[p, 0], prm[p, 1])
        U, sv, V = La.svd_const(F)
        eps = H.logs(sv)
        tr, eps_hat, n = H.trace_split(eps)
        k = prm[p, 2] / (scalar(2.0) * mu)
        if n - k > scalar(0.0):                    # NCLaw Eq. 18: isochoric return (Eq. 19)
            F = H.vm_return(F, U, sv, V, eps, eps_hat, n, k)
        out.F = F
        return out

    return SimpleNamespace(kirchhoff=H.kirchhoff, update=update)
