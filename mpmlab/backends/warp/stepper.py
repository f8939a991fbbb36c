"""Warp stepper: P2G -> grid update (+ walls) -> grid boundaries -> G2P -> one law kernel per material.

What the scene does not need is not compiled and not launched: no ``C`` array or affine terms for
PIC/FLIP, no old grid velocity except for FLIP, one law kernel per law present (built from a closure
over its ``@wp.func``s), no boundary kernels for absent boundaries, no external-force array without
loads. ``_advance`` never writes into its input state, so a saved state stays valid (replay on
divergence; tape-based gradients in issue #4).
"""

import os
import time
from concurrent.futures import ThreadPoolExecutor
from types import SimpleNamespace

import numpy as np
import warp as wp

from ...core.stepper import BaseStepper
from . import kernels as K
from .kernels import WALL_CODES
from .types import warp_types


class WarpState(SimpleNamespace):
    """x, v [N] vec; C [N] mat (affine transfers only); law: per group dict of state arrays; tau [N] mat
    (stress of the current law state, computed when the state is produced); t: float seconds."""


class WarpStepper(BaseStepper):
    backend_name = "warp"

    def __init__(self, scene, transfer, precision="fp32", check_every=None, device: str | None = None,
                 threads: int | None = None):
        super().__init__(scene, transfer, precision, check_every)
        wp.init()
        self.device = device or "cpu"
        T = self.T = warp_types(self.dim, precision)
        D = self.dim
        tr = transfer
        self.split_force = tr.flip_ratio is not None
        self.grid_shape = scene.grid_shape
        self.node_count = int(np.prod(self.grid_shape))
        strides = np.cumprod((1,) + self.grid_shape[::-1][:-1])[::-1]
        self.strides = T.ivec(*[int(s) for s in strides])
        self.shape_iv = T.ivec(*self.grid_shape)
        self.origin = T.vec(*scene.origin)
        self.dx_s = T.scalar(scene.dx)
        self.dt_s = T.scalar(self.dt)
        self.gravity = T.vec(*scene.gravity)
        # boundaries: walls fuse into the grid update; the rest are their own kernels
        self.wall_codes, self.thickness = [WALL_CODES["none"]] * (2 * D), 1
        self.grid_bcs, self.particle_bcs, self.force_bcs = [], [], []
        for b in scene.boundaries:
            impl = b.implementation("warp", "boundary")(b, scene, self)
            if getattr(impl, "kind", "") == "walls":
                self.wall_codes, self.thickness = impl.codes, impl.thickness
            elif b.stage == "grid":
                self.grid_bcs.append(impl)
            elif b.stage == "particle_velocity":
                self.particle_bcs.append(impl)
            else:
                self.force_bcs.append(impl)
        dev = self.device
        self.wall_kind = wp.array(np.asarray(self.wall_codes, np.int32), dtype=int, device=dev)
        P = self.particles
        G, N = self.node_count, P.count
        # CPU threads: Warp runs a CPU launch serially, so chunks of particles/nodes are launched from a
        # small thread pool (the launch releases the GIL); P2G chunks write private grid copies.
        if threads is None:
            threads = int(os.environ.get("MPMLAB_WARP_THREADS", 0))
        if not threads:
            threads = min(len(os.sched_getaffinity(0)), 8, max(1, N // 2048))   # small scenes: one thread
        self.threads = max(1, int(threads)) if self.device == "cpu" else 1
        self._pool = ThreadPoolExecutor(self.threads - 1) if self.threads > 1 else None
        self.copies = self.threads
        #: launch the grid update only over the nodes particles reached (False: the whole grid, for
        #: measuring what this skip saves)
        self.limit_grid = True
        # kernels (cached per specialisation)
        self.k_p2g = K.p2g_kernel(D, precision, tr.needs_affine, tr.force == "mls", self.split_force, bool(self.force_bcs))
        self.k_grid = K.grid_update_kernel(D, precision, self.split_force)
        self.k_g2p = [K.g2p_law_kernel(g.law, D, precision, tr.affine, tr.grad_v == "affine", self.split_force)
                      for g in self.groups]
        self.k_laws = [K.law_kernels(g.law, D, precision) for g in self.groups]
        self.k_guard = K.guard_kernel(D, precision)
        # static per-particle data and scratch
        self.mass = wp.array(P.mass, dtype=T.scalar, device=dev)
        self.vol = wp.array(P.volume, dtype=T.scalar, device=dev)
        self.law_params = [wp.array(g.params, dtype=T.scalar, device=dev) for g in self.groups]
        gvec = K.grid_vec_type(D, precision)
        # P2G accumulators (one private copy per thread), all zero between steps: the grid update
        # clears what it reads
        self.grid_mm = wp.zeros(G * self.copies, dtype=gvec, device=dev)
        self.grid_f = wp.zeros(G * self.copies if self.split_force else 1, dtype=T.vec, device=dev)
        self.grid_v = wp.zeros(G, dtype=T.vec, device=dev)
        self.grid_v_old = wp.zeros(G if self.split_force else 1, dtype=T.vec, device=dev)
        self._grid_dirty = False
        self.bbox = wp.zeros(2 * self.copies, dtype=T.ivec, device=dev)
        self._bbox_np = self.bbox.numpy() if dev == "cpu" else None
        self.ext = wp.zeros(N if self.force_bcs else 1, dtype=T.vec, device=dev)
        self._empty_mat = wp.zeros(1, dtype=T.mat, device=dev)
        self._empty_scalar = wp.zeros(1, dtype=T.scalar, device=dev)
        self.flag = wp.zeros(1, dtype=int, device=dev)
        lo, hi = scene.inner_bounds
        self.lo, self.hi = T.vec(*lo), T.vec(*hi)
        self._ratio = T.scalar(self.transfer.flip_ratio if self.split_force else 0.0)

    def __del__(self):
        pool = getattr(self, "_pool", None)
        if pool is not None:
            pool.shutdown(wait=False)

    # ---- state ----------------------------------------------------------------------------------
    def _alloc(self) -> WarpState:
        T, dev, N = self.T, self.device, self.particles.count
        law = []
        for g in self.groups:
            f = g.law.state_fields
            law.append({k: wp.empty(g.count, dtype=T.mat if k in ("F", "sigma") else T.scalar, device=dev) for k in f})
        return WarpState(x=wp.empty(N, dtype=T.vec, device=dev), v=wp.empty(N, dtype=T.vec, device=dev),
                         C=wp.zeros(N if self.transfer.needs_affine else 1, dtype=T.mat, device=dev),
                         law=law, tau=wp.zeros(N, dtype=T.mat, device=dev), t=0.0)

    def _law_args(self, st: dict):
        return [st.get("F", self._empty_mat), st.get("J", self._empty_scalar), st.get("sigma", self._empty_mat),
                st.get("eps_p", self._empty_scalar)]

    def init(self) -> WarpState:
        T, dev, P = self.T, self.device, self.particles
        s = self._alloc()
        s.x.assign(wp.array(P.x, dtype=T.vec, device=dev))
        s.v.assign(wp.array(P.v, dtype=T.vec, device=dev))
        for g, st, k, prm in zip(self.groups, s.law, self.k_laws, self.law_params):
            for name, a in g.law.initial_state(g.count, self.dim).items():
                st[name].assign(wp.array(a, dtype=st[name].dtype, device=dev))
            wp.launch(k.stress, dim=g.count, inputs=[*self._law_args(st), prm, g.start, s.tau], device=dev)
        return s

    # ---- one step --------------------------------------------------------------------------------
    def _chunks(self, n: int):
        """Split [0, n) into ``threads`` contiguous (start, count) chunks (fewer if n is small)."""
        k = max(1, min(self.threads, n))
        cuts = [n * i // k for i in range(k + 1)]
        return [(cuts[i], cuts[i + 1] - cuts[i]) for i in range(k) if cuts[i + 1] > cuts[i]]

    def _run(self, jobs):
        """Run launch closures on ``threads`` threads (this one and the pool): thread t runs jobs[t::threads]."""
        if len(jobs) == 1 or self._pool is None:
            for j in jobs:
                j()
            return
        lanes = [jobs[t::self.threads] for t in range(min(self.threads, len(jobs)))]
        run_lane = lambda lane: [j() for j in lane]
        futs = [self._pool.submit(run_lane, lane) for lane in lanes[1:]]
        run_lane(lanes[0])
        for f in futs:
            f.result()

    def _launcher(self, kernel, dim, inputs):
        dev = self.device
        return lambda: wp.launch(kernel, dim=dim, inputs=inputs, device=dev)

    def _step_into(self, s: WarpState, o: WarpState) -> None:
        D, dev, N, G = self.dim, self.device, self.particles.count, self.node_count
        if self._grid_dirty:          # a previous step stopped between P2G and the grid update
            self.grid_mm.zero_()
            if self.split_force:
                self.grid_f.zero_()
        if self.force_bcs:
            self.ext.zero_()
            for bc in self.force_bcs:
                bc.add_force(self.ext, s.t)
        # P2G, one private grid copy per chunk ------------------------------------------------------
        chunks = self._chunks(N)
        bb = self._bbox_np
        big = np.iinfo(np.int32).max
        if bb is not None:
            bb[0::2] = big
            bb[1::2] = -big
        self._grid_dirty = True
        self._run([self._launcher(self.k_p2g, cnt, [s.x, s.v, s.C, s.tau, self.mass, self.vol, self.ext, self.origin,
                                                    self.dx_s, self.dt_s, self.strides, start, c * G, self.grid_mm,
                                                    self.grid_f, self.bbox, c])
                   for c, (start, cnt) in enumerate(chunks)])
        # grid update over the reached nodes ------------------------------------------------------------
        if self.limit_grid and bb is not None:
            used = bb[: 2 * len(chunks)]
            lo = used[0::2].min(axis=0)
            hi = used[1::2].max(axis=0) + 3                   # stencil of the largest base node
            lo = np.maximum(lo, 0)
            hi = np.minimum(hi, self.grid_shape)
        else:
            lo, hi = np.zeros(D, int), np.asarray(self.grid_shape)
        ext = hi - lo
        count = int(np.prod(ext))
        lo_v, ext_v = self.T.ivec(*[int(a) for a in lo]), self.T.ivec(*[int(a) for a in ext])
        self._run([self._launcher(self.k_grid, cnt, [self.grid_mm, self.grid_f, len(chunks), G, start, lo_v, ext_v,
                                                     self.dt_s, self.gravity, self.shape_iv, self.strides,
                                                     self.wall_kind, self.thickness, self.grid_v, self.grid_v_old])
                   for start, cnt in self._chunks(count)])
        self._grid_dirty = False
        for bc in self.grid_bcs:
            bc.apply(self.grid_v, s.t)
        # G2P fused with each group's law update ------------------------------------------------------
        jobs = []
        for g, k, st, ot, prm in zip(self.groups, self.k_g2p, s.law, o.law, self.law_params):
            for start, cnt in self._chunks(g.count):
                jobs.append(self._launcher(k, cnt, [s.x, s.v, self.grid_v, self.grid_v_old, self.origin, self.dx_s,
                                                    self.dt_s, self.strides, self._ratio, g.start, start,
                                                    *self._law_args(st), prm, o.x, o.v, o.C, *self._law_args(ot),
                                                    o.tau]))
        self._run(jobs)
        o.t = s.t + self.dt
        for bc in self.particle_bcs:
            bc.apply_particles(o.v, s.x, o.x, o.t)

    def _advance(self, state: WarpState, steps: int) -> WarpState:
        if steps <= 0:
            return state
        out = self._alloc()
        scratch = self._alloc() if steps > 1 else None
        # alternate so that the last step lands in `out`; the input is never written
        bufs = [out, scratch] if steps % 2 == 1 else [scratch, out]
        cur = state
        for k in range(steps):
            nxt = bufs[k % 2]
            self._step_into(cur, nxt)
            cur = nxt
        return cur

    def _block(self, state):
        wp.synchronize_device(self.device)

    # ---- guards -----------------------------------------------------------------------------------
    def _is_bad(self, state) -> bool:
        self.flag.zero_()
        wp.launch(self.k_guard, dim=self.particles.count, inputs=[state.x, state.v, self.lo, self.hi, self.flag],
                  device=self.device)
        for g, st in zip(self.groups, state.law):
            for name, a in st.items():
                wp.launch(K.law_guard_kernel(self.dim, self.precision, name), dim=g.count, inputs=[a, self.flag],
                          device=self.device)
        return bool(self.flag.numpy()[0])

    # ---- numpy views ------------------------------------------------------------------------------
    def to_numpy(self, state):
        out = {"x": state.x.numpy().astype(np.float64), "v": state.v.numpy().astype(np.float64), "t": state.t}
        if self.transfer.needs_affine:
            out["C"] = state.C.numpy().astype(np.float64)
        for name in ("F", "J", "sigma", "eps_p"):
            parts = [(g, st[name]) for g, st in zip(self.groups, state.law) if name in st]
            if parts:
                out[name] = np.concatenate([a.numpy().astype(np.float64) for _, a in parts])
                out[name + "_particles"] = np.concatenate([np.arange(g.start, g.stop) for g, _ in parts])
        return out
