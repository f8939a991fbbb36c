"""Static node sets and normals for boundaries, computed once in NumPy and shared by both backends."""
from __future__ import annotations

import numpy as np

from ..boundaries import _faces


def node_indices(scene) -> np.ndarray:
    """Integer node coordinates [G, D] in the flattened (C-order) grid layout."""
    return np.stack(np.meshgrid(*[np.arange(n) for n in scene.grid_shape], indexing="ij"), -1).reshape(-1, scene.dim)


def node_positions(scene) -> np.ndarray:
    return scene.origin + node_indices(scene) * scene.dx


def wall_masks(scene, thickness: int) -> dict[str, np.ndarray]:
    """Per face, the nodes within ``thickness`` cells of it (index < t at '-', > cells - t at '+')."""
    I = node_indices(scene)
    out = {}
    for f in _faces(scene.dim):
        a = "xyz".index(f[0])
        out[f] = I[:, a] < thickness if f[1] == "-" else I[:, a] > scene.cells[a] - thickness
    return out


def friction_node_mu_index(b, scene) -> np.ndarray:
    """Index into ``b.mu`` for every node: its segment (equal lengths along ``b.along``) or its node."""
    I = node_indices(scene)[:, b.along_axis]
    if b.per_node:
        return I.astype(np.int32)
    nseg = len(b.mu)
    seg = np.floor(I / scene.cells[b.along_axis] * nseg).astype(np.int32)
    return np.clip(seg, 0, nseg - 1)


def box_obstacle_normals(b, scene) -> tuple[np.ndarray, np.ndarray]:
    """(inside [G] bool, outward normal of the nearest face [G, D]) for a static box obstacle."""
    x = node_positions(scene)
    lo, hi = np.asarray(b.lo, float), np.asarray(b.hi, float)
    inside = np.all((x >= lo) & (x <= hi), axis=1)
    d = np.concatenate([x - lo, hi - x], axis=1)          # distance to each face [G, 2D]
    k = np.argmin(d, axis=1)
    n = np.zeros_like(x)
    D = scene.dim
    n[np.arange(len(x)), k % D] = np.where(k < D, -1.0, 1.0)
    return inside, n
