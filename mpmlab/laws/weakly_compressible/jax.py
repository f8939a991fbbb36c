"""JAX weakly compressible fluid (NCLaw Eqs. 20-21) on the J state; per particle, vmapped by the stepper."""
from __future__ import annotations

from types import SimpleNamespace

import jax.numpy as jnp


def make(dim: int) -> SimpleNamespace:
    def kirchhoff(state, prm):
        J = state["J"]
        return prm[0] * J * (J - 1.0) * jnp.eye(dim, dtype=J.dtype)

    def update(state, grad_v, dt, prm):
        return {"J": state["J"] * jnp.linalg.det(jnp.eye(dim, dtype=grad_v.dtype) + dt * grad_v)}

    return SimpleNamespace(kirchhoff=kirchhoff, update=update)
