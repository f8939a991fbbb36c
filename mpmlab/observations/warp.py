"""Warp implementations of the observation operators (JAX-MPM Eqs. 26-27).

``launch(state, out)`` records Warp kernels (on the active ``wp.Tape``, if any) that write ``out``, a
``wp.array`` of L vectors of length d, from a state with ``x`` and ``v`` particle arrays. States of the
differentiable path are in scene order; a fast-path ``WarpState`` keeps particles sorted by cell
(``state.order.perm``), which the Lagrangian gather maps back. Kernels are built per (dim, precision)
and compiled on first use.
"""

from functools import lru_cache
from types import SimpleNamespace

import numpy as np
import warp as wp

from ..backends.warp.types import warp_types


@lru_cache(maxsize=None)
def _kernels(dim: int, precision: str):
    T = warp_types(dim, precision)
    scalar, vec = T.scalar, T.vec

    @wp.kernel(module="unique")
    def gather(z: wp.array(dtype=vec), idx: wp.array(dtype=int), out: wp.array(dtype=vec)):
        l = wp.tid()
        out[l] = z[idx[l]]                                   # JAX-MPM Eq. 26

    @wp.func
    def inside(x: vec, c: vec, h: scalar):
        ok = True
        for d in range(dim):
            if wp.abs(x[d] - c[d]) > h:
                ok = False
        return ok

    @wp.kernel(module="unique")
    def count(x: wp.array(dtype=vec), centers: wp.array(dtype=vec), h: scalar, cnt: wp.array(dtype=scalar)):
        l, p = wp.tid()
        if inside(x[p], centers[l], h):
            wp.atomic_add(cnt, l, scalar(1.0))

    @wp.kernel(module="unique")
    def accumulate(x: wp.array(dtype=vec), z: wp.array(dtype=vec), centers: wp.array(dtype=vec), h: scalar,
                   acc: wp.array(dtype=vec)):
        l, p = wp.tid()
        # membership is an indicator of x (no derivative), the averaged quantity carries the gradient
        if inside(x[p], centers[l], h):
            wp.atomic_add(acc, l, z[p])

    @wp.kernel(module="unique")
    def finish(acc: wp.array(dtype=vec), cnt: wp.array(dtype=scalar), out: wp.array(dtype=vec)):
        l = wp.tid()
        out[l] = acc[l] / wp.max(cnt[l], scalar(1.0))        # JAX-MPM Eq. 27; an empty monitor reads 0

    return SimpleNamespace(gather=gather, count=count, accumulate=accumulate, finish=finish)


def _storage_perm(state):
    return getattr(getattr(state, "order", None), "perm", None)


def lagrangian(obs, stepper):
    N, D = stepper.particles.count, stepper.dim
    idx = obs.indices(N).astype(np.int64)
    K = _kernels(D, stepper.precision)
    dev = stepper.device
    scene_idx = wp.array(idx.astype(np.int32), dtype=int, device=dev)
    q = obs.quantity
    cache = {}

    def launch(state, out):
        perm = _storage_perm(state)
        ia = scene_idx
        if perm is not None:                 # stored particle i is scene particle perm[i]
            hit = cache.get("perm")
            if hit is None or hit[0] is not perm:
                inv = np.empty_like(perm)
                inv[perm] = np.arange(len(perm))
                hit = cache["perm"] = (perm, wp.array(inv[idx].astype(np.int32), dtype=int, device=dev))
            ia = hit[1]
        wp.launch(K.gather, dim=len(idx), inputs=[getattr(state, q), ia, out], device=dev)

    return SimpleNamespace(shape=(len(idx), D), launch=launch, indices=idx)


def eulerian(obs, stepper):
    D = stepper.dim
    T = warp_types(D, stepper.precision)
    K = _kernels(D, stepper.precision)
    dev = stepper.device
    c = obs.centers_array(D)
    centers = wp.array(c, dtype=T.vec, device=dev)
    h = T.scalar(obs.half_size)
    q = obs.quantity
    L = len(c)

    def launch(state, out):
        x, z = state.x, getattr(state, q)
        n = x.shape[0]
        cnt = wp.zeros(L, dtype=T.scalar, device=dev)
        acc = wp.zeros(L, dtype=T.vec, device=dev, requires_grad=z.requires_grad or out.requires_grad)
        wp.launch(K.count, dim=(L, n), inputs=[x, centers, h, cnt], device=dev)
        wp.launch(K.accumulate, dim=(L, n), inputs=[x, z, centers, h, acc], device=dev)
        wp.launch(K.finish, dim=L, inputs=[acc, cnt, out], device=dev)

    return SimpleNamespace(shape=(L, D), launch=launch)


@lru_cache(maxsize=None)
def _matrix_gather(dim: int, precision: str):
    T = warp_types(dim, precision)
    flat = wp.types.vector(dim * dim, T.scalar)

    @wp.kernel(module="unique")
    def gather_matrix(z: wp.array(dtype=T.mat), idx: wp.array(dtype=int), pos: wp.array(dtype=int),
                      out: wp.array(dtype=flat)):
        l = wp.tid()
        m = z[idx[l]]
        r = flat()
        for i in range(dim):
            for j in range(dim):
                r[i * dim + j] = m[i, j]
        out[pos[l]] = r

    return gather_matrix


def particle_state(obs, stepper):
    """C or F of tracked particles from a scene-order state (the differentiable path's)."""
    from ..core.errors import ConfigError

    N, D = stepper.particles.count, stepper.dim
    idx = obs.indices(N).astype(np.int64)
    q, dev = obs.quantity, stepper.device
    K = _matrix_gather(D, stepper.precision)
    if q == "F":
        missing = [g.law.name for g in stepper.groups if "F" not in g.law.state_fields]
        if missing:
            raise ConfigError(f"observation 'particle_state': quantity F needs every law to carry F; {missing} do not.")
    blocks = []          # (group or None for C, local indices, output positions)
    if q == "C":
        blocks.append((None, idx, np.arange(len(idx))))
    else:
        for k, g in enumerate(stepper.groups):
            sel = np.nonzero((idx >= g.start) & (idx < g.stop))[0]
            if len(sel):
                blocks.append((k, idx[sel] - g.start, sel))
    arrays = [(k, wp.array(a.astype(np.int32), dtype=int, device=dev), wp.array(p.astype(np.int32), dtype=int, device=dev),
               len(a)) for k, a, p in blocks]

    def launch(state, out):
        if _storage_perm(state) is not None:
            raise ConfigError("observation 'particle_state' reads scene-order states (stepper.observe), not the "
                              "sorted fast-path state.")
        for k, ia, pa, n in arrays:
            z = state.C if k is None else state.law[k]["F"]
            wp.launch(K, dim=n, inputs=[z, ia, pa, out], device=dev)

    return SimpleNamespace(shape=(len(idx), D * D), launch=launch, indices=idx)
