"""JAX conveyor floor: a pure function of the grid velocity and the belt speed."""
from __future__ import annotations

from types import SimpleNamespace

import jax.numpy as jnp

from mpmlab.backends.boundary_geometry import wall_masks


def conveyor(b, scene, dtype):
    mask = jnp.asarray(wall_masks(scene, b.thickness)["y-"])[:, None]

    def apply(v, node_x, m, t, params):
        vy = jnp.where(v[:, 1] < 0.0, 0.0, v[:, 1])           # no motion into the floor (kept at v_y == 0)
        belt = jnp.concatenate([jnp.broadcast_to(params["speed"], v[:, :1].shape), vy[:, None], v[:, 2:]], axis=1)
        return jnp.where(mask, belt, v)

    return SimpleNamespace(params={"speed": jnp.asarray([b.speed], dtype)}, apply=apply)
