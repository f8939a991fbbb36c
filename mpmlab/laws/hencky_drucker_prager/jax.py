"""JAX Hencky + Drucker-Prager (NCLaw Eqs. 14-16); per particle, vmapped by the stepper.

Both the stress and the return map are spectral functions of F: U diag(g(s)) W^T with W = U (stress) or
W = V (return map). ``spectral`` gives them a custom JVP written with divided differences of g, because
the JVP of ``jnp.linalg.svd`` divides by s_i^2 - s_j^2 and is NaN at repeated singular values -- at
F = I, the rest state of every particle. The spectral derivative itself is well defined there.
"""
from __future__ import annotations

from types import SimpleNamespace

import jax
import jax.numpy as jnp

from ...backends.jax.linalg import HENCKY_MIN_STRETCH, lame, safe_norm, spectral, svd_rotations



def hencky_log(s):
    return jnp.log(jnp.maximum(s, HENCKY_MIN_STRETCH))


def hencky_principal_tau(s, prm):
    """Principal Kirchhoff stresses 2 mu eps + lambda tr(eps) (NCLaw Eq. 14)."""
    mu, lam = lame(prm["E"], prm["nu"])
    eps = hencky_log(s)
    return 2.0 * mu * eps + lam * jnp.sum(eps)


def hencky_kirchhoff(state, prm, w=None):
    """tau = U (2 mu eps + lambda tr(eps) I) U^T; NCLaw Eq. 14's "P" is this Kirchhoff stress (P = tau F^-T)."""
    return spectral(hencky_principal_tau, True, state["F"], prm)


def _cone(s, prm):
    """(eps, tr, eps_hat, |eps_hat|, delta_gamma) of NCLaw Eq. 15 with d = len(s)."""
    d = s.shape[0]
    mu, lam = lame(prm["E"], prm["nu"])
    sp = jnp.sin(jnp.deg2rad(prm["friction_angle"]))
    alpha = jnp.sqrt(2.0 / 3.0) * 2.0 * sp / (3.0 - sp)
    eps = hencky_log(s)
    tr = jnp.sum(eps)
    eps_hat = eps - tr / d
    n = safe_norm(eps_hat)
    dg = n + (d * lam + 2.0 * mu) / (2.0 * mu) * tr * alpha
    return eps, tr, eps_hat, n, dg


def _returned_stretch(s, prm):
    """New singular values on the plastic branches of Eq. 16: 1 (tip) if tr(eps) > 0, else the cone."""
    eps, tr, eps_hat, n, dg = _cone(s, prm)
    on_cone = jnp.exp(eps - dg * eps_hat / jnp.where(n > 0.0, n, 1.0))
    return jnp.where(tr > 0.0, jnp.ones_like(s), on_cone)


def project(F, prm):
    """The Drucker-Prager return map of a trial elastic F (NCLaw Eq. 16); ``prm`` needs E, nu and the
    friction angle [deg] (laws that compute the angle themselves, e.g. with hardening, call this)."""
    _, s, _ = svd_rotations(jax.lax.stop_gradient(F))
    _, tr, _, n, dg = _cone(s, jax.lax.stop_gradient(prm))
    plastic = (tr > 0.0) | ((dg > 0.0) & (n > 0.0))
    return jnp.where(plastic, spectral(_returned_stretch, False, F, prm), F)


def make(law, dim: int) -> SimpleNamespace:
    def update(state, grad_v, dt, prm, w):
        F = (jnp.eye(dim, dtype=grad_v.dtype) + dt * grad_v) @ state["F"]
        return {"F": project(F, prm)}

    return SimpleNamespace(kirchhoff=hencky_kirchhoff, update=update)
