"""Warp stepper: P2G -> grid update (+ walls) -> grid boundaries -> G2P fused with each material's law.

The grid shape function (``shape=``: ``quadratic`` by default, ``cubic``, ``ugimp``, ``cpdi``;
``mpmlab.shapes``) is part of every kernel's key: its window (width^D nodes from ``floor(x/dx - offset)``)
and weights are compiled in, uGIMP's particle half widths ``lp`` are a per-particle array (sorted with the
particles), and the guard's domain interior is the window's (``mpmlab.shapes.inner_bounds``). CPDI runs
P2G / G2P over the 2^D corners of each particle's domain (the same kernels, ``kernels.py``); the domain
R [D, D] is state (``WarpState.domain``: double-buffered, sorted with the particles, ``to_numpy``'s
"domain"), and the guard checks every corner (``kernels.corner_guard_kernel``).

What the scene does not need is not compiled and not launched: no ``C`` array or affine terms for
PIC/FLIP, no old grid velocity except for FLIP, one G2P+law kernel per law present (built from a
closure over its ``@wp.func``s), no boundary kernels for absent boundaries, no external-force array
without loads, no grid work outside the nodes particles reach. ``_advance`` never writes into its
input state, so a saved state stays valid (replay on divergence; tape-based gradients in issue #4).

CPU execution: particles are kept sorted by cell (cache locality; invisible to users, see
``WarpState``), and each phase is split into chunks launched from a small thread pool (a Warp CPU
launch runs on one thread and releases the GIL). Results do not depend on the thread count's
scheduling: P2G chunk c always goes to grid copy c and the copies are summed in order.
"""

import itertools
import os
from concurrent.futures import ThreadPoolExecutor
from types import SimpleNamespace

import numpy as np
import warp as wp

from ...core.stepper import BaseStepper
from . import check_device, init_warp
from . import kernels as K
from .kernels import WALL_CODES
from .transfers import warp_transfer
from .types import warp_types
from ...shapes import inner_bounds as shape_inner_bounds
from ...shapes import resolve as resolve_shape


class WarpState(SimpleNamespace):
    """x, v [N] vec; C [N] mat (affine transfers only); domain [N] mat (CPDI only: the columns are the
    particle domain's half vectors; a one-entry dummy otherwise); law: per group dict of state arrays; tau [N] mat
    (stress of the current law state, computed when the state is produced); t: float seconds.

    On the CPU the particles are kept sorted by grid cell for cache locality (re-sorted every
    ``sort_every`` steps, within each material group): ``order`` holds the permutation (``perm[i]`` =
    scene index of stored particle i, None = scene order) and the static per-particle data in that
    order; ``age`` counts the steps since the last sort. ``to_numpy`` always returns scene order.
    """


def _build_kernels(kernels, device, blame) -> None:
    """Build kernels now (they are built at the first launch anyway), so that a plugin whose Warp
    functions do not fit its declarations (a law writing a state field it does not declare, a transfer
    returning the wrong type) is refused when the stepper is built, in one line naming it:
    ``blame(first line of Warp's error) -> message``."""
    try:
        for k in kernels:
            wp.load_module(k.module, device=device)
    except Exception as e:  # noqa: BLE001 -- Warp's codegen/compile error, reported against the plugin
        from ...core.errors import ConfigError

        lines = [ln.strip().lstrip(";").strip() for ln in str(e).splitlines() if ln.strip()]
        # Warp says where (first line), what code (middle) and why (last): why first, then the code
        why = (f"{lines[-1]} (at `{lines[1]}`)" if len(lines) == 3 else lines[-1]) if lines else type(e).__name__
        raise ConfigError(blame(why)) from None


def _law_blame(law):
    return lambda first: (f"law '{law.name}' ({type(law).__module__}): its Warp functions do not build against its "
                          f"declared state {list(law.state_fields)} and parameters {list(law.param_names())}: {first}")


