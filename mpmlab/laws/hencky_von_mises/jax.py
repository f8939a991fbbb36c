"""JAX Hencky + von Mises (NCLaw Eqs. 17-19); per particle, vmapped by the stepper. The stress and the
safe-derivative spectral map are those of ``hencky_drucker_prager.jax``, plane strain in 2D as there."""
from __future__ import annotations

from types import SimpleNamespace

import jax
import jax.numpy as jnp

from ...backends.jax.linalg import lame, svd_rotations
from ...backends.jax.linalg import safe_norm, spectral
from ..hencky_drucker_prager.jax import (hencky_kirchhoff, hencky_kirchhoff_plane_strain, hencky_log,
                                        spectral_plane_strain, strains3)


def _excess(s, prm):
    """(eps, eps_hat, |eps_hat|, delta_gamma = |eps_hat| - tau_Y / (2 mu)) of NCLaw Eq. 18."""
    mu, _ = lame(prm["E"], prm["nu"])
    eps = hencky_log(s)
    eps_hat = eps - jnp.sum(eps) / s.shape[0]
    n = safe_norm(eps_hat)
    return eps, eps_hat, n, n - prm["yield_stress"] / (2.0 * mu)


def _returned_stretch(s, prm):
    """exp(eps - delta_gamma eps_hat / |eps_hat|) (Eq. 19, plastic case): tr(eps), hence det F, kept."""
    eps, eps_hat, n, dg = _excess(s, prm)
    return jnp.exp(eps - dg * eps_hat / jnp.where(n > 0.0, n, 1.0))


def _vm_return3(eps, tr, eps_hat, n, prm):
    """Eq. 19 with d = 3 (plane strain): eps - (n - k) eps_hat / n, k = tau_Y / (2 mu)."""
    mu, _ = lame(prm["E"], prm["nu"])
    return eps - (n - prm["yield_stress"] / (2.0 * mu)) * eps_hat / jnp.where(n > 0.0, n, 1.0)


def make(law, dim: int) -> SimpleNamespace:
    if dim == 2:   # plane strain (see the Law)
        def update(state, grad_v, dt, prm, w):
            F = (jnp.eye(dim, dtype=grad_v.dtype) + dt * grad_v) @ state["F"]
            ezz = state["eps_zz"]
            _, s, _ = svd_rotations(jax.lax.stop_gradient(F))
            q = jax.lax.stop_gradient(prm)
            mu, _ = lame(q["E"], q["nu"])
            n = strains3(s, jax.lax.stop_gradient(ezz))[3]
            plastic = n - q["yield_stress"] / (2.0 * mu) > 0.0
            Fn, zn = spectral_plane_strain(_vm_return3, F, ezz, prm)
            return {"F": jnp.where(plastic, Fn, F), "eps_zz": jnp.where(plastic, zn, ezz)}

        return SimpleNamespace(kirchhoff=hencky_kirchhoff_plane_strain, update=update)

    def update(state, grad_v, dt, prm, w):
        F = (jnp.eye(dim, dtype=grad_v.dtype) + dt * grad_v) @ state["F"]
        _, s, _ = svd_rotations(jax.lax.stop_gradient(F))
        dg = _excess(s, jax.lax.stop_gradient(prm))[3]
        return {"F": jnp.where(dg > 0.0, spectral(_returned_stretch, False, F, prm), F), "eps_zz": state["eps_zz"]}

    return SimpleNamespace(kirchhoff=hencky_kirchhoff, update=update)
