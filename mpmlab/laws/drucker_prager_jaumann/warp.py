"""Warp Jaumann-rate Drucker-Prager law (JAX-MPM Eq. 21, App. A), built per (dim, precision); 2D is plane
strain (sigma_zz is state, see the Law)."""

import math
from functools import lru_cache
from types import SimpleNamespace

import warp as wp

from ...backends.warp.law_structs import law_types

DEG = math.pi / 180.0
R3 = math.sqrt(3.0)
SQRT2_3 = math.sqrt(2.0) / 3.0
SQRT1_3 = math.sqrt(1.0 / 3.0)


@lru_cache(maxsize=None)
def make(law, dim: int, precision: str) -> SimpleNamespace:
    T = law_types(law, dim, precision)
    scalar, mat, LawState, Params, Weights = T.scalar, T.mat, T.LawState, T.Params, T.Weights
    PS = dim == 2       # plane strain in 2D (see Law): sigma_zz is state and enters A.3-A.4

    @wp.func
    def kirchhoff(s: LawState, prm: Params, w: Weights):
        return s.J * s.sigma

    @wp.func
    def update(s: LawState, grad_v: mat, dt: scalar, prm: Params, w: Weights):
        K = prm.bulk_modulus
        nu = prm.nu
        phi = prm.friction_angle * scalar(DEG)
        psi = prm.dilation_angle * scalar(DEG)
        c = prm.cohesion
        st = prm.tensile_strength
        G = scalar(3.0) * K * (scalar(1.0) - scalar(2.0) * nu) / (scalar(2.0) * (scalar(1.0) + nu))
        lam = K - scalar(2.0) * G / scalar(3.0)
        sp = wp.sin(phi)
        sps = wp.sin(psi)
        q_phi = scalar(6.0) * sp / (scalar(R3) * (scalar(3.0) + sp))
        k_phi = scalar(6.0) * c * wp.cos(phi) / (scalar(R3) * (scalar(3.0) + sp))
        q_psi = scalar(6.0) * sps / (scalar(R3) * (scalar(3.0) + sps))
        eye = wp.identity(dim, scalar)

        # A.1-A.2 (Eq. 21) on the Kirchhoff stress J sigma (see Law): Hughes-Winget rotation R (exactly
        # orthogonal, = I + dw + O(dw^2)) + isotropic elastic increment, then sigma_trial = tau_trial / J_new
        J_new = s.J * wp.determinant(eye + dt * grad_v)
        dd = scalar(0.5) * dt * (grad_v + wp.transpose(grad_v))
        dw = scalar(0.5) * dt * (grad_v - wp.transpose(grad_v))
        R = eye + (dw + scalar(0.5) * (dw @ dw)) / (scalar(1.0) + scalar(0.125) * wp.ddot(dw, dw))
        trial = (R @ (s.J * s.sigma) @ wp.transpose(R) + lam * wp.trace(dd) * eye + scalar(2.0) * G * dd) / J_new
        tzz = scalar(0.0)
        if wp.static(PS):        # sigma_zz's trial: d_zz = 0, R_zz = 1
            tzz = (s.J * s.sigma_zz + lam * wp.trace(dd)) / J_new

        # A.3-A.4 over three components (2D: diag(trial, tzz))
        sm = (wp.trace(trial) + tzz) / scalar(3.0)
        dev = trial - sm * eye
        dzz = scalar(0.0)
        if wp.static(PS):
            dzz = tzz - sm
        ss2 = scalar(0.5) * (wp.ddot(dev, dev) + dzz * dzz)
        tau = scalar(0.0)
        if ss2 > scalar(0.0):
            tau = wp.sqrt(ss2)

        # A.5-A.11
        fs = tau - k_phi + q_phi * sm
        ft = sm - st
        tau_p = k_phi - q_phi * st
        alpha_p = wp.sqrt(scalar(1.0) + q_phi * q_phi) - q_phi
        h = tau - tau_p - alpha_p * (sm - st)

        out = s
        new_sig = trial
        new_zz = tzz
        deps = scalar(0.0)
        zone2 = False
        if ft < scalar(0.0):
            zone2 = fs > scalar(0.0)
        else:
            zone2 = h > scalar(0.0)
        if zone2:
            dl = fs / (G + K * q_phi * q_psi)                     # A.16
            sm2 = wp.min(sm - K * q_psi * dl, st)                 # A.12, capped at sigma_t (corner return)
            tau2 = k_phi - q_phi * sm2                            # A.13
            ratio = scalar(0.0)
            if tau > scalar(0.0):
                ratio = tau2 / tau
            new_sig = ratio * dev + sm2 * eye                     # A.14
            new_zz = ratio * dzz + sm2
            deps = dl * wp.sqrt(scalar(1.0) / scalar(3.0) + scalar(2.0) / scalar(9.0) * q_psi * q_psi)  # A.15
        elif ft >= scalar(0.0):
            # A.17-A.19, the wedge tau > tau_P returned to the corner (sigma_t, tau_P) (see reference)
            tau3 = wp.min(tau, tau_p)
            ratio3 = scalar(0.0)
            if tau > scalar(0.0):
                ratio3 = tau3 / tau
            new_sig = ratio3 * dev + st * eye                     # A.17 (+ corner)
            new_zz = ratio3 * dzz + st
            deps = scalar(SQRT2_3) * (sm - st) / K + (tau - tau3) / G * scalar(SQRT1_3)   # A.18-A.19 (+ A.15)
        out.sigma = new_sig
        if wp.static(PS):
            out.sigma_zz = new_zz
        out.eps_p = s.eps_p + deps
        out.J = J_new
        return out

    return SimpleNamespace(kirchhoff=kirchhoff, update=update)
