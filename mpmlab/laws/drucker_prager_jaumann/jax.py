"""JAX Jaumann-rate Drucker-Prager law (JAX-MPM Eq. 21, App. A); per particle, vmapped by the stepper.

Branch-free: every zone is computed and picked with ``jnp.where``; tau = sqrt(s:s/2) and the Zone II ratio
use safe arguments so that gradients stay finite at zero deviator (the rest state). 2D is plane strain:
sigma_zz is state and enters A.3-A.4 (see the Law)."""
from __future__ import annotations

import math
from types import SimpleNamespace

import jax.numpy as jnp

DEG = math.pi / 180.0
R3 = math.sqrt(3.0)


def make(law, dim: int) -> SimpleNamespace:
    eye = jnp.eye(dim)
    ps = dim == 2      # plane strain

    def kirchhoff(state, prm, w):
        return state["J"] * state["sigma"]

    def update(state, grad_v, dt, prm, w):
        K, nu, phi, psi, c, st = (prm["bulk_modulus"], prm["nu"], prm["friction_angle"] * DEG, prm["dilation_angle"] * DEG,
                                  prm["cohesion"], prm["tensile_strength"])
        G = 3.0 * K * (1.0 - 2.0 * nu) / (2.0 * (1.0 + nu))
        lam = K - 2.0 * G / 3.0
        sp, ss = jnp.sin(phi), jnp.sin(psi)
        q_phi = 6.0 * sp / (R3 * (3.0 + sp))
        k_phi = 6.0 * c * jnp.cos(phi) / (R3 * (3.0 + sp))
        q_psi = 6.0 * ss / (R3 * (3.0 + ss))

        # A.1-A.2 (Eq. 21) on the Kirchhoff stress J sigma (see Law): Hughes-Winget rotation R (exactly
        # orthogonal, = I + dw + O(dw^2)) + isotropic elastic increment, then sigma_trial = tau_trial / J_new
        J = state["J"]
        J_new = J * jnp.linalg.det(eye + dt * grad_v)
        dd = 0.5 * (grad_v + grad_v.T) * dt
        dw = 0.5 * (grad_v - grad_v.T) * dt
        R = eye + (dw + 0.5 * dw @ dw) / (1.0 + 0.125 * jnp.sum(dw * dw))
        trial = (R @ (J * state["sigma"]) @ R.T + lam * jnp.trace(dd) * eye + 2.0 * G * dd) / J_new
        # 2D plane strain (see Law): sigma_zz's trial with d_zz = 0 and R_zz = 1
        tzz = (J * state["sigma_zz"] + lam * jnp.trace(dd)) / J_new if ps else 0.0

        # A.3-A.4 over three components (2D: diag(trial, tzz))
        sm = (jnp.trace(trial) + tzz) / 3.0
        s = trial - sm * eye
        szz = tzz - sm if ps else 0.0
        ss2 = 0.5 * (jnp.sum(s * s) + szz * szz)
        pos = ss2 > 0.0
        tau = jnp.where(pos, jnp.sqrt(jnp.where(pos, ss2, 1.0)), 0.0)

        # A.5-A.11
        fs = tau - k_phi + q_phi * sm
        ft = sm - st
        tau_p = k_phi - q_phi * st
        alpha_p = jnp.sqrt(1.0 + q_phi * q_phi) - q_phi
        h = tau - tau_p - alpha_p * (sm - st)
        zone2 = jnp.where(ft < 0.0, fs > 0.0, h > 0.0)
        zone3 = (ft >= 0.0) & (h <= 0.0)

        # Zone II, A.12-A.16
        dl_s = fs / (G + K * q_phi * q_psi)
        sm2 = jnp.minimum(sm - K * q_psi * dl_s, st)   # A.12, capped at sigma_t (corner return, see reference)
        tau2 = k_phi - q_phi * sm2
        tpos = tau > 0.0
        ratio = jnp.where(tpos, tau2 / jnp.where(tpos, tau, 1.0), 0.0)
        sig2 = ratio * s + sm2 * eye
        de2 = dl_s * jnp.sqrt(1.0 / 3.0 + 2.0 / 9.0 * q_psi * q_psi)
        # Zone III, A.17-A.19, the wedge tau > tau_P returned to the corner (sigma_t, tau_P) (see reference)
        tau3 = jnp.minimum(tau, tau_p)
        ratio3 = jnp.where(tpos, tau3 / jnp.where(tpos, tau, 1.0), 0.0)
        sig3 = ratio3 * s + st * eye
        de3 = math.sqrt(2.0) / 3.0 * (sm - st) / K + (tau - tau3) / G * math.sqrt(1.0 / 3.0)

        new_sigma = jnp.where(zone2, sig2, jnp.where(zone3, sig3, trial))
        deps = jnp.where(zone2, de2, jnp.where(zone3, de3, 0.0))
        new_zz = (jnp.where(zone2, ratio * szz + sm2, jnp.where(zone3, ratio3 * szz + st, tzz)) if ps
                  else state["sigma_zz"])
        return {"J": J_new, "sigma": new_sigma, "sigma_zz": new_zz, "eps_p": state["eps_p"] + deps}

    return SimpleNamespace(kirchhoff=kirchhoff, update=update)
