"""NumPy float64 reference of Hencky elasticity + Drucker-Prager plasticity (NCLaw App. B, Eqs. 14-16;
Klar et al. 2016), the conformance oracle. One particle; the dimension d is taken from F.

2D is plane strain (issue 18): the state carries the elastic out-of-plane Hencky strain ``eps_zz`` and the
stress and return map act on the three principal strains (eps_1, eps_2, eps_zz) with the 3D formulas
(``principal_strains``, ``project_plane_strain``). ``project(F, prm)`` on a 2x2 F is the old 2D continuum
(d = 2), kept for plugins that call it (the example ``dp_hardening``)."""
from __future__ import annotations

import math

import numpy as np

from .._common import named_params
from .._linalg_np import HENCKY_MIN_STRETCH, hencky_strain, lame


def _named(prm):
    """Parameters by name (a mapping, or an array in the law's declared order)."""
    from . import Law

    return named_params(prm, Law.param_names())


def kirchhoff(state, prm, w=None):
    """tau = U (2 mu eps + lambda tr(eps) I) U^T with F = U diag(s) V^T, eps = log(s) (NCLaw Eq. 14).

    NCLaw Eq. 14 calls this "P", but it is the Kirchhoff stress (the St. Venant-Kirchhoff energy in the
    Hencky strain, Barbic & James 2005 / Klar 2016); the first Piola-Kirchhoff stress is P = tau F^-T.
    """
    prm = _named(prm)
    mu, lam = lame(prm["E"], prm["nu"])
    U, eps, _ = hencky_strain(state["F"])
    tr = eps.sum() + out_of_plane(state)               # plane strain: tr over (eps_1, eps_2, eps_zz)
    return (U * (2.0 * mu * eps + lam * tr)) @ U.T


def out_of_plane(state) -> float:
    """The elastic out-of-plane Hencky strain of a 2D (plane-strain) state, 0 in 3D or when absent."""
    return float(state.get("eps_zz", 0.0)) if len(state["F"]) == 2 else 0.0


def out_of_plane_stress(state, prm) -> float:
    """tau_zz = 2 mu eps_zz + lambda (eps_1 + eps_2 + eps_zz) of a 2D plane-strain state (Eq. 14 in the
    third principal direction e_z); sigma_zz = tau_zz / (det F e^eps_zz). A derived output, not state."""
    prm = _named(prm)
    mu, lam = lame(prm["E"], prm["nu"])
    _, eps, _ = hencky_strain(state["F"])
    ezz = out_of_plane(state)
    return 2.0 * mu * ezz + lam * (eps.sum() + ezz)


def first_piola(F, prm):
    """P = tau F^-T."""
    prm = _named(prm)
    return kirchhoff({"F": F}, prm) @ np.linalg.inv(F).T


def energy(F, prm):
    """Stored energy density per reference volume, psi = mu |eps|^2 + lambda/2 tr(eps)^2 (Hencky strain,
    the same clamp and sign convention as ``hencky_strain``); its derivative is ``first_piola``, which is
    why Eq. 14's U (2 mu eps + lambda tr(eps) I) U^T is the Kirchhoff stress P F^T.

    Vectorised: ``F`` [..., D, D] and ``prm`` [..., P] (or [P]) broadcast.
    """
    prm = _named(prm)
    F = np.asarray(F, dtype=float)
    prm = _named(prm)
    mu, lam = lame(prm["E"], prm["nu"])
    s = np.linalg.svd(F, compute_uv=False)
    s[..., -1] = np.where(np.linalg.det(F) < 0.0, -s[..., -1], s[..., -1])
    eps = np.log(np.maximum(s, HENCKY_MIN_STRETCH))
    return mu * np.sum(eps**2, axis=-1) + 0.5 * lam * np.sum(eps, axis=-1) ** 2


