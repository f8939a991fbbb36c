"""Warp Hencky + Drucker-Prager (NCLaw Eqs. 14-16), built per (dim, precision).

The stress and both return maps are spectral functions of F, U diag(g(s)) W^T; they go through
``linalg.spectral_func`` so their derivatives stay finite at repeated singular values (F = I, the rest
state), as the JAX laws' ``spectral`` custom JVP. Each g comes with its Jacobian in s; the forward
arithmetic is the inline one (bit-identical results).

2D is plane strain (see the Law): ``kirchhoff_ps``, ``dp_project_ps`` and ``vm_project_ps`` carry the
elastic out-of-plane strain eps_zz (``_plane_strain_funcs``).
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

    ns = SimpleNamespace(logs=logs, trace_split=trace_split, kirchhoff=kirchhoff, vm_return=vm_return,
                         dp_return=dp_return, dp_project=dp_project)
    if dim == 2:
        ns.__dict__.update(_plane_strain_funcs(precision, La, logs, dlogs, tau_map, p2))
    return ns


def _plane_strain_funcs(precision: str, La, logs, dlogs, tau_map, p2) -> dict:
    """2D plane strain (see the Law): three principal strains (eps_1, eps_2, eps_zz), the 3D formulas.
    The in-plane returned stretches go through a spectral map whose g_i = exp(tr/3 + a u_i) has the
    Jacobian of ``return_jac`` restricted to the plane (u the 3D unit deviator); the new eps_zz = tr/3 + a u_z
    through U diag(h, h) U^T = h I (an isotropic g with equal rows), so both derivatives are exact."""
    T = warp_types(2, precision)
    scalar, vec, mat = T.scalar, T.vec, T.mat
    v3 = wp.types.vector(3, scalar)
    p3 = wp.types.vector(3, scalar)

    @wp.func
    def split3(eps: vec, ezz: scalar):
        """(tr over three, the 3D deviator (eps_1, eps_2, eps_zz) - tr/3, its norm)."""
        tr = eps[0] + eps[1] + ezz
        m = tr / scalar(3.0)
        h = v3(eps[0] - m, eps[1] - m, ezz - m)
        return tr, h, wp.length(h)

    @wp.func
    def kirchhoff_ps(F: mat, ezz: scalar, E: scalar, nu: scalar):
        """In-plane tau_i = 2 mu eps_i + lambda (eps_1 + eps_2 + eps_zz) (Eq. 14 in plane strain); d tau_i/d s_j
        is that of the 2D map (eps_zz enters as a constant), so ``tau_map``'s Jacobian holds."""
        mu, lam = La.lame(E, nu)
        U, sv, V = La.svd_const(F)
        eps = logs(sv)
        tr = eps[0] + eps[1] + ezz
        t = vec()
        for i in range(2):
            t[i] = scalar(2.0) * mu * eps[i] + lam * tr
        return tau_map(F, U, sv, V, t, p2(mu, lam))

    @wp.func
    def dlog_row(s: vec, ezz: scalar, a: scalar, da_dtr: scalar, k: int):
        """d eps_new_k / d s_j (j in the plane) for eps_new_k = tr/3 + a u_k, u = eps_hat / n over three."""
        tr, h, n = split3(logs(s), ezz)
        u = h / n
        de = dlogs(s)
        r = vec()
        for j in range(2):
            P = -scalar(1.0) / scalar(3.0)
            if k == j:
                P = P + scalar(1.0)
            r[j] = (scalar(1.0) / scalar(3.0) + da_dtr * u[k] + a * (P - u[k] * u[j]) / n) * de[j]
        return r

    @wp.func
    def a_of(s: vec, pv: p3):
        """(a, da/dtr) of the return: pv = (c alpha, -, eps_zz) Drucker-Prager (a = -c alpha tr), or
        (0, k, eps_zz) von Mises (a = k)."""
        tr, h, n = split3(logs(s), pv[2])
        if pv[0] != scalar(0.0):
            return -pv[0] * tr, -pv[0]
        return pv[1], scalar(0.0)

    @wp.func
    def inplane_jac(s: vec, g: vec, pv: p3):
        a, da = a_of(s, pv)
        Jg = mat()
        for i in range(2):
            r = dlog_row(s, pv[2], a, da, i)
            for j in range(2):
                Jg[i, j] = g[i] * r[j]
        return Jg

    @wp.func
    def zz_jac(s: vec, g: vec, pv: p3):
        a, da = a_of(s, pv)
        r = dlog_row(s, pv[2], a, da, 2)
        Jg = mat()
        for i in range(2):
            for j in range(2):
                Jg[i, j] = r[j]
        return Jg

    inplane_map = spectral_func(2, precision, inplane_jac, left=False, nparams=3)
    zz_map = spectral_func(2, precision, zz_jac, left=True, nparams=3)

    @wp.func
    def return_ps(F: mat, U: mat, sv: vec, V: mat, eps: vec, ezz: scalar, h: v3, n: scalar, dg: scalar, pv: p3):
        """eps_new = eps - dg eps_hat / n over three (Eqs. 16 / 19, d = 3): (U diag(e^eps_new) V^T, eps_new_zz)."""
        g = vec()
        for i in range(2):
            g[i] = wp.exp(eps[i] - dg * h[i] / n)
        zn = ezz - dg * h[2] / n
        Fn = inplane_map(F, U, sv, V, g, pv)
        Z = zz_map(F, U, sv, V, vec(zn, zn), pv)
        return Fn, scalar(0.5) * (Z[0, 0] + Z[1, 1])

    @wp.func
    def dp_project_ps(F: mat, ezz: scalar, E: scalar, nu: scalar, friction_angle: scalar):
        """The Drucker-Prager return map of a plane-strain trial (F, eps_zz) (Eq. 16 with d = 3)."""
        mu, lam = La.lame(E, nu)
        sp = wp.sin(friction_angle * (scalar(wp.pi) / scalar(180.0)))
        alpha = wp.sqrt(scalar(2.0) / scalar(3.0)) * scalar(2.0) * sp / (scalar(3.0) - sp)   # NCLaw Eq. 15
        U, sv, V = La.svd_const(F)
        eps = logs(sv)
        tr, h, n = split3(eps, ezz)
        Fo = F
        zo = ezz
        if tr > scalar(0.0):                       # tension: cone tip, eps = 0 (Eq. 16, first case)
            Fo = La.polar(F, U, sv, V)
            zo = scalar(0.0)
        else:
            c = (scalar(3.0) * lam + scalar(2.0) * mu) / (scalar(2.0) * mu)
            dg = n + c * tr * alpha
            if dg > scalar(0.0) and n > scalar(0.0):   # outside the cone (third case)
                Fo, zo = return_ps(F, U, sv, V, eps, ezz, h, n, dg, p3(c * alpha, scalar(0.0), ezz))
        return Fo, zo

    @wp.func
    def vm_project_ps(F: mat, ezz: scalar, E: scalar, nu: scalar, yield_stress: scalar):
        """The von Mises return map of a plane-strain trial (Eqs. 18-19 with d = 3), k = tau_Y / (2 mu)."""
        mu, lam = La.lame(E, nu)
        k = yield_stress / (scalar(2.0) * mu)
        U, sv, V = La.svd_const(F)
        eps = logs(sv)
        tr, h, n = split3(eps, ezz)
        Fo = F
        zo = ezz
        if n - k > scalar(0.0):
            Fo, zo = return_ps(F, U, sv, V, eps, ezz, h, n, n - k, p3(scalar(0.0), k, ezz))
        return Fo, zo

    return dict(kirchhoff_ps=kirchhoff_ps, dp_project_ps=dp_project_ps, vm_project_ps=vm_project_ps)


@lru_cache(maxsize=None)
def make(law, dim: int, precision: str) -> SimpleNamespace:
    T = law_types(law, dim, precision)
    H = hencky_funcs(dim, precision)
    scalar, mat, LawState, Params, Weights = T.scalar, T.mat, T.LawState, T.Params, T.Weights

    if dim == 2:   # plane strain (see the Law)
        @wp.func
        def update(s: LawState, grad_v: mat, dt: scalar, prm: Params, w: Weights):
            out = s
            F, ezz = H.dp_project_ps((wp.identity(dim, scalar) + dt * grad_v) @ s.F, s.eps_zz, prm.E, prm.nu,
                                     prm.friction_angle)
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
        out.F = H.dp_project((wp.identity(dim, scalar) + dt * grad_v) @ s.F, prm.E, prm.nu, prm.friction_angle)
        return out

    @wp.func
    def kirchhoff(s: LawState, prm: Params, w: Weights):
        return H.kirchhoff(s.F, prm.E, prm.nu)

    return SimpleNamespace(kirchhoff=kirchhoff, update=update)
