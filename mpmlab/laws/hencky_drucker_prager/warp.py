"""Warp Hencky + Drucker-Prager (NCLaw Eqs. 14-16), built per (dim, precision)."""

from functools import lru_cache
from types import SimpleNamespace

import warp as wp

from ...backends.warp.linalg import warp_linalg
from ...backends.warp.types import warp_types


@lru_cache(maxsize=None)
def hencky_funcs(dim: int, precision: str) -> SimpleNamespace:
    """Hencky pieces shared with hencky_von_mises: the Kirchhoff stress and the strain split."""
    T = warp_types(dim, precision)
    La = warp_linalg(dim, precision)
    scalar, vec, mat, LawState = T.scalar, T.vec, T.mat, T.LawState
    fdim = float(dim)   # scalar(dim) on the int closure constant confuses Warp's range(dim) (Warp 1.19)

    @wp.func
    def trace_split(eps: vec):
        """(tr(eps), eps_hat = eps - tr/d, |eps_hat|)."""
        tr = scalar(0.0)
        for i in range(dim):
            tr = tr + eps[i]
        eps_hat = vec()
        for i in range(dim):
            eps_hat[i] = eps[i] - tr / scalar(fdim)
        return tr, eps_hat, wp.length(eps_hat)

    @wp.func
    def kirchhoff(s: LawState, prm: wp.array2d(dtype=scalar), p: int):
        """tau = U (2 mu eps + lambda tr(eps) I) U^T (NCLaw Eq. 14, which calls it "P"; P = tau F^-T)."""
        mu, lam = La.lame(prm[p, 0], prm[p, 1])
        U, eps, V = La.hencky_strain(s.F)
        tr, eps_hat, n = trace_split(eps)
        t = vec()
        for i in range(dim):
            t[i] = scalar(2.0) * mu * eps[i] + lam * tr
        return U @ La.diag(t) @ wp.transpose(U)

    @wp.func
    def deviatoric_return(U: mat, eps: vec, eps_hat: vec, n: scalar, dg: scalar, V: mat):
        """F = U exp(eps - dg eps_hat/|eps_hat|) V^T: the volume-keeping return of Eqs. 16 and 19."""
        e = vec()
        for i in range(dim):
            e[i] = wp.exp(eps[i] - dg * eps_hat[i] / n)
        return U @ La.diag(e) @ wp.transpose(V)

    return SimpleNamespace(trace_split=trace_split, kirchhoff=kirchhoff, deviatoric_return=deviatoric_return)


@lru_cache(maxsize=None)
def make(dim: int, precision: str) -> SimpleNamespace:
    T = warp_types(dim, precision)
    La = warp_linalg(dim, precision)
    H = hencky_funcs(dim, precision)
    scalar, mat, LawState = T.scalar, T.mat, T.LawState
    fdim = float(dim)   # scalar(dim) on the int closure constant confuses Warp's range(dim) (Warp 1.19)

    @wp.func
    def update(s: LawState, grad_v: mat, dt: scalar, prm: wp.array2d(dtype=scalar), p: int):
        out = s
        F = (wp.identity(dim, scalar) + dt * grad_v) @ s.F
        mu, lam = La.lame(prm[p, 0], prm[p, 1])
        sp = wp.sin(prm[p, 2] * (scalar(wp.pi) / scalar(180.0)))
        alpha = wp.sqrt(scalar(2.0) / scalar(3.0)) * scalar(2.0) * sp / (scalar(3.0) - sp)   # NCLaw Eq. 15
        U, eps, V = La.hencky_strain(F)
        tr, eps_hat, n = H.trace_split(eps)
        if tr > scalar(0.0):                       # tension: cone tip (Eq. 16, first case)
            F = U @ wp.transpose(V)
        else:
            dg = n + (scalar(fdim) * lam + scalar(2.0) * mu) / (scalar(2.0) * mu) * tr * alpha
            if dg > scalar(0.0) and n > scalar(0.0):   # outside the cone: project onto it (third case)
                F = H.deviatoric_return(U, eps, eps_hat, n, dg, V)
        out.F = F
        return out

    return SimpleNamespace(kirchhoff=H.kirchhoff, update=update)
