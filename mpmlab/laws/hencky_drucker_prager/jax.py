"""JAX Hencky + Drucker-Prager (NCLaw Eqs. 14-16); per particle, vmapped by the stepper.

Both the stress and the return map are spectral functions of F: U diag(g(s)) W^T with W = U (stress) or
W = V (return map). ``spectral`` gives them a custom JVP written with divided differences of g, because
the JVP of ``jnp.linalg.svd`` divides by s_i^2 - s_j^2 and is NaN at repeated singular values -- at
F = I, the rest state of every particle. The spectral derivative itself is well defined there.

2D is plane strain (see the Law): the stress and the return map take the elastic out-of-plane strain
eps_zz as a parameter of g (``spectral``'s p, so its derivative flows), the return runs on three principal
strains, and the new eps_zz = h(s, eps_zz) is read off the spectral map U diag(h, h) U^T = h I (an isotropic
g whose rows are equal; its derivative is the exact one of h through the singular values).
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


# ---- plane strain (2D): three principal strains (eps_1, eps_2, eps_zz), the 3D formulas ----
def _ps_principal_tau(s, p):
    """In-plane principal Kirchhoff stresses 2 mu eps_i + lambda (eps_1 + eps_2 + eps_zz) (Eq. 14, plane strain)."""
    prm, ezz = p
    mu, lam = lame(prm["E"], prm["nu"])
    eps = hencky_log(s)
    return 2.0 * mu * eps + lam * (jnp.sum(eps) + ezz)


def hencky_kirchhoff_plane_strain(state, prm, w=None):
    """The in-plane Kirchhoff stress of a plane-strain state (F, eps_zz)."""
    return spectral(_ps_principal_tau, True, state["F"], (prm, state["eps_zz"]))


def strains3(s, ezz):
    """(eps_1, eps_2, eps_zz), tr over three, the 3D deviator and its norm."""
    eps = jnp.concatenate([hencky_log(s), jnp.reshape(ezz, (1,)).astype(s.dtype)])
    tr = jnp.sum(eps)
    eps_hat = eps - tr / 3.0
    return eps, tr, eps_hat, safe_norm(eps_hat)


def returned_strains_plane_strain(return3, s, p):
    """exp of the in-plane returned strains and the returned eps_zz of ``return3(eps, tr, eps_hat, n, prm)
    -> eps_new`` [3] (NCLaw Eq. 16 / 19 with d = 3)."""
    prm, ezz = p
    eps, tr, eps_hat, n = strains3(s, ezz)
    return return3(eps, tr, eps_hat, n, prm)


def spectral_plane_strain(return3, F, ezz, prm):
    """(U diag(exp(eps_new[:2])) V^T, eps_new[2]) with derivatives through the spectral maps (module doc)."""
    p = (prm, ezz)
    Fn = spectral(lambda s, q: jnp.exp(returned_strains_plane_strain(return3, s, q)[:2]), False, F, p)
    Z = spectral(lambda s, q: jnp.full((2,), returned_strains_plane_strain(return3, s, q)[2]), True, F, p)
    return Fn, 0.5 * (Z[0, 0] + Z[1, 1])


def _dp_return3(eps, tr, eps_hat, n, prm):
    """Eq. 16 with d = 3: the tip (0) if tr > 0, else the cone eps - dg eps_hat / n (dg of Eq. 15)."""
    mu, lam = lame(prm["E"], prm["nu"])
    sp = jnp.sin(jnp.deg2rad(prm["friction_angle"]))
    alpha = jnp.sqrt(2.0 / 3.0) * 2.0 * sp / (3.0 - sp)
    dg = n + (3.0 * lam + 2.0 * mu) / (2.0 * mu) * tr * alpha
    on_cone = eps - dg * eps_hat / jnp.where(n > 0.0, n, 1.0)
    return jnp.where(tr > 0.0, jnp.zeros_like(eps), on_cone)


def project_plane_strain(F, ezz, prm):
    """The Drucker-Prager return map of a plane-strain trial (F, eps_zz): (F_new, eps_zz_new)."""
    _, s, _ = svd_rotations(jax.lax.stop_gradient(F))
    q = jax.lax.stop_gradient(prm)
    mu, lam = lame(q["E"], q["nu"])
    sp = jnp.sin(jnp.deg2rad(q["friction_angle"]))
    alpha = jnp.sqrt(2.0 / 3.0) * 2.0 * sp / (3.0 - sp)
    _, tr, _, n = strains3(s, jax.lax.stop_gradient(ezz))
    dg = n + (3.0 * lam + 2.0 * mu) / (2.0 * mu) * tr * alpha
    plastic = (tr > 0.0) | ((dg > 0.0) & (n > 0.0))
    Fn, zn = spectral_plane_strain(_dp_return3, F, ezz, prm)
    return jnp.where(plastic, Fn, F), jnp.where(plastic, zn, ezz)


def make(law, dim: int) -> SimpleNamespace:
    if dim == 2:
        def update(state, grad_v, dt, prm, w):
            F = (jnp.eye(dim, dtype=grad_v.dtype) + dt * grad_v) @ state["F"]
            F, ezz = project_plane_strain(F, state["eps_zz"], prm)
            return {"F": F, "eps_zz": ezz}

        return SimpleNamespace(kirchhoff=hencky_kirchhoff_plane_strain, update=update)

    def update(state, grad_v, dt, prm, w):
        F = (jnp.eye(dim, dtype=grad_v.dtype) + dt * grad_v) @ state["F"]
        return {"F": project(F, prm), "eps_zz": state["eps_zz"]}

    return SimpleNamespace(kirchhoff=hencky_kirchhoff, update=update)