def alpha(friction_angle_deg):
    """Cone slope alpha = sqrt(2/3) 2 sin(phi) / (3 - sin(phi)) (NCLaw Eq. 15; 0.3266 at 30 deg)."""
    sp = math.sin(math.radians(friction_angle_deg))
    return math.sqrt(2.0 / 3.0) * 2.0 * sp / (3.0 - sp)


def project(F, prm):
    """Drucker-Prager return map in the Hencky strain (NCLaw Eqs. 15-16), written for d = dim(F).

    tr(eps) > 0: tension, to the cone tip U V^T. Otherwise, with eps_hat = eps - tr(eps)/d,
    delta_gamma = |eps_hat| + (d lambda + 2 mu) / (2 mu) tr(eps) alpha (Eq. 15 has d = 3); delta_gamma <= 0:
    elastic, F unchanged; else eps <- eps - delta_gamma eps_hat / |eps_hat|, which lands on the cone
    |dev tau| + alpha tr(tau) = 0 (Frobenius norm, dev and tr over d dimensions).
    """
    prm = _named(prm)
    d = len(F)
    mu, lam = lame(prm["E"], prm["nu"])
    U, eps, V = hencky_strain(F)
    tr = eps.sum()
    if tr > 0.0:
        return U @ V.T
    eps_hat = eps - tr / d
    n = np.linalg.norm(eps_hat)
    dg = n + (d * lam + 2.0 * mu) / (2.0 * mu) * tr * alpha(prm["friction_angle"])
    if dg <= 0.0 or n == 0.0:   # n == 0 implies dg <= 0 here; kept as an explicit division guard
        return F
    return (U * np.exp(eps - dg * eps_hat / n)) @ V.T


def cone_return(eps, prm):
    """Eqs. 15-16 on principal Hencky strains ``eps`` (d = len(eps)): the returned strains, or None if
    elastic. tr(eps) > 0: the tip (0); outside the cone: eps - delta_gamma eps_hat / |eps_hat|."""
    d = len(eps)
    mu, lam = lame(prm["E"], prm["nu"])
    tr = eps.sum()
    if tr > 0.0:
        return np.zeros_like(eps)
    eps_hat = eps - tr / d
    n = np.linalg.norm(eps_hat)
    dg = n + (d * lam + 2.0 * mu) / (2.0 * mu) * tr * alpha(prm["friction_angle"])
    if dg <= 0.0 or n == 0.0:
        return None
    return eps - dg * eps_hat / n


def principal_strains(F, ezz):
    """(U, (eps_1, eps_2, eps_zz), V) of a plane-strain state: F = U diag(e^eps_1, e^eps_2) V^T in the plane,
    e_z the third principal direction (F_zz^e = e^eps_zz)."""
    U, eps, V = hencky_strain(F)
    return U, np.append(eps, ezz), V


def project_plane_strain(F, ezz, prm):
    """The return map of a plane-strain trial (F in the plane, elastic eps_zz out of it) on the three
    principal strains with the 3D cone (d = 3 in Eq. 15): (F_new, eps_zz_new). The total F_zz stays 1;
    the plastic flow changes the elastic eps_zz (the tip sets it to 0)."""
    prm = _named(prm)
    U, eps, V = principal_strains(F, ezz)
    new = cone_return(eps, prm)
    if new is None:
        return F, ezz
    return (U * np.exp(new[:2])) @ V.T, float(new[2])


def update(state, grad_v, dt, prm, w=None):
    """F_trial = (I + dt grad_v) F (NCLaw Alg. 3 step 3), then the return map (2D: plane strain, the
    trial keeps the previous elastic eps_zz since d_zz = 0)."""
    prm = _named(prm)
    F = state["F"]
    trial = (np.eye(len(F)) + dt * grad_v) @ F
    if len(F) == 2:
        F_new, ezz = project_plane_strain(trial, out_of_plane(state), prm)
        return {"F": F_new, "eps_zz": np.asarray(ezz)}
    return {"F": project(trial, prm), "eps_zz": np.asarray(state.get("eps_zz", 0.0), dtype=float)}
