"""Warp Hencky + Drucker-Prager (NCLaw Eqs. 14-16), built per (dim, precision).

The stress and both return maps are spectral functions of F, U diag(g(s)) W^T; they go through
``linalg.spectral_func`` so their derivatives stay finite at repeated singular values (F = I, the rest
state), as the JAX laws' ``spectral`` custom JVP. Each g comes with its Jacobians in s and in its
parameters; the forward arithmetic is unchanged.
"""

from functools import lru_cache
from types import SimpleNamespace

import warp as wp

from ...backends.warp.linalg import HENCKY_MIN_STRETCH, spectral_func, warp_linalg
from ...backends.warp.types import warp_types


@lru_cache(maxsize=None)
def hencky_funcs(dim: int, precision: str) -> SimpleNamespace:
    """Hencky pieces shared with hencky_von_mises: the Kirchhoff stress, the strain split and the
    volume-keeping return maps of Eqs. 16 and 19."""
    T = warp_types(dim, precision)
    La = warp_linalg(dim, precision)
    scalar, vec, mat, LawState = T.scalar, T.vec, T.mat, T.LawState
    fdim = float(dim)   # scalar(dim) on the int closure constant confuses Warp's range(dim) (Warp 1.19)
    p1, p2 = wp.types.vector(1, scalar), wp.types.vector(2, scalar)
    j1, j2 = wp.types.matrix((dim, 1), scalar), wp.types.matrix((dim, 2), scalar)

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

    # ---- principal Kirchhoff stresses 2 mu eps + lambda tr(eps), pv = (mu, lambda) (NCLaw Eq. 14) ----
    @wp.func
    def tau_g(s: vec, pv: p2):
        eps = logs(s)
        tr, eps_hat, n = trace_split(eps)
        t = vec()
        for i in range(dim):
            t[i] = scalar(2.0) * pv[0] * eps[i] + pv[1] * tr
        return t

    @wp.func
    def tau_jac(s: vec, pv: p2):
        eps = logs(s)
        de = dlogs(s)
        tr, eps_hat, n = trace_split(eps)
        Jg = mat()
        Jp = j2()
        for i in range(dim):
            for j in range(dim):
                Jg[i, j] = pv[1] * de[j]
            Jg[i, i] = Jg[i, i] + scalar(2.0) * pv[0] * de[i]
            Jp[i, 0] = scalar(2.0) * eps[i]
            Jp[i, 1] = tr
        return Jg, Jp

    tau_map = spectral_func(dim, precision, SimpleNamespace(g=tau_g, jac=tau_jac), left=True, nparams=2)

    @wp.func
    def kirchhoff(s: LawState, prm: wp.array2d(dtype=scalar), p: int):
        """tau = U (2 mu eps + lambda tr(eps) I) U^T (NCLaw Eq. 14, which calls it "P"; P = tau F^-T)."""
        mu, lam = La.lame(prm[p, 0], prm[p, 1])
        U, sv, V = La.svd_const(s.F)
        return tau_map(s.F, U, sv, V, p2(mu, lam))

    # ---- exp(eps - dg eps_hat / |eps_hat|): isochoric returns. With u = eps_hat / n, g_i = exp(tr/d +
    # a u_i) where a = k (von Mises, dg = n - k) or a = -c alpha tr (Drucker-Prager, dg = n + c alpha
    # tr); du_i/deps_j = (P_ij - u_i u_j) / n with P = I - 11^T/d. ----
    @wp.func
    def returned(eps: vec, eps_hat: vec, n: scalar, dg: scalar):
        e = vec()
        for i in range(dim):
            e[i] = wp.exp(eps[i] - dg * eps_hat[i] / n)
        return e

    @wp.func
    def return_jac(g: vec, de: vec, u: vec, n: scalar, a: scalar, da_dtr: scalar):
        """dg_i/ds_j for g_i = exp(tr/d + a u_i), a depending on tr with slope da_dtr."""
        Jg = mat()
        for i in range(dim):
            for j in range(dim):
                P = -scalar(1.0) / scalar(fdim)
                if i == j:
                    P = P + scalar(1.0)
                Jg[i, j] = g[i] * (scalar(1.0) / scalar(fdim) + da_dtr * u[i] + a * (P - u[i] * u[j]) / n) * de[j]
        return Jg

    @wp.func
    def vm_g(s: vec, pv: p1):
        eps = logs(s)
        tr, eps_hat, n = trace_split(eps)
        return returned(eps, eps_hat, n, n - pv[0])                      # NCLaw Eq. 19, k = tau_Y / (2 mu)

    @wp.func
    def vm_jac(s: vec, pv: p1):
        g = vm_g(s, pv)
        eps = logs(s)
        tr, eps_hat, n = trace_split(eps)
        u = eps_hat / n
        Jp = j1()
        for i in range(dim):
            Jp[i, 0] = g[i] * u[i]
        return return_jac(g, dlogs(s), u, n, pv[0], scalar(0.0)), Jp

    @wp.func
    def dp_g(s: vec, pv: p2):
        eps = logs(s)
        tr, eps_hat, n = trace_split(eps)
        return returned(eps, eps_hat, n, n + pv[0] * tr * pv[1])         # NCLaw Eq. 16, (c, alpha)

    @wp.func
    def dp_jac(s: vec, pv: p2):
        g = dp_g(s, pv)
        eps = logs(s)
        tr, eps_hat, n = trace_split(eps)
        u = eps_hat / n
        ca = pv[0] * pv[1]
        Jp = j2()
        for i in range(dim):
            Jp[i, 0] = -g[i] * pv[1] * tr * u[i]
            Jp[i, 1] = -g[i] * pv[0] * tr * u[i]
        return return_jac(g, dlogs(s), u, n, -ca * tr, -ca), Jp

    vm_return = spectral_func(dim, precision, SimpleNamespace(g=vm_g, jac=vm_jac), left=False, nparams=1)
    dp_return = spectral_func(dim, precision, SimpleNamespace(g=dp_g, jac=dp_jac), left=False, nparams=2)

    return SimpleNamespace(logs=logs, trace_split=trace_split, kirchhoff=kirchhoff, vm_return=vm_return,
                           dp_return=dp_return, p1=p1, p2=p2)


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
        U, sv, V = La.svd_const(F)
        tr, eps_hat, n = H.trace_split(H.logs(sv))
        if tr > scalar(0.0):                       # tension: cone tip (Eq. 16, first case)
            F = La.polar(F, U, sv, V, La.no_params())
        else:
            c = (scalar(fdim) * lam + scalar(2.0) * mu) / (scalar(2.0) * mu)
            dg = n + c * tr * alpha
            if dg > scalar(0.0) and n > scalar(0.0):   # outside the cone: project onto it (third case)
                F = H.dp_return(F, U, sv, V, H.p2(c, alpha))
        out.F = F
        return out

    return SimpleNamespace(kirchhoff=H.kirchhoff, update=update)
