"""Warp Drucker-Prager with hardening: mpmlab's Hencky Drucker-Prager return map (``dp_project``) with
the friction angle of the hardening state (Klar et al. 2016, Sec. 7.3)."""
from functools import lru_cache
from types import SimpleNamespace

import warp as wp

from mpmlab.backends.warp import law_types
from mpmlab.backends.warp.linalg import HENCKY_MIN_STRETCH, warp_linalg
from mpmlab.laws.hencky_drucker_prager.warp import hencky_funcs


@lru_cache(maxsize=None)
def make(law, dim: int, precision: str) -> SimpleNamespace:
    T = law_types(law, dim, precision)
    La = warp_linalg(dim, precision)
    H = hencky_funcs(dim, precision)
    scalar, vec, mat, LawState, Params, Weights = T.scalar, T.vec, T.mat, T.LawState, T.Params, T.Weights
    fdim = float(dim)
    deg = 3.141592653589793 / 180.0

    @wp.func
    def kirchhoff(s: LawState, prm: Params, w: Weights):
        return H.kirchhoff(s.F, prm.E, prm.nu)

    @wp.func
    def update(s: LawState, grad_v: mat, dt: scalar, prm: Params, w: Weights):
        out = s
        F = (wp.identity(dim, scalar) + dt * grad_v) @ s.F
        q = s.q
        phi = prm.h0 + (prm.h1 * q - prm.h3) * wp.exp(-prm.h2 * q)
        out.F = H.dp_project(F, prm.E, prm.nu, phi)
        sv = La.singular_values(F)                  # with its derivative (finite at repeated values)
        eps = vec()
        for i in range(dim):
            eps[i] = wp.log(wp.max(sv[i], scalar(HENCKY_MIN_STRETCH)))
        tr = scalar(0.0)
        for i in range(dim):
            tr = tr + eps[i]
        eps_hat = eps - (tr / scalar(fdim)) * vec(scalar(1.0))
        n2 = wp.dot(eps_hat, eps_hat)
        n = scalar(0.0)
        if n2 > scalar(0.0):
            n = wp.sqrt(n2)
        mu = prm.E / (scalar(2.0) * (scalar(1.0) + prm.nu))
        lam = prm.E * prm.nu / ((scalar(1.0) + prm.nu) * (scalar(1.0) - scalar(2.0) * prm.nu))
        sp = wp.sin(phi * scalar(deg))
        alpha = wp.sqrt(scalar(2.0) / scalar(3.0)) * scalar(2.0) * sp / (scalar(3.0) - sp)
        dg = n + (scalar(fdim) * lam + scalar(2.0) * mu) / (scalar(2.0) * mu) * tr * alpha
        dq = scalar(0.0)
        if tr > scalar(0.0):
            e2 = wp.dot(eps, eps)
            if e2 > scalar(0.0):
                dq = wp.sqrt(e2)
        elif dg > scalar(0.0) and n > scalar(0.0):
            dq = dg
        out.q = q + dq
        return out

    return SimpleNamespace(kirchhoff=kirchhoff, update=update)
