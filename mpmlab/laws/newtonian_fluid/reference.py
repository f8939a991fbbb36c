"""NumPy float64 reference of the weakly compressible Newtonian fluid (JAX-MPM Eqs. 19-20)."""
from __future__ import annotations

import numpy as np

from .._common import named_params


def _named(prm):
    """Parameters by name (a mapping, or an array in the law's declared order)."""
    from . import Law

    return named_params(prm, Law.param_names())


def pressure(J, prm):
    """Eq. 20: p = c^2 (rho - rho0), rho = rho0 / J, with the tension cut-off p >= min_pressure (prm["min_pressure"])."""
    prm = _named(prm)
    c, rho0, pmin = prm["sound_speed"], prm["rest_density"], prm["min_pressure"]
    return np.maximum(c * c * (rho0 / J - rho0), pmin)


def cauchy(J, grad_v, prm):
    """Eq. 19 with the strain rate D = sym(grad_v): sigma = -p I + 2 mu (D - tr(D)/3 I).

    (The paper writes the increment D dt, dimensionally inconsistent; 1/3 kept in 2D too.)
    """
    prm = _named(prm)
    mu = prm["viscosity"]
    eye = np.eye(len(grad_v))
    D = 0.5 * (grad_v + grad_v.T)
    return -pressure(J, prm) * eye + 2.0 * mu * (D - np.trace(D) / 3.0 * eye)


def kirchhoff(state, prm, w=None):
    """tau = J sigma."""
    prm = _named(prm)
    return state["J"] * state["sigma"]


def update(state, grad_v, dt, prm, w=None):
    """J <- J det(I + dt grad_v); sigma from Eqs. 19-20 at the new J and the current rate."""
    prm = _named(prm)
    J = state["J"] * np.linalg.det(np.eye(len(grad_v)) + dt * grad_v)
    return {"J": J, "sigma": cauchy(J, grad_v, prm)}
