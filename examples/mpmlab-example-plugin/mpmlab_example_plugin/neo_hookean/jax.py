"""JAX compressible Neo-Hookean law: per-particle pure functions, vmapped by mpmlab's JAX stepper."""
from __future__ import annotations

from types import SimpleNamespace

import jax.numpy as jnp


def make(law, dim: int) -> SimpleNamespace:
    def kirchhoff(state, prm, w):
        F = state["F"]
        E, nu = prm["E"], prm["nu"]
        mu = E / (2.0 * (1.0 + nu))
        lam = E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
        eye = jnp.eye(dim, dtype=F.dtype)
        # log of |J| keeps the function finite if an element inverts; mpmlab's guard reports J <= 0
        logJ = jnp.log(jnp.abs(jnp.linalg.det(F)))
        return mu * (F @ F.T - eye) + lam * logJ * eye

    def update(state, grad_v, dt, prm, w):
        F = state["F"]
        return {"F": (jnp.eye(dim, dtype=F.dtype) + dt * grad_v) @ F}

    return SimpleNamespace(kirchhoff=kirchhoff, update=update)
