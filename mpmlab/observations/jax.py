"""JAX implementations of the observation operators (pure functions of the stepper state)."""
from __future__ import annotations

from types import SimpleNamespace

import jax.numpy as jnp
import numpy as np


def lagrangian(obs, stepper):
    # NumPy constants: the factory may run inside a jax trace (first call under jit); jnp constants made
    # there would be tracers that leak into the cached function
    idx = obs.indices(stepper.particles.count)
    q = obs.quantity

    def fn(state):
        return state[q][idx]                                       # JAX-MPM Eq. 26

    return SimpleNamespace(fn=fn, shape=(int(idx.shape[0]), stepper.dim))


def eulerian(obs, stepper):
    c = np.asarray(obs.centers_array(stepper.dim), dtype=np.dtype(stepper.dtype))
    h = obs.half_size
    q = obs.quantity

    def fn(state):
        x = state["x"]
        # membership is an indicator (no gradient through x), Eq. 27
        inside = jnp.all(jnp.abs(x[None, :, :] - c[:, None, :]) <= h, axis=-1).astype(x.dtype)   # [L, N]
        cnt = inside.sum(axis=1)
        return (inside @ state[q]) / jnp.maximum(cnt, 1.0)[:, None]

    return SimpleNamespace(fn=fn, shape=(int(c.shape[0]), stepper.dim))


def particle_state(obs, stepper):
    idx = obs.indices(stepper.particles.count)
    D, q = stepper.dim, obs.quantity
    if q == "F":
        missing = [g.law.name for g in stepper.groups if "F" not in g.law.state_fields]
        if missing:
            from ..core.errors import ConfigError
            raise ConfigError(f"observation 'particle_state': quantity F needs every law to carry F; {missing} do not.")
    if q == "C" and not stepper.transfer.needs_affine:
        from ..core.errors import ConfigError
        raise ConfigError(f"observation 'particle_state': transfer '{stepper.transfer.name}' carries no C.")

    def fn(state):
        a = state["C"] if q == "C" else jnp.concatenate([st["F"] for st in state["law"]], axis=0)
        return a[idx].reshape(len(idx), D * D)

    return SimpleNamespace(fn=fn, shape=(int(idx.shape[0]), D * D))
