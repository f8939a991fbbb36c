"""JAX implementation of ``body_force`` (``mpmlab.boundaries.body_force``): the field's closed form
evaluated with ``jax.numpy`` at the particles' reference positions (or, for a field that declares
``position = "current"``, at their positions at the start of the step), times the particle mass.

The field parameters are a differentiable array in ``params["boundary"]``; the reference positions
are a constant of the compiled step (they never change)."""
from __future__ import annotations

from types import SimpleNamespace

import jax.numpy as jnp


def body_force(b, scene, dtype):
    P = scene.particles()
    D = scene.dim
    X0 = jnp.asarray(P.x, dtype)
    field, options = b.field_impl, b.options
    current = b.position == "current"
    mask = None if b.bodies is None else jnp.asarray(b.mask(scene), dtype)[:, None]
    t0, t1 = b.t_start, b.t_end

    def particle_force(x, mass, t, params):
        f = mass[:, None] * field.evaluate(jnp, x if current else X0, t, params["field"], D, options).astype(dtype)
        if mask is not None:
            f = f * mask
        if t0 > 0 or t1 < float("inf"):
            f = jnp.where((t >= t0) & (t < t1), f, 0.0)
        return f

    return SimpleNamespace(params={"field": jnp.asarray(b.packed(D), dtype)}, particle_force=particle_force)
