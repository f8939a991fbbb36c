"""JAX weakly compressible fluid (NCLaw Eqs. 20-21) on the J state; per particle, vmapped by the stepper."""
from __future__ import annotations

from types import SimpleNamespace

import jax.numpy as jnp


def make(law, dim: int) -> SimpleNamespace:
    def kirchhoff(state, prm, w):
        J = state["J"]
        return prm["bulk_modulus"] * J * (J - 1.0) * jnp.eye(dim, dtype=J.dtype)

    def update(state, grad_v, dt, prm, w):
        return {"J": state["J"] * jnp.linalg.det(jnp.eye(dim, dtype=grad_v.dtype) + dt * grad_v)}

    return SimpleNamespace(kirchhoff=kirchhoff, update=update)
