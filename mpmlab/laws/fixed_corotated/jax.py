"""JAX fixed corotated law (NCLaw Eq. 12); per particle, vmapped by the stepper."""
from __future__ import annotations

from types import SimpleNamespace

import jax.numpy as jnp

from ...backends.jax.linalg import lame, polar_rotation


def make(law, dim: int) -> SimpleNamespace:
    def kirchhoff(state, prm, w):
        F = state["F"]
        eye = jnp.eye(dim, dtype=F.dtype)
        mu, lam = lame(prm["E"], prm["nu"])
        J = jnp.linalg.det(F)
        return 2.0 * mu * (F - polar_rotation(F)) @ F.T + lam * J * (J - 1.0) * eye

    def update(state, grad_v, dt, prm, w):
        F = state["F"]
        return {"F": (jnp.eye(dim, dtype=F.dtype) + dt * grad_v) @ F}

    return SimpleNamespace(kirchhoff=kirchhoff, update=update)
