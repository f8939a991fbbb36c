"""Warp Hencky + Drucker-Prager (NCLaw Eqs. 14-16), built per (dim, precision).

The stress and both return maps are spectral functions of F, U diag(g(s)) W^T; they go through
``linalg.spectral_func`` so their derivatives stay finite at repeated singular values (F = I, the rest
state), as the JAX laws' ``spectral`` custom JVP. Each g comes with its Jacobian in s; the forward
arithmetic is the inline one (bit-identical results).
"""

from functools import lru_cache
from types import SimpleNamespace

import warp as wp

from ...backends.warp.linalg import HENCKY_MIN_STRETCH, spectral_func, warp_linalg
from ...backends.warp.law_structs import law_types
from ...backends.warp.types import warp_types


@lru_cache(maxsize=None)
def hencky_funcs(dim: int, precision: str) -> SimpleNamespace:
    """Hencky pieces shared with hencky_von_mises: the Kirchhoff stress, the strain split and the
    volume-keeping return maps of Eqs. 16 and 19."""
    T = warp_types(dim, precision)
    La = warp_linalg(dim, precision)
    scalar, vec, mat = T.scalar, T.vec, T.mat
    fdim = float(dim)   # scalar(dim) on the int closure constant confuses Warp's range(dim) (Warp 1.19)
    p1, p2 = wp.types.vector(1, scalar), wp.types.vector(2, scalar)

    @wp.func
    def logs(s: vec):
        """eps = log of the clamped singular values (the Hencky strain's principal values)."""
        eps = vec()
        for i in range(dim):
            eps[i] = wp.log(wp.max(s[i], scalar(HENCKY_MIN_STRETCH)))
        return eps

    @wp.func
    def dlogs(s: vec):
        """d eps_i / d s_i (0 below the clamp)."""
        d = vec()
        for i in range(dim):
            if s[i] > scalar(HENCKY_MIN_STRETCH):
                d[i] = scalar(1.0) / s[i]
        return d

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

    # ---- principal Kirchhoff stresses t = 2 mu eps + lambda tr(eps), pv = (mu, lambda) (NCLaw Eq. 14) ----
    @wp.func
    def tau_jac(s: vec, t: vec, pv: p2):
        de = dlogs(s)
        Jg = mat()
        for i in range(dim):
            for j in range(dim):
                Jg[i, j] = pv[1] * de[j]
            Jg[i, i] = Jg[i, i] + scalar(2.0) * pv[0] * de[i]
        return Jg

    tau_map = spectral_func(dim, precision, tau_jac, left=True, nparams=2)

    @wp.func
    def kirchhoff(F: mat, E: scalar, nu: scalar):
        """tau = U (2 mu eps + lambda tr(eps) I) U^T (NCLaw Eq. 14, which calls it "P"; P = tau F^-T)."""
        mu, lam = La.lame(E, nu)
        U, sv, V = La.svd_const(F)
        eps = logs(sv)
        tr, eps_hat, n = trace_split(eps)
        t = vec()
        for i in range(dim):
            t[i] = scalar(2.0) * mu * eps[i] + lam * tr
        return tau_map(F, U, sv, V, t, p2(mu, lam))

    # ---- e = exp(eps - dg eps_hat / |eps_hat|): the volume-keeping returns of Eqs. 16 and 19. With
    # u = eps_hat / n, e_i = exp(tr/d + a u_i) where a = k (von Mises, dg = n - k) or a = -c alpha tr
    # (Drucker-Prager, dg = n + c alpha tr); du_i/deps_j = (P_ij - u_i u_j) / n, P = I - 11^T/d. ----
    @wp.func
    def returned(eps: vec, eps_hat: vec, n: scalar, dg: scalar):
        e = vec()
        for i in range(dim):
            e[i] = wp.exp(eps[i] - dg * eps_hat[i] / n)
        return e

    @wp.func
    def return_jac(g: vec, s: vec, a: scalar, da_dtr: scalar):
        """dg_i/ds_j for g_i = exp(tr/d + a u_i), a depending on tr with slope da_dtr."""
        tr, eps_hat, n = trace_split(logs(s))
        u = eps_hat / n
        de = dlogs(s)
        Jg = mat()
        for i in range(dim):
            for j in range(dim):
                P = -scalar(1.0) / scalar(fdim)
                if i == j:
                    P = P + scalar(1.0)
                Jg[i, j] = g[i] * (scalar(1.0) / scalar(fdim) + da_dtr * u[i] + a * (P - u[i] * u[j]) / n) * de[j]
        return Jg

    @wp.func
    def vm_jac(s: vec, g: vec, pv: p1):
        return return_jac(g, s, pv[0], scalar(0.0))                      # pv = (k = tau_Y / (2 mu))

    @wp.func
    def dp_jac(s: vec, g: vec, pv: p2):
        tr, eps_hat, n = trace_split(logs(s))
        ca = pv[0] * pv[1]                                               # pv = (c, alpha)
        return return_jac(g, s, -ca * tr, -ca)

    vm_map = spectral_func(dim, precision, vm_jac, left=False, nparams=1)
    dp_map = spectral_func(dim, precision, dp_jac, left=False, nparams=2)

    @wp.func
    def vm_return(F: mat, U: mat, sv: vec, V: mat, eps: vec, eps_hat: vec, n: scalar, k: scalar):
        """NCLaw Eq. 19 for dg = n - k > 0, k = tau_Y / (2 mu)."""
        return vm_map(F, U, sv, V, returned(eps, eps_hat, n, n - k), p1(k))

    @wp.func
    def dp_return(F: mat, U: mat, sv: vec, V: mat, eps: vec, eps_hat: vec, n: scalar, tr: scalar, c: scalar,
                  alpha: scalar):
        """NCLaw Eq. 16, third case: dg = n + c tr alpha, c = (d lambda + 2 mu) / (2 mu)."""
        return dp_map(F, U, sv, V, returned(eps, eps_hat, n, n + c * tr * alpha), p2(c, alpha))

    @wp.func
    def dp_project(F: mat, E: scalar, nu: scalar, friction_angle: scalar):
        """The Drucker-Prager return map of a trial elastic F (NCLaw Eq. 16), friction angle in degrees;
        also used by laws that compute the angle themselves (e.g. with hardening, the example plugin)."""
        mu, lam = La.lame(E, nu)
        sp = wp.sin(friction_angle * (scalar(wp.pi) / scalar(180.0)))
        alpha = wp.sqrt(scalar(2.0) / scalar(3.0)) * scalar(2.0) * sp / (scalar(3.0) - sp)   # NCLaw Eq. 15
        U, sv, V = La.svd_const(F)
        eps = logs(sv)
        tr, eps_hat, n = trace_split(eps)
        if tr > scalar(0.0):                       # tension: cone tip (Eq. 16, first case)
            F = La.polar(F, U, sv, V)
        else:
            c = (scalar(fdim) * lam + scalar(2.0) * mu) / (scalar(2.0) * mu)
            dg = n + c * tr * alpha
            if dg > scalar(0.0) and n > scalar(0.0):   # outside the cone: project onto it (third case)
                F = dp_return(F, U, sv, V, eps, eps_hat, n, tr, c, alpha)
        return F

    return SimpleNamespace(logs=logs, trace_split=trace_split, kirchhoff=kirchhoff, vm_return=vm_return,
                           dp_return=dp_return, dp_project=dp_project)


@lru_cache(maxsize=None)
def make(law, dim: int, precision: str) -> SimpleNamespace:
    T = law_types(law, dim, precision)
    H = hencky_funcs(dim, precision)
    scalar, mat, LawState, Params, Weights = T.scalar, T.mat, T.LawState, T.Params, T.Weights

    @wp.func
    def update(s: LawState, grad_v: mat, dt: scalar, prm: Params, w: Weights):
        out = s
        out.F = H.dp_project((wp.identity(dim, scalar) + dt * grad_v) @ s.F, prm.E, prm.nu, prm.friction_angle)
        return out

    @wp.func
    def kirchhoff(s: LawState, prm: Params, w: Weights):
        return H.kirchhoff(s.F, prm.E, prm.nu)

    return SimpleNamespace(kirchhoff=kirchhoff, update=update)
