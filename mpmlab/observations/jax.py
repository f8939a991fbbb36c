"""JAX implementations of the observation operators (pure functions of the stepper state)."""
from __future__ import annotations

from types import SimpleNamespace

import jax.numpy as jnp


def lagrangian(obs, stepper):
    idx = jnp.asarray(obs.indices(stepper.particles.count))
    q = obs.quantity

    def fn(state):
        return state[q][idx]                                       # JAX-MPM Eq. 26

    return SimpleNamespace(fn=fn, shape=(int(idx.shape[0]), stepper.dim))


def eulerian(obs, stepper):
    c = jnp.asarray(obs.centers_array(stepper.dim), stepper.dtype)
    h = obs.half_size
    q = obs.quantity

    def fn(state):
        x = state["x"]
        # membership is an indicator (no gradient through x), Eq. 27
        inside = jnp.all(jnp.abs(x[None, :, :] - c[:, None, :]) <= h, axis=-1).astype(x.dtype)   # [L, N]
        cnt = inside.sum(axis=1)
        return (inside @ state[q]) / jnp.maximum(cnt, 1.0)[:, None]

    return SimpleNamespace(fn=fn, shape=(int(c.shape[0]), stepper.dim))
