"""NumPy float64 reference of Hencky elasticity + von Mises plasticity (NCLaw App. B, Eqs. 17-19), the
conformance oracle. One particle; the dimension d is taken from F. The elastic part (Eq. 17) is the
Hencky stress of ``hencky_drucker_prager`` (Eq. 14), plane strain in 2D as there: the state carries the
elastic out-of-plane strain eps_zz and the return runs on (eps_1, eps_2, eps_zz) with d = 3."""
from __future__ import annotations

import numpy as np

from .._common import named_params
from .._linalg_np import hencky_strain, lame
from ..hencky_drucker_prager.reference import (energy, first_piola, kirchhoff, out_of_plane,  # noqa: F401  (Eq. 17)
                                              out_of_plane_stress, principal_strains)


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


def mises_return(eps, prm):
    """Eqs. 18-19 on principal Hencky strains ``eps`` (d = len(eps)): the returned strains, or None if elastic."""
    mu, _ = lame(prm["E"], prm["nu"])
    eps_hat = eps - eps.sum() / len(eps)
    n = np.linalg.norm(eps_hat)
    dg = n - prm["yield_stress"] / (2.0 * mu)
    if dg <= 0.0:
        return None
    return eps - dg * eps_hat / n


def project_plane_strain(F, ezz, prm):
    """The von Mises return of a plane-strain trial on (eps_1, eps_2, eps_zz) (d = 3): (F_new, eps_zz_new)."""
    prm = _named(prm)
    U, eps, V = principal_strains(F, ezz)
    new = mises_return(eps, prm)
    if new is None:
        return F, ezz
    return (U * np.exp(new[:2])) @ V.T, float(new[2])


def update(state, grad_v, dt, prm, w=None):
    """F_trial = (I + dt grad_v) F (NCLaw Alg. 3 step 3), then the return map (2D: plane strain, the trial
    keeps the previous elastic eps_zz since d_zz = 0)."""
    prm = _named(prm)
    F = state["F"]
    trial = (np.eye(len(F)) + dt * grad_v) @ F
    if len(F) == 2:
        F_new, ezz = project_plane_strain(trial, out_of_plane(state), prm)
        return {"F": F_new, "eps_zz": np.asarray(ezz)}
    return {"F": project(trial, prm), "eps_zz": np.asarray(state.get("eps_zz", 0.0), dtype=float)}
