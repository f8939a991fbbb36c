"""NumPy float64 reference of the compressible Neo-Hookean law (the conformance oracle)."""
from __future__ import annotations

import numpy as np


def _named(prm):
    """Parameters by name: a mapping, or an array in the declared order (E, nu)."""
    from mpmlab.core.interfaces import named_params

    from . import Law

    return named_params(prm, Law.param_names())


def lame(E, nu):
    return E / (2.0 * (1.0 + nu)), E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))


def first_piola(F, prm):
    """P = mu (F - F^-T) + lambda log(J) F^-T."""
    prm = _named(prm)
    mu, lam = lame(prm["E"], prm["nu"])
    FinvT = np.linalg.inv(F).T
    return mu * (F - FinvT) + lam * np.log(np.linalg.det(F)) * FinvT


def energy(F, prm):
    """psi = mu/2 (|F|^2 - d) - mu log J + lambda/2 (log J)^2 (vectorised over leading axes)."""
    F = np.asarray(F, dtype=float)
    prm = _named(prm)
    mu, lam = lame(prm["E"], prm["nu"])
    d = F.shape[-1]
    logJ = np.log(np.linalg.det(F))
    return 0.5 * mu * (np.sum(F * F, axis=(-2, -1)) - d) - mu * logJ + 0.5 * lam * logJ**2


def kirchhoff(state, prm, w=None):
    """tau = mu (F F^T - I) + lambda log(J) I."""
    F = state["F"]
    prm = _named(prm)
    mu, lam = lame(prm["E"], prm["nu"])
    eye = np.eye(len(F))
    return mu * (F @ F.T - eye) + lam * np.log(np.linalg.det(F)) * eye


def update(state, grad_v, dt, prm, w=None):
    F = state["F"]
    return {"F": (np.eye(len(F)) + dt * grad_v) @ F}
