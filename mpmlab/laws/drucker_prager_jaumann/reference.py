"""NumPy float64 reference of the Jaumann-rate Drucker-Prager law (JAX-MPM Eq. 21, App. A); 2D is plane
strain (the out-of-plane stress sigma_zz is state; the return map runs on diag(sigma, sigma_zz))."""
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
    """(sigma_m, s, tau): mean stress tr/D (A.3), deviator, A.4 tau (2D runs it on the 3x3 plane-strain stress)."""
    d = len(sig)
    sm = np.trace(sig) / d
    s = sig - sm * np.eye(d)
    return sm, s, math.sqrt(0.5 * float(np.sum(s * s)))


def rotation_increment(dw):
    """Hughes-Winget (Cayley) rotation of the spin increment dw = skew(grad_v) dt:
    R = (I - dw/2)^-1 (I + dw/2) = I + (dw + dw dw / 2) / (1 + |w|^2 / 4), |w|^2 = dw:dw / 2 (the axial
    vector's squared norm; the closed form holds in 2D and 3D). R is orthogonal for any dw, and
    R = I + dw + O(dw^2): A.2's first-order rotation sigma + sigma dw^T + dw sigma, made exact."""
    d = len(dw)
    return np.eye(d) + (dw + 0.5 * dw @ dw) / (1.0 + 0.125 * float(np.sum(dw * dw)))


def jaumann_trial(sigma, grad_v, dt, prm, J=1.0):
    """Trial Cauchy stress of A.1-A.2 (Eq. 21), integrated on the Kirchhoff stress tau = J sigma:

        tau_trial = R (J sigma) R^T + lambda tr(dd) I + 2 G dd,   sigma_trial = tau_trial / J_new,

    dd = sym(grad_v) dt, R = rotation_increment(skew(grad_v) dt), J_new = J det(I + dt grad_v). At J = 1 and
    to first order in dt this is A.1-A.2 (the differences are O(dt^2) rotation terms and sigma tr(dd), a
    relative O(sigma / K) change); see the Law docstring for why the elastic increment is on tau."""
    prm = _named(prm)
    G, lam = moduli(prm["bulk_modulus"], prm["nu"])
    d = len(sigma)
    dd = 0.5 * (grad_v + grad_v.T) * dt
    R = rotation_increment(0.5 * (grad_v - grad_v.T) * dt)
    J_new = J * np.linalg.det(np.eye(d) + dt * grad_v)
    tau = R @ (J * sigma) @ R.T + lam * np.trace(dd) * np.eye(d) + 2.0 * G * dd
    return tau / J_new


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
    # Zone III: A.17 sets sigma_m = sigma_t and keeps the deviator; where the trial lies in the wedge
    # tau_P < tau <= tau_P + alpha_P (sigma_m - sigma_t) (h <= 0 admits it) that leaves f_s = tau - tau_P > 0,
    # a stress outside the cone (c = sigma_t = 0: any tau > 0 at sigma_m = 0, i.e. a tensile principal
    # stress). mpmlab returns those to the corner (sigma_t, tau_P), the deviator scaled as in A.14.
    dl = (sm - st) / K                                              # A.19
    tau_p = k_phi - q_phi * st                                      # A.8
    tau_new = min(tau, tau_p)
    ratio = tau_new / tau if tau > 0.0 else 0.0
    dl_s = (tau - tau_new) / G                                      # deviatoric part of the corner return
    return ratio * s + st * np.eye(d), math.sqrt(2.0) / 3.0 * dl + dl_s * math.sqrt(1.0 / 3.0)  # A.17-18 (+A.15)


def kirchhoff(state, prm, w=None):
    """tau = J sigma."""
    prm = _named(prm)
    return state["J"] * state["sigma"]


def plane_strain_trial(sigma_zz, grad_v, dt, prm, J=1.0):
    """The out-of-plane trial Cauchy stress of a plane-strain state (2D): A.1-A.2 on tau_zz = J sigma_zz with
    d_zz = 0 and no spin coupling (the 2D spin has no z components, R_zz = 1):
    tau_zz_trial = J sigma_zz + lambda tr(dd), sigma_zz_trial = tau_zz_trial / J_new."""
    prm = _named(prm)
    _, lam = moduli(prm["bulk_modulus"], prm["nu"])
    dd = 0.5 * (grad_v + grad_v.T) * dt
    J_new = J * np.linalg.det(np.eye(len(grad_v)) + dt * grad_v)
    return (J * sigma_zz + lam * np.trace(dd)) / J_new


def embed(sigma, sigma_zz):
    """The 3x3 stress diag(sigma, sigma_zz) of a plane-strain state."""
    out = np.zeros((3, 3))
    out[:2, :2] = sigma
    out[2, 2] = sigma_zz
    return out


def update(state, grad_v, dt, prm, w=None):
    """Eq. 21 / App. A: Jaumann trial stress (on tau = J sigma), three-zone return map, J <- J det(I + dt grad_v).
    2D is plane strain: the return map runs on the 3x3 trial diag(sigma_trial, sigma_zz_trial) (A.3's tr/3)."""
    prm = _named(prm)
    trial = jaumann_trial(state["sigma"], grad_v, dt, prm, state["J"])
    J = state["J"] * np.linalg.det(np.eye(len(grad_v)) + dt * grad_v)
    szz = np.asarray(state.get("sigma_zz", 0.0), dtype=float)
    if len(grad_v) == 2:
        s3, deps = return_map(embed(trial, plane_strain_trial(float(szz), grad_v, dt, prm, state["J"])), prm)
        return {"J": J, "sigma": s3[:2, :2], "sigma_zz": np.asarray(s3[2, 2]), "eps_p": state["eps_p"] + deps}
    sigma, deps = return_map(trial, prm)
    return {"J": J, "sigma": sigma, "sigma_zz": szz, "eps_p": state["eps_p"] + deps}
