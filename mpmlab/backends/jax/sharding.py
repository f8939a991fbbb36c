"""One simulation on several devices (``backend.devices=N``, JAX): particles sharded, grid replicated.

Each device holds a block of particles and the whole grid. A step is ``jax.shard_map`` of the
single-device ``step_fn`` over the device's block: its P2G scatter-add fills a full local grid, one
``lax.psum`` (an all-reduce of ``[nodes, K]``) sums the blocks, every device then updates the whole
grid (the same arithmetic on each, so the copies stay identical) and gathers its own particles'
velocities from it. Nothing particle-sized crosses devices during a step; the backward pass is the
mirror image (one all-reduce of the grid cotangent). Why this and not slabs of grid with halos:
``benchmarks/README.md``, "One simulation on several devices".

Layout. A device's block must be material groups in the same order as the scene, each of a fixed
size, so that ``step_fn`` slices the laws' rows locally with static bounds (group g's block on device d
is its rows d*l_g .. (d+1)*l_g). The per-particle arrays are therefore stored device-major
(``[block 0 | block 1 | ...]``, each block ``[group 0 rows | group 1 rows | ...]``) and each group is
padded to a multiple of N (shard_map needs equal blocks). A padding particle is a massless clone of its
group's last particle: mass and volume 0, so every P2G term it adds is an exact zero (all are products
with m or V), while its x, v, C and law state follow its twin's bit for bit (they depend on the
particle's own values and the grid only), so it never trips a guard the real particles do not trip.
``to_scene_order`` drops the clones; ``to_numpy``, trajectories and observations never see them.

The stepper's public state (``init``, ``rollout``) is in this layout; controls and observations stay in
scene order (``differentiable.split_controls`` calls ``to_layout``; observations read
``to_scene_order``).
"""
from __future__ import annotations

import logging
import os
from functools import cached_property

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from ...core.errors import ConfigError
from .stepper import JaxStepper

log = logging.getLogger("mpmlab")
AXIS = "p"
FORCE_FLAG = "--xla_force_host_platform_device_count"
POOL_ENV = ("PJRT_NPROC", "NPROC")       # what XLA's CPU client sizes its thread pool by (else the cores)


def cpu_pool_threads() -> int:
    """The threads of XLA's CPU thread pool (read by the CPU client when JAX starts)."""
    for key in POOL_ENV:
        if os.environ.get(key, "").isdigit():
            return int(os.environ[key])
    return len(os.sched_getaffinity(0))


#: a batched LAPACK call on fewer matrices than this runs in its own thread (jaxlib splits a batch only
#: when it holds >= 2e5 FLOP: >= ~1000 3x3 SVDs; a margin below that)
SPLIT_MIN = 256
_WARNED: set = set()


