"""A compact node set for ``JaxStepper.step_fn``: the grid as a stack of small dense windows.

A reduced model's Eulerian quadrature (Chen et al. 2023, Alg. 4; ``mpmlab.rom.stepper``) touches only the
nodes around its |M| sample points, a few thousand, however large the body and its grid are. Running its
P2G, grid update and G2P on the scene's grid makes every step cost O(grid) (the zeroed grid, the grid
update, the boundary masks), so the step time grows with the body: the paper's "compact node set" is
what keeps it flat.

The node set here is ``n_win`` windows of ``width``^D nodes each, window w starting at the global node
``origin[w]``; every particle scatters into and gathers from one window (``window[p]``) that must hold its
whole stencil. Stacked along the first axis they form one dense array ``[n_win * width, width, ..]``, so
P2G and G2P are the stepper's own windowed scatter and gather (``adjoints.p2g`` / ``adjoints.g2p``) with
each particle's base node moved into its window. Windows overlap where samples are near each other: the
copies of a node are summed after P2G (``merge``, a sort and a segment sum: O(n log n) in the windows'
nodes, nothing of the grid's size), so every copy holds the node's full mass and momentum, the grid
update gives every copy the same velocity, and G2P reads the same value from whichever copy a particle's
window has. The result equals the scene-grid step's (``tests/test_rom_stepper.py``).
"""
from __future__ import annotations

import itertools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np


@jax.tree_util.register_pytree_node_class
class NodeWindows(NamedTuple):
    origin: Any        #: [n_win, D] int32: the global index of each window's lowest node
    window: Any        #: [N] int32: the window each particle scatters into and gathers from
    width: int         #: nodes per axis of a window (static: a pytree's auxiliary data, never traced)

    def tree_flatten(self):
        return (self.origin, self.window), self.width

    @classmethod
    def tree_unflatten(cls, width, children):
        return cls(*children, width)

    @property
    def shape(self) -> tuple[int, ...]:
        """The stacked windows' dense shape, [n_win * width, width, ..]."""
        n, D = self.origin.shape
        return (n * self.width,) + (self.width,) * (D - 1)

    def local_base(self, base, stencil: int):
        """Global base nodes [N, D] -> each particle's base in the stacked windows (clipped so that its
        ``stencil``-wide window stays in its own window: only padding rows, which carry no mass, need it)."""
        local = jnp.clip(base - self.origin[self.window], 0, self.width - stencil)
        return local.at[:, 0].add(self.window * self.width)

    def nodes(self):
        """The global index [n_win * width^D, D] of every node of the stacked windows, in the order of
        their flattened array (window-major, then C order within a window)."""
        D = self.origin.shape[1]
        offs = jnp.asarray(np.array(list(itertools.product(range(self.width), repeat=D)), np.int32))
        return (self.origin[:, None, :] + offs[None]).reshape(-1, D)

    def scene_ids(self, nodes, grid_shape):
        """Flat index of each node in the scene's grid (C order), -1 for a node outside it: what the
        boundaries' per-node masks are read at."""
        g = jnp.asarray(grid_shape, jnp.int32)
        inside = jnp.all((nodes >= 0) & (nodes < g), axis=1)
        flat = jnp.ravel_multi_index(tuple(jnp.clip(nodes, 0, g - 1).T), tuple(int(a) for a in grid_shape), mode="clip")
        return jnp.where(inside, flat, -1)

    def merge(self, grid, nodes):
        """``grid`` [n_win * width^D, K] (each window's own P2G sums) -> every copy of a node holding the
        sum over its copies. ``nodes``: their global indices (``nodes()``)."""
        key = _key(nodes + self.width)               # a unique key per node, inside the grid or not
        order = jnp.argsort(key)
        k = key[order]
        seg = jnp.concatenate([jnp.zeros(1, jnp.int32), jnp.cumsum((k[1:] != k[:-1]).astype(jnp.int32))])
        sums = jax.ops.segment_sum(grid[order], seg, num_segments=grid.shape[0], indices_are_sorted=True)
        return jnp.zeros_like(grid).at[order].set(sums[seg], unique_indices=True)


def key_bits(dim: int) -> int:
    """Bits per axis of a node's merge key (a 32-bit int): 10 in 3D, 15 in 2D."""
    return 31 // dim


def fits(grid_shape, width: int) -> bool:
    """Whether windows of ``width`` around a grid of ``grid_shape`` nodes have unique merge keys."""
    return max(int(a) for a in grid_shape) + 2 * width < (1 << key_bits(len(grid_shape)))


def _key(nodes):
    """A unique int32 key per non-negative node index [n, D], row-major over a box of 2^key_bits per axis
    (``fits`` checks a scene's windows against it)."""
    D = nodes.shape[1]
    bits = key_bits(D)
    key = jnp.zeros(nodes.shape[0], jnp.int32)
    for d in range(D):
        key = key * (1 << bits) + nodes[:, d]
    return key
