"""JAX MLP hyperelastic law: the weights arrive un-batched (one copy for the whole group)."""
from __future__ import annotations

from types import SimpleNamespace

import jax.numpy as jnp


def make(law, dim: int) -> SimpleNamespace:
    def kirchhoff(state, prm, w):
        F = state["F"]
        eye = jnp.eye(dim, dtype=F.dtype)
        B = F @ F.T
        J = jnp.linalg.det(F)
        z = jnp.stack([jnp.trace(B) - dim, J - 1.0])
        a, b = w["W2"] @ jnp.tanh(w["W1"] @ z)
        c = w["c"]
        return prm["stress_scale"] * ((c[0] + b) * (B - eye) + (c[1] * (J - 1.0) + a) * eye)

    def update(state, grad_v, dt, prm, w):
        F = state["F"]
        return {"F": (jnp.eye(dim, dtype=F.dtype) + dt * grad_v) @ F}

    return SimpleNamespace(kirchhoff=kirchhoff, update=update)
