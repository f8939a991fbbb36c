"""NumPy float64 reference of the Jaumann-rate Drucker-Prager law (JAX-MPM Eq. 21, App. A)."""
from __future__ import annotations

import math

import numpy as np

from .._common import named_params

DEG = math.pi / 180.0


def _named(prm):
    """Parameters by name (a mapping, or an array in the law's declared order)."""
    from . import Law

    return named_params(prm, Law.param_names())


def moduli(K, nu):
    """(G, lambda) from the bulk modulus and Poisson ratio."""
    G = 3.0 * K * (1.0 - 2.0 * nu) / (2.0 * (1.0 + nu))
    return G, K - 2.0 * G / 3.0


def cone_constants(phi_deg, psi_deg, c):
    """(q_phi, k_phi, q_psi) of App. A (angles in degrees)."""
    sp, cp, ss = math.sin(phi_deg * DEG), math.cos(phi_deg * DEG), math.sin(psi_deg * DEG)
    r3 = math.sqrt(3.0)
    return 6.0 * sp / (r3 * (3.0 + sp)), 6.0 * c * cp / (r3 * (3.0 + sp)), 6.0 * ss / (r3 * (3.0 + ss))


def invariants(sig):
    """(sigma_m, s, tau): mean stress (tr/D: tr/3 in 3D, tr/2 for the 2D continuum), deviator, A.4 tau."""
    d = len(sig)
    sm = np.trace(sig) / d
    s = sig - sm * np.eye(d)
    return sm, s, math.sqrt(0.5 * float(np.sum(s * s)))


def jaumann_trial(sigma, grad_v, dt, prm):
    """A.1-A.2: sigma_R = sigma + sigma dw^T + dw sigma, trial = sigma_R + lambda tr(dd) I + 2 G dd."""
    prm = _named(prm)
    G, lam = moduli(prm["bulk_modulus"], prm["nu"])
    d = len(sigma)
    dd = 0.5 * (grad_v + grad_v.T) * dt
    dw = 0.5 * (grad_v - grad_v.T) * dt
    # (A.2) sigma_ik dw_jk = (sigma dw^T)_ij, sigma_jk dw_ik = (dw sigma^T)_ij = (dw sigma)_ij
    sigma_r = sigma + sigma @ dw.T + dw @ sigma
    return sigma_r + lam * np.trace(dd) * np.eye(d) + 2.0 * G * dd


def zone(sm, tau, prm):
    """1, 2 or 3 (A.9-A.11) for trial invariants (sm, tau)."""
    prm = _named(prm)
    q_phi, k_phi, _ = cone_constants(prm["friction_angle"], prm["dilation_angle"], prm["cohesion"])
    st = prm["tensile_strength"]
    fs = tau - k_phi + q_phi * sm                                   # A.5
    ft = sm - st                                                    # A.6
    tau_p = k_phi - q_phi * st                                      # A.8
    alpha_p = math.sqrt(1.0 + q_phi * q_phi) - q_phi
    h = tau - tau_p - alpha_p * (sm - st)                           # A.7
    if ft < 0.0:
        return 1 if fs <= 0.0 else 2
    return 2 if h > 0.0 else 3


def return_map(trial, prm):
    """A.3-A.19: (sigma, delta eps_eq) from the trial stress."""
    prm = _named(prm)
    K = prm["bulk_modulus"]
    G, _ = moduli(prm["bulk_modulus"], prm["nu"])
    q_phi, k_phi, q_psi = cone_constants(prm["friction_angle"], prm["dilation_angle"], prm["cohesion"])
    st = prm["tensile_strength"]
    d = len(trial)
    sm, s, tau = invariants(trial)
    z = zone(sm, tau, prm)
    if z == 1:
        return trial, 0.0
    if z == 2:
        fs = tau - k_phi + q_phi * sm
        dl = fs / (G + K * q_phi * q_psi)                           # A.16
        # A.12, capped at the tension cutoff: a shear return past sigma_t (possible from the h > 0, f_t >= 0
        # branch beyond the apex) goes to the corner (sigma_t, tau_P) instead of flipping the deviator
        sm_new = min(sm - K * q_psi * dl, st)
        tau_new = k_phi - q_phi * sm_new                            # A.13
        ratio = tau_new / tau if tau > 0.0 else 0.0
        return ratio * s + sm_new * np.eye(d), dl * math.sqrt(1.0 / 3.0 + 2.0 / 9.0 * q_psi * q_psi)  # A.14-15
    dl = (sm - st) / K                                              # A.19
    return trial + (st - sm) * np.eye(d), math.sqrt(2.0) / 3.0 * dl  # A.17-18


def kirchhoff(state, prm, w=None):
    """tau = J sigma."""
    prm = _named(prm)
    return state["J"] * state["sigma"]


def update(state, grad_v, dt, prm, w=None):
    """Eq. 21 / App. A: Jaumann trial stress, three-zone return map, J <- J det(I + dt grad_v)."""
    prm = _named(prm)
    sigma, deps = return_map(jaumann_trial(state["sigma"], grad_v, dt, prm), prm)
    J = state["J"] * np.linalg.det(np.eye(len(grad_v)) + dt * grad_v)
    return {"J": J, "sigma": sigma, "eps_p": state["eps_p"] + deps}