def _transfer_blame(transfer):
    return lambda first: (f"{transfer.describe()}: its Warp functions do not build against its declarations "
                          f"(momentum_terms {sorted(transfer.momentum_terms)}, force_terms "
                          f"{sorted(transfer.force_terms)}, moments {sorted(transfer.moments)}; AbstractTransfer "
                          f"documents the signatures): {first}")


def _compile_step_kernels(st) -> None:
    """The law's own kernels, the transfer's P2G, then each fused G2P + law kernel; a fused kernel that
    fails although both parts built alone is the law's if its stand-alone update fails, else the
    transfer's ``g2p``."""
    dev = st.device
    for g, kl in zip(st.groups, st.k_laws):
        _build_kernels((kl.stress,), dev, _law_blame(g.law))
    _build_kernels((st.k_p2g,), dev, _transfer_blame(st.transfer))
    for g, kg, kl in zip(st.groups, st.k_g2p, st.k_laws):
        try:
            _build_kernels((kg,), dev, _transfer_blame(st.transfer))
        except Exception:
            _build_kernels((kl.update,), dev, _law_blame(g.law))
            raise


class WarpStepper(BaseStepper):
    backend_name = "warp"

    def __init__(self, scene, transfer, precision="fp32", check_every=None, device: str | None = None,
                 threads: int | None = None, p2g_atomic: bool | None = None, shape="quadratic"):
        super().__init__(scene, transfer, precision, check_every)
        init_warp()   # quiet: no "could not find the CUDA driver" line on a CPU machine
        # backend.device wins; MPMLAB_WARP_DEVICE sets the default (e.g. cuda:0 to run the test suite
        # on a GPU); otherwise the CPU
        self.device = str(device or os.environ.get("MPMLAB_WARP_DEVICE") or "cpu")
        check_device(self.device, "backend.device" if device else "MPMLAB_WARP_DEVICE")
        #: numpy dtype of every float array ``to_numpy`` returns (the stepper's precision)
        self.np_dtype = np.dtype(np.float64 if precision == "fp64" else np.float32)
        T = self.T = warp_types(self.dim, precision)
        D = self.dim
        tr = transfer
        #: the grid shape function (``mpmlab.shapes``; checked against the transfer) and, for one that uses
        #: the particle size (uGIMP), each particle's half width in cells (scene order; constant)
        self.shape, lp = resolve_shape(shape, tr, D, scene.dx, self.particles.volume)
        #: CPDI (``kind = "corners"``): P2G / G2P over the 2^D corners of each particle's domain, carried as
        #: ``state.domain`` [N] mat (mpmlab/shapes/cpdi/reference.py; kernels.py's corner loops)
        self.corners = self.shape.kind == "corners"
        #: the scheme's @wp.funcs and declarations (mpmlab/transfers/<name>/warp.py), the kernels' key
        self.warp_transfer = warp_transfer(tr, D, precision)
        self.split_force = self.warp_transfer.split_force
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
        # Default: the cores this process may use, at most 8, and one thread per 4096 particles. It
        # does not follow the machine's load on purpose: the thread count sets how P2G sums its grid
        # copies, so a load-dependent count would change results at round-off from run to run. On a
        # busy machine ``threads=1`` (or $MPMLAB_WARP_THREADS=1) is often faster.
        if threads is None:
            threads = int(os.environ.get("MPMLAB_WARP_THREADS", 0))
        if not threads:
            threads = max(1, min(len(os.sched_getaffinity(0)), 8, N // 4096))
        self.threads = max(1, int(threads)) if self.device == "cpu" else 1
        self._pool = ThreadPoolExecutor(self.threads - 1) if self.threads > 1 else None
        # chunks per phase for the dynamically scheduled kernels: G2P; the grid update (small: the
        # reached nodes only) runs on this thread unless the grid is large, saving a hand-off
        self._dyn_chunks = 1 if self.threads == 1 else 2 * self.threads
        self._grid_chunks = self._dyn_chunks if G >= 2_000_000 else 1
        self._cmd_cache = {}
        self.copies = self.threads
        #: launch the grid update only over the nodes particles reached (False: the whole grid, for
        #: measuring what this skip saves)
        self.limit_grid = True
        #: a compact node set (``node_list.NodeList``) the grid update visits instead of that box (None: the
        #: box); its owner lists every node the step's particles reach (e.g. the reduced model's windows)
        self.node_list = None
        # kernels (cached per specialisation)
        #: P2G sums with atomic adds into one grid (CUDA: required, every particle runs at once; None =
        #: by device) instead of plain adds into per-thread copies (CPU)
        self.p2g_atomic = not self.device.startswith("cpu") if p2g_atomic is None else bool(p2g_atomic)
        self.k_p2g = K.p2g_kernel(D, precision, self.warp_transfer, bool(self.force_bcs), atomic=self.p2g_atomic,
                                  shape=self.shape)
        self.k_grid = K.grid_update_kernel(D, precision, self.split_force)
        self.k_g2p = [K.g2p_law_kernel(g.law, D, precision, self.warp_transfer, shape=self.shape) for g in self.groups]
        self.k_laws = [K.law_kernels(g.law, D, precision) for g in self.groups]
        _compile_step_kernels(self)
        self.k_guard = K.guard_kernel(D, precision)
        self.k_corner_guard = K.corner_guard_kernel(D, precision) if self.corners else None
        # static per-particle data and scratch
        self.mass = wp.array(P.mass, dtype=T.scalar, device=dev)
        self.vol = wp.array(P.volume, dtype=T.scalar, device=dev)
        #: half particle widths in cells for the shape function (a one-entry dummy when it does not use them)
        self.lp = wp.array(lp if lp is not None else np.zeros(1), dtype=T.scalar, device=dev)
        self.law_params = [wp.array(g.params, dtype=T.scalar, device=dev) for g in self.groups]
        #: each group's shared law weights: {name: wp.array} and the law's ``Weights`` struct over them
        self.law_weights = [{k: wp.array(a, dtype=T.scalar, device=dev) for k, a in g.weights.items()}
                            for g in self.groups]
        self._weights_structs = [k.types.weights(w) for k, w in zip(self.k_laws, self.law_weights)]
        gvec = K.grid_vec_type(D, precision)
        # P2G accumulators (one private copy per thread), all zero between steps: the grid update
        # clears what it reads
        self.grid_mm = wp.zeros(G * self.copies, dtype=gvec, device=dev)
        self.grid_f = wp.zeros(G * self.copies if self.split_force else 1, dtype=T.vec, device=dev)
        self.grid_v = wp.zeros(G, dtype=T.vec, device=dev)
        self.grid_v_old = wp.zeros(G if self.split_force else 1, dtype=T.vec, device=dev)
        self._grid_dirty = False
        self.bbox = wp.zeros(2 * self.copies, dtype=T.ivec, device=dev)
        # the atomic P2G keeps no bounding box: the grid update then visits the whole grid
        self._bbox_np = self.bbox.numpy() if (dev == "cpu" and not self.p2g_atomic) else None
        self.ext = wp.zeros(N if self.force_bcs else 1, dtype=T.vec, device=dev)
        self.flag = wp.zeros(1, dtype=int, device=dev)
        self._gravity_unused = wp.zeros(1, dtype=T.vec, device=dev)   # the tape form's gravity argument
        #: the region the shape's window stays on the grid (one cell less per side for cubic B-splines)
        self.inner_bounds = lo, hi = shape_inner_bounds(self.shape, scene)
        # refuses particles (CPDI: the corners of their initial domains) outside it, one line
        shape_inner_bounds(self.shape, scene, self.particles.x, self.initial_domain() if self.corners else None)
        self.lo, self.hi = T.vec(*lo), T.vec(*hi)
        #: the scheme's runtime numbers (``scalars()``, e.g. the FLIP ratio), read by its Warp functions
        self.transfer_scalars = wp.array(np.asarray(tuple(tr.scalars()) or (0.0,), dtype=self.np_dtype),
                                         dtype=T.scalar, device=dev)
        #: re-sort particles by cell every this many steps (CPU only; None: never). Particle boundaries
        #: and loads address particles by scene index, so scenes with them are not sorted.
        self.sort_every = 100 if (self.device == "cpu" and not self.particle_bcs and not self.force_bcs) else None
        self._base_order = SimpleNamespace(perm=None, mass=self.mass, vol=self.vol, params=self.law_params, lp=self.lp)

    def __del__(self):
        pool = getattr(self, "_pool", None)
        if pool is not None:
            pool.shutdown(wait=False)

    # ---- state ----------------------------------------------------------------------------------
    def _alloc(self) -> WarpState:
        T, dev, N = self.T, self.device, self.particles.count
        law = []
        for g, k in zip(self.groups, self.k_laws):
            law.append({n: wp.empty(g.count, dtype=d, device=dev) for n, d, _ in k.types.fields})
        return WarpState(x=wp.empty(N, dtype=T.vec, device=dev), v=wp.empty(N, dtype=T.vec, device=dev),
                         C=wp.zeros(N if self.transfer.needs_affine else 1, dtype=T.mat, device=dev),
                         domain=wp.zeros(N if self.corners else 1, dtype=T.mat, device=dev),
                         law=law, tau=wp.zeros(N, dtype=T.mat, device=dev), t=0.0)

    def _law_args(self, g: int, st: dict, prm=None, weights=None):
        """Kernel arguments of group ``g``'s law: its state arrays (a ``StateArrays`` struct), per-particle
        parameters and shared ``Weights`` (struct); ``prm``/``weights`` override the stepper's own."""
        L = self.k_laws[g].types
        return [L.state_arrays(st), self.law_params[g] if prm is None else prm,
                self._weights_structs[g] if weights is None else weights]

    def init(self) -> WarpState:
        T, dev, P = self.T, self.device, self.particles
        s = self._alloc()
        s.x.assign(wp.array(P.x, dtype=T.vec, device=dev))
        s.v.assign(wp.array(P.v, dtype=T.vec, device=dev))
        if self.transfer.needs_affine:
            s.C.assign(wp.array(self.initial_C(), dtype=T.mat, device=dev))
        if self.corners:
            s.domain.assign(wp.array(self.initial_domain(), dtype=T.mat, device=dev))
        for i, (g, st, k) in enumerate(zip(self.groups, s.law, self.k_laws)):
            for name, a in g.initial_state(self.dim).items():
                st[name].assign(wp.array(a, dtype=st[name].dtype, device=dev))
            wp.launch(k.stress, dim=g.count, inputs=[*self._law_args(i, st), g.start, s.tau], device=dev)
        s.order, s.age = self._base_order, (self.sort_every or 0)     # sorted at the first step
        return s

    def _sort_into(self, s: WarpState, d: WarpState) -> None:
        """d <- s with particles sorted by base node within each group (NumPy views of CPU arrays)."""
        x = s.x.numpy()
        cell = np.floor((x - np.asarray(self.scene.origin)) / self.scene.dx - float(self.shape.offset))
        # a diverged particle (NaN/inf or far off the grid; the next guard check names it) gets a clipped
        # key instead of an invalid integer cast
        shape = np.asarray(self.grid_shape, dtype=float)
        cell = np.clip(np.where(np.isfinite(cell), cell, shape), -1.0, shape)
        key = cell.astype(np.int64) @ np.asarray(list(self.strides), dtype=np.int64)
        p = np.concatenate([g.start + np.argsort(key[g.start:g.stop], kind="stable") for g in self.groups])
        take = lambda src, dst, idx: np.take(src.numpy(), idx, axis=0, out=dst.numpy())
        take(s.x, d.x, p)
        take(s.v, d.v, p)
        take(s.tau, d.tau, p)
        if self.transfer.needs_affine:
            take(s.C, d.C, p)
        if self.corners:
            take(s.domain, d.domain, p)
        for g, st, dt_ in zip(self.groups, s.law, d.law):
            for name, a in st.items():
                take(a, dt_[name], p[g.start:g.stop] - g.start)
        o = s.order
        T, dev = self.T, self.device
        perm = p if o.perm is None else o.perm[p]
        lp = getattr(o, "lp", self.lp)
        d.order = SimpleNamespace(
            perm=perm, mass=wp.array(o.mass.numpy()[p], dtype=T.scalar, device=dev),
            vol=wp.array(o.vol.numpy()[p], dtype=T.scalar, device=dev),
            lp=wp.array(lp.numpy()[p], dtype=T.scalar, device=dev) if lp.shape[0] > 1 else lp,
            params=[wp.array(a.numpy()[p[g.start:g.stop] - g.start], dtype=T.scalar, device=dev)
                    for g, a in zip(self.groups, o.params)])
        d.t, d.age = s.t, 0

    # ---- one step --------------------------------------------------------------------------------
    # Launches are recorded once per (input, output) state pair of an ``_advance`` call (Warp
    # ``Launch`` objects: replaying one skips argument packing) and run on ``threads`` CPU threads.
    # P2G chunks are assigned statically (chunk c -> thread c -> grid copy c), so the summation order
    # and hence the result are the same in every run; G2P and grid-update chunks write disjoint
    # outputs and are handed out dynamically (finer chunks balance a core that is busy elsewhere).

    def _chunks(self, n: int, k: int):
        """Split [0, n) into at most k contiguous non-empty (start, count) chunks."""
        k = max(1, min(k, n))
        cuts = [n * i // k for i in range(k + 1)]
        return [(cuts[i], cuts[i + 1] - cuts[i]) for i in range(k) if cuts[i + 1] > cuts[i]]

    def _run_static(self, cmds):
        """cmds[t] runs on thread t (this thread runs cmds[0]); wait for all."""
        if len(cmds) == 1 or self._pool is None:
            for c in cmds:
                c.launch()
            return
        futs = [self._pool.submit(c.launch) for c in cmds[1:]]
        cmds[0].launch()
        for f in futs:
            f.result()

    def _run_dynamic(self, cmds):
        """Run cmds on all threads, each thread taking the next unstarted one; wait for all."""
        if len(cmds) == 1 or self._pool is None:
            for c in cmds:
                c.launch()
            return
        order = itertools.count()          # next() on a count is atomic under the GIL

        def lane():
            while (i := next(order)) < len(cmds):
                cmds[i].launch()

        futs = [self._pool.submit(lane) for _ in range(self.threads - 1)]
        lane()
        for f in futs:
            f.result()

    def _record(self, s: WarpState, o: WarpState) -> SimpleNamespace:
        dev, N, G = self.device, self.particles.count, self.node_count
        rec = lambda kernel, n, inputs: wp.launch(kernel, dim=n, inputs=inputs, device=dev, record_cmd=True)
        lp = getattr(s.order, "lp", self.lp)
        p2g = [rec(self.k_p2g, cnt, [s.x, s.v, s.C, s.tau, s.order.mass, s.order.vol, self.ext, lp, self.origin, self.dx_s,
                                     self.dt_s, self.transfer_scalars, self.strides, start, c * G, self.grid_mm, self.grid_f, self.bbox, c, s.domain])
               for c, (start, cnt) in enumerate(self._chunks(N, self.threads))]
        zero = self.T.ivec()
        grid = [rec(self.k_grid, 1, [self.grid_mm, self.grid_f, len(p2g), G, 0, zero, zero, self.dt_s, self.gravity,
                                     self._gravity_unused, self.shape_iv, self.strides, self.wall_kind, self.thickness,
                                     self.grid_v, self.grid_v_old])
                for _ in range(self._grid_chunks)]
        g2p = []
        for i, (g, k, st, ot, prm) in enumerate(zip(self.groups, self.k_g2p, s.law, o.law, s.order.params)):
            law_in = self._law_args(i, st, prm)
            law_out = self.k_laws[i].types.state_arrays(ot)
            for start, cnt in self._chunks(g.count, self._dyn_chunks):
                g2p.append(rec(k, cnt, [s.x, s.v, self.grid_v, self.grid_v_old, self.origin, self.dx_s, self.dt_s,
                                        self.strides, self.transfer_scalars, lp, g.start, start, *law_in, o.x, o.v,
                                        o.C, law_out, o.tau, s.domain, o.domain]))
        return SimpleNamespace(p2g=p2g, grid=grid, g2p=g2p)

    def _step_into(self, s: WarpState, o: WarpState) -> None:
        key = (id(s), id(o), id(s.order))
        cmds = self._cmd_cache.get(key)
        if cmds is None:
            cmds = self._cmd_cache[key] = self._record(s, o)
        if self._grid_dirty:          # a previous step stopped between P2G and the grid update
            self.grid_mm.zero_()
            if self.split_force:
                self.grid_f.zero_()
        if self.force_bcs:
            self.ext.zero_()
            for bc in self.force_bcs:
                bc.add_force(self.ext, s.t, s.x)
        # P2G, one private grid copy per thread ----------------------------------------------------------
        bb = self._bbox_np
        if bb is not None:
            bb[0::2] = np.iinfo(np.int32).max
            bb[1::2] = np.iinfo(np.int32).min
        self._grid_dirty = True
        self._run_static(cmds.p2g)
        # grid update over the reached nodes (their bounding box, or a compact node set) --------------------
        if self.node_list is not None:
            self._grid_update_listed(self.node_list, len(cmds.p2g))
        else:
            self._grid_update_box(cmds.grid, bb, len(cmds.p2g))
        self._grid_dirty = False
        for bc in self.grid_bcs:
            bc.apply(self.grid_v, s.t)
        # G2P fused with each group's law update ---------------------------------------------------------
        self._run_dynamic(cmds.g2p)
        o.t = s.t + self.dt
        o.order, o.age = s.order, s.age + 1
        for bc in self.particle_bcs:
            bc.apply_particles(o.v, s.x, o.x, o.t)

    def _grid_update_box(self, grid_cmds, bb, copies: int) -> None:
        """The grid update over the bounding box of the nodes P2G reached (``bb``: the P2G chunks' boxes;
        None or ``limit_grid`` False: the whole grid), in the recorded launches ``grid_cmds``."""
        D = self.dim
        if self.limit_grid and bb is not None:
            used = bb[: 2 * copies]
            lo = np.maximum(used[0::2].min(axis=0), 0)
            hi = np.minimum(used[1::2].max(axis=0) + self.shape.width, self.grid_shape)   # + the last base node's window
        else:
            lo, hi = np.zeros(D, int), np.asarray(self.grid_shape)
        ext = np.maximum(hi - lo, 0)   # 0 when no particle is on the grid (all diverged off it): nothing to do
        lo_v, ext_v = self.T.ivec(*lo.tolist()), self.T.ivec(*ext.tolist())
        chunks = self._chunks(int(np.prod(ext)), len(grid_cmds))
        for c, (start, cnt) in zip(grid_cmds, chunks):
            c.set_param_by_name("start", start)
            c.set_param_by_name("lo", lo_v)
            c.set_param_by_name("ext", ext_v)
            c.set_dim(cnt)
        self._run_dynamic(grid_cmds[:len(chunks)])

    def _grid_update_listed(self, nl, copies: int) -> None:
        """The grid update over a compact node set (``node_list.NodeList``: its owner listed every node
        the step's particles reach)."""
        kernel = K.grid_update_listed_kernel(self.dim, self.precision, self.split_force)   # cached; built on first use
        wp.launch(kernel, dim=nl.capacity, device=self.device,
                  inputs=[self.grid_mm, self.grid_f, copies, self.node_count, nl.nodes, nl.count, self.dt_s,
                          self.gravity, self.shape_iv, self.strides, self.wall_kind, self.thickness, self.grid_v,
                          self.grid_v_old])

    def _advance(self, state: WarpState, steps: int) -> WarpState:
        if steps <= 0:
            return state
        # own buffers only (the input state is never written); a step or a sort writes into one that
        # does not hold the current state
        bufs = [self._alloc()]
        cur = state

        def free():
            for b in bufs:
                if b is not cur:
                    return b
            bufs.append(self._alloc())
            return bufs[-1]

        self._cmd_cache = {}
        try:
            for _ in range(steps):
                if self.sort_every and cur.age >= self.sort_every:
                    nxt = free()
                    self._sort_into(cur, nxt)
                    cur = nxt
                nxt = free()
                self._step_into(cur, nxt)
                cur = nxt
        finally:
            self._cmd_cache = {}       # recorded launches hold the state arrays
        return cur

    def _block(self, state):
        wp.synchronize_device(self.device)

    def _set_dt(self, dt):
        # dt is a kernel argument: launches recorded by the next ``_advance`` pick up the new value
        super()._set_dt(dt)
        self.dt_s = self.T.scalar(self.dt)

    def _max_speed(self, state) -> float:
        v = state.v.numpy()             # a view on the CPU, one copy of [N, D] on a GPU
        return float(np.sqrt(np.max(np.sum(v.astype(np.float64) ** 2, axis=1), initial=0.0)))

    # ---- guards -----------------------------------------------------------------------------------
    def _is_bad(self, state) -> bool:
        self.flag.zero_()
        wp.launch(self.k_guard, dim=self.particles.count, inputs=[state.x, state.v, self.lo, self.hi, self.flag],
                  device=self.device)
        if self.corners:                # CPDI: a corner of a domain outside the region, or a non-finite domain
            wp.launch(self.k_corner_guard, dim=self.particles.count,
                      inputs=[state.x, state.domain, self.lo, self.hi, self.flag], device=self.device)
        for g, st in zip(self.groups, state.law):
            for f in g.law.state:
                k = K.law_guard_kernel(self.dim, self.precision, f.resolved_shape(self.dim), f.check)
                wp.launch(k, dim=g.count, inputs=[st[f.name], self.flag], device=self.device)
        return bool(self.flag.numpy()[0])

    # ---- differentiable entry points (issue #4) -----------------------------------------------------
    # The tape-safe path (``grad.py``: scene order, fresh buffers, the same kernel factories), built on
    # first use: forward-only runs compile nothing for it. Controls are torch tensors; ``observe`` is a torch.autograd.Function.
    def controls(self) -> dict:
        from . import grad

        return grad.controls(self)

    def observe(self, controls, observation, steps, segment=None):
        """Differentiable observations (``grad.py``); every step uses the build-time dt (an adaptive
        ``dt: auto`` is not recomputed here; a warning says so)."""
        from . import grad

        self._observe_dt_note()

        return grad.observe(self, controls, observation, steps, segment)

    # ---- numpy views ------------------------------------------------------------------------------
    def to_numpy(self, state):
        perm = getattr(getattr(state, "order", None), "perm", None)

        def scene_order(a, lo=0, hi=None):
            # a copy (the Warp array's memory is reused by later steps) in the stepper's precision
            a = np.array(a.numpy(), dtype=self.np_dtype)
            if perm is None:
                return a
            out = np.empty_like(a)
            out[perm[lo:hi] - lo] = a
            return out

        out = {"x": scene_order(state.x), "v": scene_order(state.v), "t": state.t}
        if self.transfer.needs_affine:
            out["C"] = scene_order(state.C)
        if self.corners:
            out["domain"] = scene_order(state.domain)
        for name in self.state_field_names:
            parts = [(g, st[name]) for g, st in zip(self.groups, state.law) if name in st]
            if parts:
                out[name] = np.concatenate([scene_order(a, g.start, g.stop) for g, a in parts])
                out[name + "_particles"] = np.concatenate([np.arange(g.start, g.stop) for g, _ in parts])
        return out
