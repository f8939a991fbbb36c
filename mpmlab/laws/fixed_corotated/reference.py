"""NumPy float64 reference of the fixed corotated law (NCLaw Eq. 12), the conformance oracle."""
from __future__ import annotations

import numpy as np

from .._common import named_params
from .._linalg_np import lame, polar_rotation


def _named(prm):
    """Parameters by name (a mapping, or an array in the law's declared order)."""
    from . import Law

    return named_params(prm, Law.param_names())


def first_piola(F, prm):
    """P = 2 mu (F - R) + lambda J (J - 1) F^-T (NCLaw Eq. 12)."""
    prm = _named(prm)
    mu, lam = lame(prm["E"], prm["nu"])
    J = np.linalg.det(F)
    return 2.0 * mu * (F - polar_rotation(F)) + lam * J * (J - 1.0) * np.linalg.inv(F).T


def energy(F, prm):
    """Stored energy density per reference volume, psi = mu sum_i (s_i - 1)^2 + lambda/2 (J - 1)^2
    (Stomakhin et al. 2012), i.e. mu |F - R|^2 + lambda/2 (J - 1)^2, whose derivative is ``first_piola``.

    Vectorised: ``F`` [..., D, D] and ``prm`` [..., P] (or [P]) broadcast; the last singular value
    carries det(F)'s sign (as in ``svd_rotations``), so inverted elements are penalised.
    """
    F = np.asarray(F, dtype=float)
    prm = _named(prm)
    mu, lam = lame(prm["E"], prm["nu"])
    s = np.linalg.svd(F, compute_uv=False)
    J = np.linalg.det(F)
    s[..., -1] = np.where(J < 0.0, -s[..., -1], s[..., -1])
    return mu * np.sum((s - 1.0) ** 2, axis=-1) + 0.5 * lam * (J - 1.0) ** 2


def kirchhoff(state, prm, w=None):
    """tau = P F^T = 2 mu (F - R) F^T + lambda J (J - 1) I (no inverse needed, defined for J <= 0)."""
    prm = _named(prm)
    F = state["F"]
    mu, lam = lame(prm["E"], prm["nu"])
    J = np.linalg.det(F)
    return 2.0 * mu * (F - polar_rotation(F)) @ F.T + lam * J * (J - 1.0) * np.eye(len(F))


def project(F, prm):
    """Identity return map (NCLaw Eq. 13)."""
    prm = _named(prm)
    return F


def update(state, grad_v, dt, prm, w=None):
    """F <- (I + dt grad_v) F (NCLaw Alg. 3 step 3)."""
    prm = _named(prm)
    F = state["F"]
    return {"F": project((np.eye(len(F)) + dt * grad_v) @ F, prm)}
