"""Warp conveyor floor: the fast in-place kernel over the floor nodes and, as ``tape()``, the
out-of-place kernel over every node that the differentiable path records (new vectors are built, never
a component overwritten, so Warp's adjoint is exact)."""
from functools import lru_cache
from types import SimpleNamespace

import numpy as np
import warp as wp

from mpmlab.backends.boundary_geometry import wall_masks
from mpmlab.backends.warp.types import warp_types


@lru_cache(maxsize=None)
def _kernels(dim: int, precision: str):
    T = warp_types(dim, precision)
    scalar, vec = T.scalar, T.vec

    @wp.func
    def belt(v: vec, speed: scalar):
        vy = v[1]
        if vy < scalar(0.0):
            vy = scalar(0.0)
        if wp.static(dim == 3):
            return vec(speed, vy, v[2])
        else:
            return vec(speed, vy)

    @wp.kernel(module="unique")
    def fast(grid_v: wp.array(dtype=vec), nodes: wp.array(dtype=int), speed: wp.array(dtype=scalar)):
        k = wp.tid()
        i = nodes[k]
        grid_v[i] = belt(grid_v[i], speed[0])

    @wp.kernel(module="unique")
    def tape(grid_v: wp.array(dtype=vec), on: wp.array(dtype=int), speed: wp.array(dtype=scalar),
             out: wp.array(dtype=vec)):
        i = wp.tid()
        v = grid_v[i]
        if on[i] != 0:
            v = belt(v, speed[0])
        out[i] = v

    return SimpleNamespace(fast=fast, tape=tape)


def conveyor(b, scene, stepper):
    mask = wall_masks(scene, b.thickness)["y-"]
    K = _kernels(scene.dim, stepper.precision)
    dev = stepper.device
    nodes = wp.array(np.nonzero(mask)[0].astype(np.int32), dtype=int, device=dev)
    speed = wp.array([b.speed], dtype=stepper.T.scalar, device=dev)

    def apply(grid_v, t):
        wp.launch(K.fast, dim=nodes.shape[0], inputs=[grid_v, nodes, speed], device=dev)

    def tape():
        on = wp.array(mask.astype(np.int32), dtype=int, device=dev)

        def grid(grid_v, out, p, t):
            wp.launch(K.tape, dim=len(mask), inputs=[grid_v, on, p["speed"], out], device=dev)

        return SimpleNamespace(stage="grid", params={"speed": np.asarray([b.speed], float)},
                               param_kinds={"speed": "scalar"}, grid=grid)

    return SimpleNamespace(kind="grid", params={"speed": speed}, apply=apply, tape=tape)
