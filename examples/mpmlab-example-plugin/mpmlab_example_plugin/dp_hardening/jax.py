"""JAX Drucker-Prager with hardening: mpmlab's Hencky Drucker-Prager return map, called by name with
the friction angle of the hardening state (Klar et al. 2016, Sec. 7.3)."""
from __future__ import annotations

from types import SimpleNamespace

import jax.numpy as jnp

from mpmlab.backends.jax.linalg import HENCKY_MIN_STRETCH, safe_norm
from mpmlab.laws.hencky_drucker_prager.jax import hencky_kirchhoff, project


def make(law, dim: int) -> SimpleNamespace:
    def kirchhoff(state, prm, w):
        return hencky_kirchhoff({"F": state["F"]}, prm)

    def update(state, grad_v, dt, prm, w):
        F = (jnp.eye(dim, dtype=grad_v.dtype) + dt * grad_v) @ state["F"]
        q = state["q"]
        phi = prm["h0"] + (prm["h1"] * q - prm["h3"]) * jnp.exp(-prm["h2"] * q)
        new = project(F, {"E": prm["E"], "nu": prm["nu"], "friction_angle": phi})
        # dq = |eps_trial - eps_new| from the principal Hencky strains (ds = diag(U^T dF V): finite at
        # repeated singular values)
        eps = jnp.log(jnp.maximum(jnp.linalg.svd(F, compute_uv=False), HENCKY_MIN_STRETCH))
        tr = jnp.sum(eps)
        eps_hat = eps - tr / dim
        n = safe_norm(eps_hat)
        mu = prm["E"] / (2.0 * (1.0 + prm["nu"]))
        lam = prm["E"] * prm["nu"] / ((1.0 + prm["nu"]) * (1.0 - 2.0 * prm["nu"]))
        sp = jnp.sin(jnp.deg2rad(phi))
        alpha = jnp.sqrt(2.0 / 3.0) * 2.0 * sp / (3.0 - sp)
        dg = n + (dim * lam + 2.0 * mu) / (2.0 * mu) * tr * alpha
        dq = jnp.where(tr > 0.0, safe_norm(eps), jnp.where((dg > 0.0) & (n > 0.0), dg, 0.0))
        return {"F": new, "q": q + dq}

    return SimpleNamespace(kirchhoff=kirchhoff, update=update)