def cpu_threads_needed(devices: int, group_sizes=()) -> int:
    """Forced host devices share one thread pool. jaxlib's batched LAPACK calls (the SVD of the F-based
    laws) split a large batch into tasks on that pool and block their thread until the tasks are done;
    when every thread of the pool is so blocked (each device can run one such call per material group
    at once) nothing runs the tasks: a deadlock (seen: 2 devices on a 2-thread pool, 33k particles per
    device). One thread more than the calls that can wait at once prevents it."""
    large = sum(1 for c in group_sizes if -(-c // devices) >= SPLIT_MIN)
    return devices * large + 1


def check_devices(devices, group_sizes=()) -> int:
    """The number of devices to shard over; ``ConfigError`` (one sentence) for an impossible request.

    On forced host devices, before JAX's CPU client exists, it sizes the client's thread pool
    (``PJRT_NPROC``, unless set) to :func:`cpu_threads_needed`; afterwards it can only warn."""
    if isinstance(devices, bool) or not isinstance(devices, (int, np.integer)) or devices < 1:
        raise ConfigError(f"backend.devices = {devices!r} must be a whole number >= 1 (1: one device, "
                          f"as without it).")
    need = cpu_threads_needed(int(devices), group_sizes)
    from jax._src import xla_bridge

    started = bool(getattr(xla_bridge, "_backends", None))
    if (FORCE_FLAG in os.environ.get("XLA_FLAGS", "") and not started and cpu_pool_threads() < need
            and not any(k in os.environ for k in POOL_ENV)):
        os.environ["PJRT_NPROC"] = str(need)
    found = jax.devices()
    if devices > len(found):
        kind = found[0].platform
        hint = (f"on a CPU, start Python with XLA_FLAGS={FORCE_FLAG}={devices} to split it into {devices} "
                f"host devices" if kind == "cpu" else f"use a machine with {devices} {kind.upper()} devices")
        raise ConfigError(f"backend.devices = {devices} but JAX sees {len(found)} {kind} device(s); "
                          f"{hint}, or set backend.devices <= {len(found)}.")
    if devices > 1 and found[0].platform == "cpu" and cpu_pool_threads() < need and need not in _WARNED:
        _WARNED.add(need)
        log.warning("backend.devices = %d: XLA's CPU thread pool has %d threads, fewer than the %d that keep "
                    "batched LAPACK calls (the laws' SVDs) from deadlocking on %d host devices; start Python "
                    "with PJRT_NPROC=%d.", devices, cpu_pool_threads(), need, devices, need)
    return int(devices)


class ShardedJaxStepper(JaxStepper):
    """``JaxStepper`` whose particles are split over ``devices`` devices (the module docstring)."""

    def __init__(self, scene, transfer, precision="fp32", check_every=None, devices=2, shape="quadratic"):
        n = check_devices(devices, [g.count for g in scene.particles().groups])
        by_index = [b.name for b in scene.boundaries if b.stage != "grid"]
        if by_index:
            raise ConfigError(f"backend.devices = {n}: boundary '{by_index[0]}' acts on particles by index, "
                              f"which the sharded stepper does not support yet; run this scene with "
                              f"backend.devices=1.")
        super().__init__(scene, transfer, precision, check_every, shape=shape)
        self.devices = n
        self.mesh = Mesh(np.array(jax.devices()[:n]), (AXIS,))
        self._rows = NamedSharding(self.mesh, P(AXIS))
        counts = [g.count for g in self.groups]
        block = [-(-c // n) for c in counts]                     # a group's rows per device
        edges = np.cumsum([0] + block)
        self._group_slices = [slice(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:])]
        # slot k of the device-major arrays holds scene particle src[k] (a padding slot: its twin)
        src, real = [], []
        for d in range(n):
            for g, b in zip(self.groups, block):
                rows = g.start + d * b + np.arange(b)
                src.append(np.minimum(rows, g.stop - 1))
                real.append(rows < g.stop)
        src, real = np.concatenate(src), np.concatenate(real)
        slot = np.empty(self.particles.count, np.int64)
        slot[src[real]] = np.nonzero(real)[0]
        self._src, self._real, self._slot = jnp.asarray(src), jnp.asarray(real), jnp.asarray(slot)
        # a group's own arrays (law state and parameters): its rows padded at the end with its last row
        self._group_src = [jnp.asarray(np.minimum(np.arange(b * n), c - 1)) for b, c in zip(block, counts)]
        self._jit_layout = jax.jit(self.to_layout)
        self._jit_scene_order = jax.jit(self.to_scene_order)

    # ---- layout ---------------------------------------------------------------------------------
    def _put(self, a, sharding):
        return jax.lax.with_sharding_constraint(a, sharding)

    def to_layout(self, state=None, params=None):
        rows = lambda a: self._put(a[self._src], self._rows)
        group_rows = lambda arrays: tuple(jax.tree.map(lambda a, i=i: self._put(a[i], self._rows), arr)
                                          for i, arr in zip(self._group_src, arrays))
        if state is not None:
            state = dict(state)
            for k in ("x", "v", "C", "domain"):     # (CPDI's domain: per particle, like C)
                if k in state:
                    state[k] = rows(state[k])
            state["law"] = group_rows(state["law"])
        if params is not None:
            params = dict(params)
            params["law"] = group_rows(params["law"])
            for k in ("mass", "volume"):            # the clones are massless: their P2G terms are exact zeros
                params[k] = self._put(jnp.where(self._real, params[k][self._src], 0.0), self._rows)
            if "lp" in params:                      # uGIMP's particle half widths: a clone keeps its twin's
                params["lp"] = rows(params["lp"])
        return state, params

    def to_scene_order(self, state):
        out = dict(state)
        for k in ("x", "v", "C", "domain"):
            if k in out:
                out[k] = out[k][self._slot]
        out["law"] = tuple(jax.tree.map(lambda a, c=g.count: a[:c], st) for g, st in zip(self.groups, state["law"]))
        return out

    # ---- state and parameters --------------------------------------------------------------------
    def init(self):
        return self._jit_layout(super().init())[0]

    @property
    def params(self):
        if not hasattr(self, "_params"):
            self._params = self._jit_layout(None, self.default_params())[1]
        return self._params

    @cached_property
    def unsharded(self) -> JaxStepper:
        """The single-device stepper of the same scene (NaN-gradient replays run on it)."""
        return JaxStepper(self.scene, self.transfer, self.precision, self.check_every, shape=self.shape)

    # ---- the step ----------------------------------------------------------------------------------
    def _sum_grid(self, grid):
        return jax.lax.psum(grid, AXIS)

    def step_fn(self, state, params, dt=None):
        """``JaxStepper.step_fn`` on each device's block (shard_map), the P2G sums all-reduced."""
        rows, same = P(AXIS), P()
        st_spec = {k: (same if k == "t" else rows) for k in state}
        pr_spec = {k: (rows if k in ("law", "mass", "volume", "lp") else same) for k in params}
        local = lambda s, p, dt_: JaxStepper.step_fn(self, s, p, dt_)
        if dt is None:                               # the build-time dt stays a constant of the program
            return jax.shard_map(lambda s, p: local(s, p, None), mesh=self.mesh, in_specs=(st_spec, pr_spec),
                                 out_specs=st_spec)(state, params)
        return jax.shard_map(local, mesh=self.mesh, in_specs=(st_spec, pr_spec, same),
                             out_specs=st_spec)(state, params, dt)

    # ---- numpy views --------------------------------------------------------------------------------
    def to_numpy(self, state):
        return super().to_numpy(self._jit_scene_order(state))

    def meta(self):
        return {**super().meta(), "devices": self.devices}
