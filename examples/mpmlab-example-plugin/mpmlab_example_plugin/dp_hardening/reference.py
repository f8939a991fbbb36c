"""NumPy float64 reference of Drucker-Prager with hardening (Klar et al. 2016, Sec. 7.3)."""
from __future__ import annotations

import math

import numpy as np

from mpmlab.laws._linalg_np import HENCKY_MIN_STRETCH
from mpmlab.laws.hencky_drucker_prager import reference as dp


def friction_angle(q, prm):
    """phi_F = h0 + (h1 q - h3) exp(-h2 q) [deg]."""
    return prm["h0"] + (prm["h1"] * q - prm["h3"]) * np.exp(-prm["h2"] * q)


def kirchhoff(state, prm, w=None):
    return dp.kirchhoff({"F": state["F"]}, {"E": prm["E"], "nu": prm["nu"], "friction_angle": 0.0})


def update(state, grad_v, dt, prm, w=None):
    F = state["F"]
    d = len(F)
    trial = (np.eye(d) + dt * grad_v) @ F
    phi = friction_angle(state["q"], prm)
    new = dp.project(trial, {"E": prm["E"], "nu": prm["nu"], "friction_angle": phi})
    eps = np.log(np.maximum(np.linalg.svd(trial, compute_uv=False), HENCKY_MIN_STRETCH))
    tr = eps.sum()
    eps_hat = eps - tr / d
    n = np.linalg.norm(eps_hat)
    E, nu = prm["E"], prm["nu"]
    mu, lam = E / (2.0 * (1.0 + nu)), E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
    sp = math.sin(math.radians(phi))
    alpha = math.sqrt(2.0 / 3.0) * 2.0 * sp / (3.0 - sp)
    dg = n + (d * lam + 2.0 * mu) / (2.0 * mu) * tr * alpha
    if tr > 0.0:
        dq = np.linalg.norm(eps)           # the tip: eps_new = 0
    elif dg > 0.0 and n > 0.0:
        dq = dg                            # the cone: eps_new = eps - dg eps_hat / n
    else:
        dq = 0.0
    return {"F": new, "q": state["q"] + dq}
