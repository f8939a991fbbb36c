"""NumPy float64 reference of the weakly compressible Newtonian fluid (JAX-MPM Eqs. 19-20)."""
from __future__ import annotations

import numpy as np


def pressure(J, prm):
    """Eq. 20: p = c^2 (rho - rho0), rho = rho0 / J, with the tension cut-off p >= min_pressure (prm[3])."""
    c, rho0, pmin = prm[0], prm[2], prm[3]
    return np.maximum(c * c * (rho0 / J - rho0), pmin)


def cauchy(J, grad_v, prm):
    """Eq. 19 with the strain rate D = sym(grad_v): sigma = -p I + 2 mu (D - tr(D)/3 I).

    (The paper writes the increment D dt, dimensionally inconsistent; 1/3 kept in 2D too.)
    """
    mu = prm[1]
    eye = np.eye(len(grad_v))
    D = 0.5 * (grad_v + grad_v.T)
    return -pressure(J, prm) * eye + 2.0 * mu * (D - np.trace(D) / 3.0 * eye)


def kirchhoff(state, prm):
    """tau = J sigma."""
    return state["J"] * state["sigma"]


def update(state, grad_v, dt, prm):
    """J <- J det(I + dt grad_v); sigma from Eqs. 19-20 at the new J and the current rate."""
    J = state["J"] * np.linalg.det(np.eye(len(grad_v)) + dt * grad_v)
    return {"J": J, "sigma": cauchy(J, grad_v, prm)}
