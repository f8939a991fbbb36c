"""NumPy float64 reference of Hencky elasticity + Drucker-Prager plasticity (NCLaw App. B, Eqs. 14-16;
Klar et al. 2016), the conformance oracle. One particle; the dimension d is taken from F."""
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
    return (U * (2.0 * mu * eps + lam * eps.sum())) @ U.T


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


def update(state, grad_v, dt, prm, w=None):
    """F_trial = (I + dt grad_v) F (NCLaw Alg. 3 step 3), then the return map."""
    prm = _named(prm)
    F = state["F"]
    return {"F": project((np.eye(len(F)) + dt * grad_v) @ F, prm)}
