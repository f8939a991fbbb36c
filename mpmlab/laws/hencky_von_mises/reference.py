"""NumPy float64 reference of Hencky elasticity + von Mises plasticity (NCLaw App. B, Eqs. 17-19), the
conformance oracle. One particle; the dimension d is taken from F. The elastic part (Eq. 17) is the
Hencky stress of ``hencky_drucker_prager`` (Eq. 14)."""
from __future__ import annotations

import numpy as np

from .._common import named_params
from .._linalg_np import hencky_strain, lame
from ..hencky_drucker_prager.reference import energy, first_piola, kirchhoff  # noqa: F401  (same elasticity, Eq. 17)


def _named(prm):
    """Parameters by name (a mapping, or an array in the law's declared order)."""
    from . import Law

    return named_params(prm, Law.param_names())


def project(F, prm):
    """Von Mises return map in the Hencky strain (NCLaw Eqs. 18-19).

    eps_hat = eps - tr(eps)/d; delta_gamma = |eps_hat| - tau_Y / (2 mu); if > 0,
    eps <- eps - delta_gamma eps_hat / |eps_hat|: the deviator shrinks to |dev tau| = 2 mu |eps_hat| = tau_Y
    (Frobenius norm), tr(eps) is kept, so det F is preserved (isochoric).
    """
    prm = _named(prm)
    d = len(F)
    mu, _ = lame(prm["E"], prm["nu"])
    U, eps, V = hencky_strain(F)
    eps_hat = eps - eps.sum() / d
    n = np.linalg.norm(eps_hat)
    dg = n - prm["yield_stress"] / (2.0 * mu)
    if dg <= 0.0:          # also covers n == 0 (tau_Y > 0)
        return F
    return (U * np.exp(eps - dg * eps_hat / n)) @ V.T


def update(state, grad_v, dt, prm, w=None):
    """F_trial = (I + dt grad_v) F (NCLaw Alg. 3 step 3), then the return map."""
    prm = _named(prm)
    F = state["F"]
    return {"F": project((np.eye(len(F)) + dt * grad_v) @ F, prm)}
