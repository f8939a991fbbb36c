"""NumPy float64 reference of the fixed corotated law (NCLaw Eq. 12), the conformance oracle."""
from __future__ import annotations

import numpy as np

from .._linalg_np import lame, polar_rotation


def first_piola(F, prm):
    """P = 2 mu (F - R) + lambda J (J - 1) F^-T (NCLaw Eq. 12)."""
    mu, lam = lame(prm[0], prm[1])
    J = np.linalg.det(F)
    return 2.0 * mu * (F - polar_rotation(F)) + lam * J * (J - 1.0) * np.linalg.inv(F).T


def kirchhoff(state, prm):
    """tau = P F^T = 2 mu (F - R) F^T + lambda J (J - 1) I (no inverse needed, defined for J <= 0)."""
    F = state["F"]
    mu, lam = lame(prm[0], prm[1])
    J = np.linalg.det(F)
    return 2.0 * mu * (F - polar_rotation(F)) @ F.T + lam * J * (J - 1.0) * np.eye(len(F))


def project(F, prm):
    """Identity return map (NCLaw Eq. 13)."""
    return F


def update(state, grad_v, dt, prm):
    """F <- (I + dt grad_v) F (NCLaw Alg. 3 step 3)."""
    F = state["F"]
    return {"F": project((np.eye(len(F)) + dt * grad_v) @ F, prm)}
