"""A compact node set for ``WarpStepper``: the grid update over a list of nodes instead of the box of nodes
particles reached.

A reduced model's Eulerian quadrature (Chen et al. 2023, Alg. 4; ``mpmlab.rom.stepper_warp``) touches only
the nodes around its |M| sample points, a few thousand, however large the body is; the box that bounds them
is the body's. The Warp stepper's P2G and G2P already cost O(points) and its grid boundaries O(their own
nodes) (each holds its node list); what grows with the body is the grid update over that box. With a
``NodeList`` set on the stepper (``WarpStepper.node_list``), the update visits the listed nodes only.

The JAX backend does the same with stacked dense windows (``backends/jax/node_windows.py``), because XLA
wants static shapes and no scattered writes into a large grid. Warp writes into the scene's grid freely, so
the node set here is a list into it: the grid's memory stays allocated (once), and the work per step is
O(list). The list is built per step from windows of ``width``^D nodes (``claim_windows``): a node in several
windows is listed once (an atomic claim on a per-node flag, cleared again by ``release``, also O(list)).

The caller's contract: every node a particle's stencil reaches this step is in the list (the update clears
the P2G accumulators it reads, and G2P reads the velocities it wrote). Nodes outside the list keep stale
velocities that no particle reads.
"""

import itertools
from functools import lru_cache

import numpy as np
import warp as wp

from .types import warp_types


@lru_cache(maxsize=None)
def _kernels(dim: int):
    ivec = warp_types(dim, "fp32").ivec

    @wp.kernel(module="unique")
    def claim_windows(origin: wp.array(dtype=ivec), offsets: wp.array(dtype=ivec), shape: ivec, strides: ivec,
                      flag: wp.array(dtype=int), nodes: wp.array(dtype=int), count: wp.array(dtype=int)):
        w, k = wp.tid()
        I = origin[w] + offsets[k]
        i = int(0)
        for d in range(dim):
            if I[d] < 0 or I[d] >= shape[d]:
                return
            i = i + I[d] * strides[d]
        if wp.atomic_add(flag, i, 1) == 0:          # the first window to reach node i lists it
            nodes[wp.atomic_add(count, 0, 1)] = i

    @wp.kernel(module="unique")
    def release(flag: wp.array(dtype=int), nodes: wp.array(dtype=int), count: wp.array(dtype=int)):
        t = wp.tid()
        if t < count[0]:
            flag[nodes[t]] = 0

    return claim_windows, release


class NodeList:
    """Up to ``capacity`` distinct nodes of a ``dim``-D grid of ``grid_shape`` nodes (C order), built from
    windows (``claim_windows``) and handed to the stepper's listed grid update (module doc)."""

    def __init__(self, dim: int, grid_shape, width: int, windows: int, device: str = "cpu"):
        self.dim, self.width, self.windows, self.device = int(dim), int(width), int(windows), device
        self.grid_shape = tuple(int(a) for a in grid_shape)
        self.capacity = self.windows * self.width ** self.dim
        self.ivec = warp_types(self.dim, "fp32").ivec
        self.shape = self.ivec(*self.grid_shape)
        strides = np.cumprod((1,) + self.grid_shape[:0:-1])[::-1]
        self.strides = self.ivec(*[int(a) for a in strides])
        self.flag = wp.zeros(int(np.prod(self.grid_shape)), dtype=int, device=device)
        self.nodes = wp.zeros(self.capacity, dtype=int, device=device)
        self.count = wp.zeros(1, dtype=int, device=device)
        offs = np.array(list(itertools.product(range(self.width), repeat=self.dim)), np.int32)
        self.offsets = wp.array(offs, dtype=self.ivec, device=device)
        self._claim, self._release = _kernels(self.dim)

    def claim_windows(self, origin) -> None:
        """List the nodes of the windows whose lowest nodes are ``origin`` ([windows, D] ints: a wp.array of
        ivec, or anything ``wp.from_torch`` / ``wp.array`` takes); nodes off the grid are skipped."""
        if hasattr(origin, "detach"):                   # a torch tensor (zero-copy where the device allows)
            import torch

            origin = wp.from_torch(origin.to(torch.int32).contiguous(), dtype=self.ivec)
        elif not isinstance(origin, wp.array):
            origin = wp.array(np.asarray(origin, np.int32), dtype=self.ivec, device=self.device)
        if origin.shape[0] > self.windows:
            raise ValueError(f"NodeList: {origin.shape[0]} windows, room for {self.windows}")
        self.count.zero_()
        wp.launch(self._claim, dim=(origin.shape[0], self.offsets.shape[0]),
                  inputs=[origin, self.offsets, self.shape, self.strides, self.flag, self.nodes, self.count],
                  device=self.device)

    def release(self) -> None:
        """Clear the claims (the flags of the listed nodes), O(list), for the next ``claim_windows``."""
        wp.launch(self._release, dim=self.capacity, inputs=[self.flag, self.nodes, self.count], device=self.device)

    def listed(self) -> np.ndarray:
        """The listed nodes' flat indices, sorted (a host copy: for tests and diagnostics)."""
        return np.sort(self.nodes.numpy()[: int(self.count.numpy()[0])])
