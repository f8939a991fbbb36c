"""Differentiable Warp path (issue #4): ``controls()`` and ``observe()`` of ``WarpStepper``.

The fast stepper (``stepper.py``) sorts particles, splits P2G over private grid copies and clears the
grid it reads, all in place; a ``wp.Tape`` cannot replay that. This module is the separate
gradient-correct path (Genesis-style forward-fast / gradient-correct split): particles in scene order,
a separate grid and particle state per step of a segment (buffers allocated once and reused, never
overwritten while a tape still needs them). Every kernel comes from the fast path's factories (one
source): P2G in its atomic (CUDA) form, the grid update's tape-safe form (``kernels.grid_update_kernel
(tape=True)``: every node, fresh outputs), G2P fused with each law's update and the initial stress as
they are, and each boundary's own ``tape()`` implementation (``boundaries.py``; a boundary without
one has no Warp gradient). The laws' spectral maps carry hand-written adjoints
(``linalg.spectral_func``) so the derivative is finite at repeated singular values.

Adjoints (issue 17): the forward launches of P2G and of G2P + law are the fast path's kernels, but on
the tape they are recorded with hand-written adjoints (``adjoints.py``, ``Tape.record_func``): P2G's is
a per-particle gather of the node adjoints (no atomics, no replay of the scatter), G2P's stencil part
a scatter written by hand while the scheme's ``g2p`` and the law keep Warp's generated adjoint.
``GradPath.adjoints = "generated"`` (module default ``ADJOINTS``) records Warp's generated adjoints
instead; the two agree to rounding (``tests/test_warp_adjoints.py``). CPDI (shape ``cpdi``): the
hand-written adjoints are written for one separable window per particle and do not cover the corner loops
(each corner's own window and fx, R^-1, the inertia's inverse, the Cayley update), so a CPDI stepper's path
uses ``"generated"`` (Warp's generated adjoints of the same forward kernels; checked against central
differences, ``tests/test_shapes_warp.py``) and refuses ``"hand"`` in one line. The domain flows through
the per-step state like x, v, C; its initial value is a constant (``initial_domain()``), not a control. The grid update keeps its
generated adjoint (measured: ~10 % of the backward, ``benchmarks/_adjoint_split_warp.py``).

Memory (JAX-MPM Sec. 3.3.2, Remarks 4-5): the forward pass keeps only the states at segment starts
(every ``segment`` steps) and the observations. The backward pass walks the segments from the last:
it recomputes one segment under one ``wp.Tape`` per step from its saved start state, seeds the
adjoint of the segment's end state (from the later segment) and of its observations, runs the tapes
backwards (control adjoints accumulate in the control arrays' ``.grad``) and hands the start state's
adjoint to the previous segment: O(steps / segment + segment) states. ``segment="auto"``
(``core.budget.resolve_segment`` with :meth:`GradPath.bytes_per_step`): when every step's buffers fit
the budget, the forward pass itself records the whole rollout on tapes (one segment) and the backward
pass recomputes nothing: forward + adjoint instead of 2 forwards + adjoint (JAX-MPM Remark 5's
trade-off decided by size). The kept step buffers are the path's shared pool; a second kept rollout
alive at the same time gets buffers of its own.

Non-finite adjoints: after each segment's backward pass a device-side check flags non-finite entries
of the adjoints of the segment's start state and of the controls (a non-finite adjoint anywhere in
the segment that matters for the gradient reaches them). Only then is the segment's backward pass
replayed with a check after every step; the last-flagged step (the first one the backward pass met)
is reported as a ``GradientError`` naming that step and the first particle (scene order) whose
adjoint is non-finite. Nothing is zeroed. (Checking every step always cost ~15 % of a gradient.)

Kernels are compiled on first use only (forward-only runs build none of them).
"""

import weakref
from functools import lru_cache
from types import SimpleNamespace

import numpy as np
import warp as wp

from ...core.budget import resolve_segment
from ...core.errors import ConfigError, GradientError, SimulationDiverged
from . import adjoints as ADJ
from . import kernels as K
from .types import warp_types

#: Steps per recomputed segment when ``observe`` is not given one.
DEFAULT_SEGMENT = 100

#: Adjoint of P2G on the tape: ``"hand"`` (``adjoints.py``: a per-particle gather registered with
#: ``Tape.record_func``) or ``"generated"`` (Warp's generated adjoint of the forward kernel). Both give
#: the same gradient (to rounding, ``tests/test_warp_adjoints.py``); a ``GradPath`` copies this at
#: construction and its ``adjoints`` attribute can be changed afterwards.
ADJOINTS = "hand"
ADJOINT_KINDS = ("hand", "generated")


def _active_tape():
    """The ``wp.Tape`` being recorded, or None (Warp keeps it in its runtime; no public accessor in 1.19)."""
    try:
        return wp._src.context.runtime.tape
    except AttributeError:                  # another Warp layout: fall back to the generated adjoints
        return None


# ---- kernels ----------------------------------------------------------------------------------------
@lru_cache(maxsize=None)
def finite_kernels(dim: int, precision: str):
    """flags[slot] = 1 where an array holds a non-finite entry (one kernel per element type)."""
    T = warp_types(dim, precision)
    scalar, vec, mat = T.scalar, T.vec, T.mat

    @wp.kernel(module="unique")
    def check_scalar(a: wp.array(dtype=scalar), flags: wp.array(dtype=int), slot: int):
        i = wp.tid()
        if not wp.isfinite(a[i]):
            flags[slot] = 1

    @wp.kernel(module="unique")
    def check_vec(a: wp.array(dtype=vec), flags: wp.array(dtype=int), slot: int):
        i = wp.tid()
        for k in range(dim):
            if not wp.isfinite(a[i][k]):
                flags[slot] = 1

    @wp.kernel(module="unique")
    def check_mat(a: wp.array(dtype=mat), flags: wp.array(dtype=int), slot: int):
        i = wp.tid()
        for k in range(dim):
            for l in range(dim):
                if not wp.isfinite(a[i][k, l]):
                    flags[slot] = 1

    @wp.kernel(module="unique")
    def check_2d(a: wp.array2d(dtype=scalar), flags: wp.array(dtype=int), slot: int):
        i, j = wp.tid()
        if not wp.isfinite(a[i, j]):
            flags[slot] = 1

    return {scalar: check_scalar, vec: check_vec, mat: check_mat, "2d": check_2d}


# ---- the path ---------------------------------------------------------------------------------------
class GradPath:
    """The differentiable rollout of one ``WarpStepper`` (built once per stepper, on first use)."""

    def __init__(self, st):
        self.st = st
        T, D, prec, dev = st.T, st.dim, st.precision, st.device
        self.T, self.dim, self.dev = T, D, dev
        tr = st.transfer
        scene = st.scene
        self.N, self.G = st.particles.count, st.node_count
        self.split = st.split_force
        self.affine = tr.needs_affine
        #: CPDI: the particles' domains flow through the per-step state like x, v, C (not a control: the
        #: initial domain is a constant, ``initial_domain()``); the hand-written adjoints do not cover the
        #: corner loops, so the tape records Warp's generated adjoints of the same kernels
        self.corners = bool(getattr(st, "corners", False))
        # boundaries, in scene order: each one's tape-safe Warp implementation (``tape()`` of its factory,
        # backends/warp/boundaries.py documents the protocol) and its differentiable data
        self.bcs = []
        self.wall_kind = wp.array(np.asarray([K.WALL_CODES["none"]] * (2 * D), np.int32), dtype=int, device=dev)
        self.thickness = 1
        for b in scene.boundaries:
            impl = b.implementation("warp", "boundary")(b, scene, st)
            if not callable(getattr(impl, "tape", None)):
                raise ConfigError(f"boundary '{b.name}' has no differentiable Warp implementation (its Warp factory "
                                  f"gives no tape()); use the JAX backend for gradients through it.")
            bc = impl.tape()
            bc.name, bc.b = b.name, b
            if bc.stage == "walls":
                self.wall_kind = wp.array(np.asarray(bc.codes, np.int32), dtype=int, device=dev)
                self.thickness = int(bc.thickness)
            self.bcs.append(bc)
        self.has_ext = any(bc.stage == "particle_force" for bc in self.bcs)
        # P2G: the fast path's kernel in its atomic form (one grid, atomic adds: what CUDA runs), which is
        # tape-safe; the bounding box it skips is a dummy here
        self.k_p2g = K.p2g_kernel(D, prec, st.warp_transfer, self.has_ext, atomic=True, shape=st.shape)
        self.bbox = wp.zeros(2, dtype=T.ivec, device=dev)
        self.k_grid = K.grid_update_kernel(D, prec, self.split, tape=True)   # the fast path's, tape-safe form
        self.k_g2p = st.k_g2p
        self.k_laws = st.k_laws
        self.k_finite = finite_kernels(D, prec)
        self.k_guard = K.guard_kernel(D, prec)
        self.k_corner_guard = K.corner_guard_kernel(D, prec) if self.corners else None
        self.empty_domain = wp.zeros(1, dtype=T.mat, device=dev)
        self.flag = wp.zeros(1, dtype=int, device=dev)
        self.gvec = K.grid_vec_type(D, prec)
        self.empty_vec = wp.zeros(1, dtype=T.vec, device=dev)
        self.empty_C = wp.zeros(1, dtype=T.mat, device=dev)
        #: per group: the law's generated types (state fields and their Warp dtypes, weight shapes)
        self.law_types = [k.types for k in st.k_laws]
        self._obs_cache = {}
        self.adjoints = "generated" if self.corners else ADJOINTS
        #: steps run by :meth:`step` since construction (forward, recomputed and recorded alike): the tests
        #: use it to check that ``segment="auto"`` skips the recomputation
        self.steps_run = 0
        self._pool_owner = None             # weakref to the kept recording that holds the step buffers
        self._pool_generation = 0           # bumped whenever the shared step buffers are taken

    @property
    def adjoints(self):
        return self._adjoints

    @adjoints.setter
    def adjoints(self, kind):
        if kind not in ADJOINT_KINDS:
            raise ConfigError(f"adjoints = {kind!r}: use one of {ADJOINT_KINDS}.")
        if kind == "hand" and self.corners:
            raise ConfigError("adjoints = 'hand': the hand-written Warp adjoints do not cover CPDI's corner P2G / "
                              "G2P; use 'generated' (Warp's generated adjoints, the default for shape cpdi).")
        self._adjoints = kind

    @property
    def k_p2g_adj(self):
        k = self.__dict__.get("_k_p2g_adj")
        if k is None:
            k = self.__dict__["_k_p2g_adj"] = ADJ.p2g_adjoint_kernels(self.dim, self.st.precision,
                                                                        self.st.warp_transfer, self.has_ext,
                                                                        shape=self.st.shape)
        return k

    def k_g2p_adj(self, i: int):
        """Group i's G2P + law kernel with the hand-written stencil adjoint (compiled on first use)."""
        ks = self.__dict__.setdefault("_k_g2p_adj", {})
        if i not in ks:
            ks[i] = ADJ.g2p_adjoint_kernel(self.st.groups[i].law, self.dim, self.st.precision, self.st.warp_transfer,
                                           shape=self.st.shape)
        return ks[i]

    def p2g_adj_scratch(self):
        """Scratch of the hand-written P2G adjoint: its (unused) output and the seed 1 of its adjoint."""
        sc = self.__dict__.get("_p2g_scratch")
        if sc is None:
            T, dev, N = self.T, self.dev, self.N
            sc = SimpleNamespace(out=wp.zeros(N, dtype=T.scalar, device=dev), f=wp.zeros(1, dtype=T.vec, device=dev),
                                 ones=wp.full(N, value=T.scalar(1.0), dtype=T.scalar, device=dev))
            self.__dict__["_p2g_scratch"] = sc
        return sc

    # ---- controls -----------------------------------------------------------------------------------
    def controls(self):
        import torch

        st, P = self.st, self.st.particles
        dt = torch.float64 if st.precision == "fp64" else torch.float32
        dev = _torch_device(self.dev)
        t = lambda a: torch.tensor(np.asarray(a, float), dtype=dt, device=dev)
        out = {"x": t(P.x), "v": t(P.v), "law": tuple(t(g.params) for g in st.groups),
               "law_weights": tuple({k: t(a) for k, a in g.weights.items()} for g in st.groups),
               "law_state": tuple({k: t(a) for k, a in g.initial_state(st.dim).items()} for g in st.groups),
               "boundary": tuple({k: t(a) for k, a in bc.params.items()} for bc in self.bcs),
               "gravity": t(st.scene.gravity), "mass": t(P.mass), "volume": t(P.volume)}
        if self.affine:
            out["C"] = t(st.initial_C())
        return out

    def flatten(self, c):
        """Control tensors in a fixed order, with their names (for errors) and shapes. ``law_weights``,
        ``law_state`` and ``C`` are optional: missing ones take the laws' weights and the scene's initial
        state (the bodies' initial F and C; else F = I, C = 0)."""
        missing = {"x", "v", "law", "boundary", "gravity", "mass", "volume"} - set(c)
        if missing:
            raise ConfigError(f"controls lack {sorted(missing)}; start from stepper.controls() and replace entries.")
        if len(c["law"]) != len(self.st.groups) or len(c["boundary"]) != len(self.bcs):
            raise ConfigError(f"controls have {len(c['law'])} law and {len(c['boundary'])} boundary entries; this "
                              f"scene has {len(self.st.groups)} material groups and {len(self.bcs)} boundaries.")
        groups = self.st.groups
        defaults = None
        if not {"law_weights", "law_state"} <= set(c) or (self.affine and "C" not in c):
            defaults = self.controls()
        names, flat = ["x", "v"], [c["x"], c["v"]]
        for i, a in enumerate(c["law"]):
            names.append(f"law[{i}]"); flat.append(a)
        for key in ("law_weights", "law_state"):
            entries = c[key] if key in c else defaults[key]
            if len(entries) != len(groups):
                raise ConfigError(f"controls['{key}'] has {len(entries)} entries; this scene has {len(groups)} "
                                  f"material groups.")
            for i, (g, d, L) in enumerate(zip(groups, entries, self.law_types)):
                want = list(L.weight_shapes) if key == "law_weights" else [n for n, _, _ in L.fields]
                if set(d) != set(want):
                    raise ConfigError(f"controls['{key}'][{i}] (law '{g.law.name}') has {sorted(d)}; the law "
                                      f"declares {sorted(want)}.")
                for k in want:
                    names.append(f"{key}[{i}].{k}"); flat.append(d[k])
        if self.affine:
            names.append("C"); flat.append(c["C"] if "C" in c else defaults["C"])
        for i, (bc, d) in enumerate(zip(self.bcs, c["boundary"])):
            for k in bc.params:
                if k not in d:
                    raise ConfigError(f"controls['boundary'][{i}] ({bc.name}) lacks '{k}'.")
                names.append(f"boundary[{i}].{k}"); flat.append(d[k])
        for k in ("gravity", "mass", "volume"):
            names.append(k); flat.append(c[k])
        return names, flat

    def to_warp(self, names, flat, grad: bool):
        """Warp arrays over the control tensors (zero-copy where dtype and layout allow)."""
        import torch

        T, D, N = self.T, self.dim, self.N
        dt = torch.float64 if self.st.precision == "fp64" else torch.float32
        dev = _torch_device(self.dev)
        out = SimpleNamespace(law=[], bc=[{} for _ in self.bcs])

        def arr(item, dtype, shape):
            name, tensor = item
            a = torch.as_tensor(tensor).detach().to(device=dev, dtype=dt)
            if a.numel() != int(np.prod(shape)):
                raise ConfigError(f"control '{name}' has shape {tuple(a.shape)}; this scene needs {shape} "
                                  f"(the shape stepper.controls() gives).")
            a = a.reshape(shape).contiguous()
            if not grad:
                return wp.from_torch(a, dtype=dtype, requires_grad=False)
            return wp.from_torch(a, dtype=dtype, requires_grad=True, grad=torch.zeros_like(a))

        it = iter(zip(names, flat))
        out.x = arr(next(it), T.vec, (N, D))
        out.v = arr(next(it), T.vec, (N, D))
        for g in self.st.groups:
            out.law.append(arr(next(it), T.scalar, (g.count, len(g.law.params))))
        out.weights = [{k: arr(next(it), T.scalar, s) for k, s in L.weight_shapes.items()} for L in self.law_types]
        out.weights_struct = [L.weights(w) for L, w in zip(self.law_types, out.weights)]
        out.law_state = [{n: arr(next(it), d, (g.count,) + shape) for n, d, shape in L.fields}
                         for g, L in zip(self.st.groups, self.law_types)]
        out.C = arr(next(it), T.mat, (N, D, D)) if self.affine else None
        for i, bc in enumerate(self.bcs):
            for k, a in bc.params.items():
                if bc.param_kinds.get(k, "scalar") == "vec":
                    out.bc[i][k] = arr(next(it), T.vec, (1, D))
                else:
                    out.bc[i][k] = arr(next(it), T.scalar, (max(1, int(np.size(a))),))
        out.gravity = arr(next(it), T.vec, (1, D))
        out.mass = arr(next(it), T.scalar, (N,))
        out.volume = arr(next(it), T.scalar, (N,))
        return out

    def control_arrays(self, ctl):
        """(name, array, kind) of every control, for the non-finite checks."""
        out = [("x", ctl.x, "particle"), ("v", ctl.v, "particle")]
        for i, a in enumerate(ctl.law):
            out.append((f"law[{i}]", a, ("group", i)))
        for i, d in enumerate(ctl.weights):
            for k, a in d.items():
                out.append((f"law_weights[{i}].{k}", a, None))
        for i, d in enumerate(ctl.law_state):
            for k, a in d.items():
                out.append((f"law_state[{i}].{k}", a, ("group", i)))
        if self.affine:
            out.append(("C", ctl.C, "particle"))
        for i, d in enumerate(ctl.bc):
            for k, a in d.items():
                out.append((f"boundary[{i}].{k}", a, None))
        out += [("gravity", ctl.gravity, None), ("mass", ctl.mass, "particle"), ("volume", ctl.volume, "particle")]
        return out

    # ---- one step -----------------------------------------------------------------------------------
    def initial(self, ctl, grad: bool):
        """State 0 from the controls: x, v, C and the law state are the control arrays themselves; tau
        from the law state."""
        T, dev = self.T, self.dev
        C = ctl.C if self.affine else self.empty_C
        tau = wp.zeros(self.N, dtype=T.mat, device=dev, requires_grad=grad)
        domain = self.empty_domain
        if self.corners:                # a constant (not a control); its adjoint is computed and dropped
            domain = wp.array(self.st.initial_domain(), dtype=T.mat, device=dev, requires_grad=grad)
        law = [dict(a) for a in ctl.law_state]
        for i, (g, st, k) in enumerate(zip(self.st.groups, law, self.k_laws)):
            wp.launch(k.stress, dim=g.count, inputs=[*self.st._law_args(i, st, ctl.law[i], ctl.weights_struct[i]),
                                                     g.start, tau], device=dev)
        return SimpleNamespace(x=ctl.x, v=ctl.v, C=C, law=law, tau=tau, domain=domain)

    def alloc_state(self, grad: bool):
        T, dev, N = self.T, self.dev, self.N
        z = lambda n, dtype: wp.zeros(n, dtype=dtype, device=dev, requires_grad=grad)
        law = [{n: z(g.count, d) for n, d, _ in L.fields} for g, L in zip(self.st.groups, self.law_types)]
        return SimpleNamespace(x=z(N, T.vec), v=z(N, T.vec), C=z(N, T.mat) if self.affine else self.empty_C,
                               law=law, tau=z(N, T.mat), domain=z(N, T.mat) if self.corners else self.empty_domain)

    def alloc_buffers(self, grad: bool):
        """Every array one step writes (its output state, grids, boundary outputs), allocated once and
        reused: allocating them per step cost ~15 % of a gradient (Python-side, ~50 us per array)."""
        T, dev, N, G = self.T, self.dev, self.N, self.G
        z = lambda n, dtype: wp.zeros(n, dtype=dtype, device=dev, requires_grad=grad)
        return SimpleNamespace(
            state=self.alloc_state(grad), grid_mm=z(G, self.gvec), grid_f=z(G if self.split else 1, T.vec),
            grid_v=z(G, T.vec), grid_v_old=z(G if self.split else 1, T.vec),
            ext=z(N, T.vec) if self.has_ext else self.empty_vec,
            bc_out=[z(G, T.vec) for bc in self.bcs if bc.stage == "grid"],
            pv=[(z(N, T.vec), z(N, T.vec)) for bc in self.bcs if bc.stage == "particle_velocity"])

    def grad_buffers(self, count: int):
        """``count`` step buffers with gradients, kept between calls (allocating a segment's worth
        costs about as much as a 2000-step forward pass); :meth:`release_buffers` frees them."""
        pool = self.__dict__.setdefault("_grad_pool", [])
        while len(pool) < count:
            pool.append(self.alloc_buffers(True))
        return pool[:count]

    def release_buffers(self):
        self.__dict__.pop("_grad_pool", None)

    def buffer_arrays(self, buf):
        """The arrays of ``buf`` that carry gradients."""
        out = [buf.grid_mm, buf.grid_f, buf.grid_v, buf.grid_v_old, buf.ext, *buf.bc_out,
               *(a for xv in buf.pv for a in xv)]
        out += [a for _, a, _ in self.state_arrays(buf.state)]
        return [a for a in out if a.requires_grad]

    def zero_grads(self, buf):
        for a in self.buffer_arrays(buf):
            a.grad.zero_()

    def step(self, s, ctl, t: float, grad: bool, buf=None):
        """One step from state s at time t into a fresh state (or into ``buf``, from
        :meth:`alloc_buffers`, which must not hold s); every launch lands on the active tape."""
        st, dev, N, G = self.st, self.dev, self.N, self.G
        if buf is None:
            buf = self.alloc_buffers(grad)
        else:                               # atomically accumulated or partly written: clear
            buf.grid_mm.zero_()
            if self.split:
                buf.grid_f.zero_()
                buf.grid_v_old.zero_()
            if self.has_ext:
                buf.ext.zero_()
        ext = self.empty_vec
        if self.has_ext:
            ext = buf.ext
            for bc, c in zip(self.bcs, ctl.bc):
                if bc.stage == "particle_force":
                    bc.force(ext, c, t, ctl, s.x)
        self.steps_run += 1
        grid_mm, grid_f = buf.grid_mm, buf.grid_f
        p2g_in = [s.x, s.v, s.C, s.tau, ctl.mass, ctl.volume, ext, st.lp, st.origin, st.dx_s, st.dt_s,
                  st.transfer_scalars, st.strides, 0, 0, grid_mm, grid_f, self.bbox, 0, s.domain]
        tape = _active_tape() if (grad and self._adjoints == "hand") else None
        if tape is not None and grid_mm.requires_grad:
            # the forward off the tape, its hand-written adjoint (a gather, adjoints.py) on it
            wp.launch(self.k_p2g, dim=N, inputs=p2g_in, device=dev, record_tape=False)
            tape.record_func(ADJ.RecordedP2G(self, p2g_in, s, ctl, ext, grid_mm, grid_f),
                             arrays=[grid_mm] + ([grid_f] if self.split else []))
        else:
            wp.launch(self.k_p2g, dim=N, inputs=p2g_in, device=dev)
        grid_v, grid_v_old = buf.grid_v, buf.grid_v_old
        zero = self.T.ivec()
        wp.launch(self.k_grid, dim=G, inputs=[grid_mm, grid_f, 1, G, 0, zero, zero, st.dt_s, self.T.vec(), ctl.gravity,
                                              st.shape_iv, st.strides, self.wall_kind, self.thickness, grid_v, grid_v_old],
                  device=dev)
        outs = iter(buf.bc_out)
        for bc, c in zip(self.bcs, ctl.bc):
            if bc.stage != "grid":
                continue
            out = next(outs)
            bc.grid(grid_v, out, c, t)
            grid_v = out
        o = SimpleNamespace(**vars(buf.state))
        for i, (g, k, ls, lo) in enumerate(zip(st.groups, self.k_g2p, s.law, o.law)):
            g2p_in = [s.x, s.v, grid_v, grid_v_old, st.origin, st.dx_s, st.dt_s, st.strides, st.transfer_scalars,
                      st.lp, g.start, 0, *st._law_args(i, ls, ctl.law[i], ctl.weights_struct[i]),
                      o.x, o.v, o.C, self.law_types[i].state_arrays(lo), o.tau, s.domain, o.domain]
            if tape is not None and grid_v.requires_grad:
                # the forward off the tape, the adjoint with the hand-written stencil part on it
                wp.launch(k, dim=g.count, inputs=g2p_in, device=dev, record_tape=False)
                tape.record_func(ADJ.RecordedG2P(self, k, self.k_g2p_adj(i), g.count, g2p_in, grid_v, grid_v_old),
                                 arrays=[grid_v] + ([grid_v_old] if self.split else []))
            else:
                wp.launch(k, dim=g.count, inputs=g2p_in, device=dev)
        t_end = t + st.dt
        pv = iter(buf.pv)
        for bc, c in zip(self.bcs, ctl.bc):
            if bc.stage != "particle_velocity":
                continue
            x2, v2 = next(pv)
            if bc.particles(s.x, o.x, o.v, c, t_end, st.dt_s, x2, v2):
                o.x, o.v = x2, v2
        return o

    def state_arrays(self, s):
        """(field, array, first particle) of a state's differentiable arrays, scene order."""
        out = [("x", s.x, 0), ("v", s.v, 0)]
        if self.affine:
            out.append(("C", s.C, 0))
        if self.corners:
            out.append(("domain", s.domain, 0))
        for g, d in zip(self.st.groups, s.law):
            for k, a in d.items():
                out.append((k, a, g.start))
        out.append(("tau", s.tau, 0))
        return out

    def clone(self, s, grad: bool = False):
        c = lambda a: wp.clone(a, requires_grad=grad)
        return SimpleNamespace(x=c(s.x), v=c(s.v), C=c(s.C) if self.affine else self.empty_C,
                               law=[{k: c(a) for k, a in d.items()} for d in s.law], tau=c(s.tau),
                               domain=c(s.domain) if self.corners else self.empty_domain)

    # ---- observations -------------------------------------------------------------------------------
    def observer(self, observation):
        key = id(observation)
        hit = self._obs_cache.get(key)
        if hit is None or hit[0] is not observation:
            impl = observation.implementation("warp", "observation")(observation, self.st)
            hit = self._obs_cache[key] = (observation, impl)
        return hit[1]

    # ---- rollout and its adjoint --------------------------------------------------------------------
    def bytes_per_step(self) -> int:
        """What one kept step costs (``segment="auto"``): every array of its step buffer
        (:meth:`alloc_buffers`: output state, grids, boundary outputs) and its gradient, measured on a
        buffer allocated once (no gradients) and doubled; the tapes' bookkeeping is not counted."""
        b = self.__dict__.get("_bytes_per_step")
        if b is None:
            buf = self.alloc_buffers(False)
            arrays = [buf.grid_mm, buf.grid_f, buf.grid_v, buf.grid_v_old, buf.ext, *buf.bc_out,
                      *(a for xv in buf.pv for a in xv)] + [a for _, a, _ in self.state_arrays(buf.state)]
            b = self.__dict__["_bytes_per_step"] = 2 * int(sum(a.capacity for a in arrays))
        return b

    def _take_pool(self, count: int):
        """(``count`` step buffers with gradients, token): the kept pool (:meth:`grad_buffers`) and its
        new generation number, unless a kept recording (``segment="auto"``) whose first backward pass has
        not run yet holds it; then fresh buffers and token None."""
        owner = self._pool_owner() if self._pool_owner is not None else None
        if owner is not None and owner.busy:
            return [self.alloc_buffers(True) for _ in range(count)], None
        self._pool_generation += 1
        return self.grad_buffers(count), self._pool_generation

    def _record(self, ctl, k0, k1, start, times, want, obs, pool, guard=False):
        """Steps k0 -> k1 under one ``wp.Tape`` per step (the initial state's stress and observation on
        ``init_tape`` when ``start`` is None, i.e. k0 = 0), observations of the steps in ``want``."""
        L, d = obs.shape
        ovec = wp.types.vector(d, self.T.scalar)
        init_tape = wp.Tape()
        if start is None:
            with init_tape:
                s = self.initial(ctl, grad=True)
        else:
            s = start
        if guard:
            self._guard(s, k0)
        states, tapes, outs = [s], [], {}
        if k0 == 0 and 0 in want:
            with init_tape:
                outs[0] = wp.zeros(L, dtype=ovec, device=self.dev, requires_grad=True)
                obs.launch(s, outs[0])
        for k in range(k0 + 1, k1 + 1):
            tape = wp.Tape()
            with tape:
                s = self.step(s, ctl, times[k - 1], grad=True, buf=pool[k - k0 - 1])
                if k in want:
                    outs[k] = wp.zeros(L, dtype=ovec, device=self.dev, requires_grad=True)
                    obs.launch(s, outs[k])
            tapes.append(tape)
            states.append(s)
            if guard:
                self._guard(s, k)
        return _Record(k0=k0, k1=k1, init_tape=init_tape, states=states, tapes=tapes, outs=outs, pool=pool)

    def forward(self, names, flat, observation, steps, segment, keep=False):
        """Observations [T, L, d] (a torch tensor) and what the backward pass needs: the saved
        segment-start states, or with ``keep`` the whole rollout recorded on tapes (one segment of all
        the steps; the backward pass then recomputes nothing)."""
        import torch

        obs = self.observer(observation)
        L, d = obs.shape
        n = int(steps[-1])
        want = {int(k): i for i, k in enumerate(steps)}
        tdt = torch.float64 if self.st.precision == "fp64" else torch.float32
        out = torch.empty((len(steps), L, d), dtype=tdt, device=_torch_device(self.dev))
        times, t = [], 0.0
        for _ in range(n):
            times.append(t)
            t = t + self.st.dt            # accumulated like the fast path's state.t (boundary windows)
        if keep:
            ctl = self.to_warp(names, flat, grad=True)
            pool, token = self._take_pool(n)
            rec = self._record(ctl, 0, n, None, times, want, obs, pool, guard=True)
            rec.token, rec.busy = token, True
            for k, o in rec.outs.items():
                out[want[k]] = wp.to_torch(o).reshape(L, d).clone()
            saved = SimpleNamespace(saved={}, times=times, record=rec, ctl=ctl)
            if token is not None:
                self._pool_owner = weakref.ref(rec)
            return out, saved
        ctl = self.to_warp(names, flat, grad=False)
        s = self.initial(ctl, grad=False)
        self._guard(s, 0)
        saved = {}
        pool = [self.alloc_buffers(False), self.alloc_buffers(False)] if n else []   # ping-pong
        for k in range(n + 1):
            if k in want:
                o = wp.zeros(L, dtype=wp.types.vector(d, self.T.scalar), device=self.dev)
                obs.launch(s, o)
                out[want[k]] = wp.to_torch(o).reshape(L, d)
            if k == n:
                break
            if k % segment == 0 and k > 0:
                saved[k] = self.clone(s)
            s = self.step(s, ctl, times[k], grad=False, buf=pool[k % 2])
            self._guard(s, k + 1)
        return out, SimpleNamespace(saved=saved, times=times, record=None, ctl=None)

    def backward(self, names, flat, observation, steps, segment, saved, grad_out):
        """Gradients (torch tensors, one per flat control) of sum(grad_out * observations)."""
        import torch

        if not torch.isfinite(grad_out).all():
            T_, L_ = grad_out.shape[:2]
            bad = torch.nonzero(~torch.isfinite(grad_out.reshape(T_, L_, -1)).all(dim=2))[0].tolist()
            raise GradientError(int(steps[bad[0]]), -1, f"observation[{bad[0]}, {bad[1]}]",
                                "the incoming gradient of the observations (from the loss) is non-finite")
        obs = self.observer(observation)
        L, d = obs.shape
        ovec = wp.types.vector(d, self.T.scalar)
        kept = saved.record
        if kept is not None and kept.token is not None and kept.token != self._pool_generation:
            raise RuntimeError("observe(segment='auto'): this kept Warp rollout's step buffers were reused by a "
                               "later gradient before this backward pass; run its backward passes before the next "
                               "gradient, or give an integer segment.")
        ctl = saved.ctl if kept is not None else self.to_warp(names, flat, grad=True)
        ctl_arrays = self.control_arrays(ctl)
        if kept is not None:                            # a repeated backward pass (retain_graph) starts afresh
            for _, a, _ in ctl_arrays:
                a.grad.zero_()
        n = int(steps[-1])
        want = {int(k): i for i, k in enumerate(steps)}
        g_out = grad_out.detach().to(device=_torch_device(self.dev)).contiguous()
        times = saved.times
        adj_end = None                                  # adjoint of the current segment's end state
        if kept is not None:
            starts, segment = [0], max(n, 1)            # the whole rollout, recorded by the forward pass
        else:
            starts = list(range(0, n, segment)) or [0]    # segment start steps (n = 0: one empty segment)
            pool = self._take_pool(min(segment, n))[0]    # one per step of a segment
        for k0 in reversed(starts):
            k1 = min(k0 + segment, n)
            if kept is not None:
                rec = kept
            else:
                start = None if k0 == 0 else self.clone(saved.saved[k0], grad=True)
                rec = self._record(ctl, k0, k1, start, times, want, obs, pool)
            init_tape, states, tapes, outs = rec.init_tape, rec.states, rec.tapes, rec.outs
            before = [wp.clone(a.grad) for _, a, _ in ctl_arrays]   # finite: checked after the later segment

            def run_backward(flags):
                """Seed and run this segment's tapes backwards; with ``flags``, check every step's adjoints."""
                for buf in rec.pool[: k1 - k0]:
                    self.zero_grads(buf)
                for a in [a for _, a, _ in self.state_arrays(states[0]) if a.requires_grad]:
                    a.grad.zero_()
                for (_, a, _), g in zip(ctl_arrays, before):    # after: segment 0 starts from x, v themselves
                    a.grad.assign(g)
                # seed: the later segment's adjoint of our end state, and the observations' cotangents
                if adj_end is not None:
                    for (_, a, _), g in zip(self.state_arrays(states[-1]), adj_end):
                        a.grad.assign(g)
                for k, o in outs.items():
                    o.grad.assign(wp.from_torch(g_out[want[k]].reshape(L, d), dtype=ovec))
                for k in range(k1, k0, -1):
                    tapes[k - k0 - 1].backward()
                    if flags is not None:
                        self._flag(states[k - k0 - 1], ctl_arrays, flags, k - k0)
                if k0 == 0:
                    init_tape.backward()
                    if flags is not None:
                        self._flag(None, ctl_arrays, flags, 0)

            # one non-finite check per segment (start-state and control adjoints: a non-finite adjoint
            # anywhere in the segment reaches them); only when it fires is the segment replayed with a
            # check after every step, to name the step and particle
            try:
                run_backward(None)
                flag = wp.zeros(1, dtype=int, device=self.dev)
                self._flag(states[0] if k0 > 0 else None, ctl_arrays, flag, 0)
                if flag.numpy()[0]:
                    flags = wp.zeros(k1 - k0 + 1, dtype=int, device=self.dev)
                    run_backward(flags)
                    f = flags.numpy()
                    slot = int(np.nonzero(f)[0].max()) if f.any() else 0
                    self._raise(k0 + slot, states[slot - 1] if slot > 0 else None, ctl_arrays)
            finally:
                if kept is not None:
                    # the buffers may be taken again; a further backward pass through this recording
                    # (retain_graph) is still exact until they are (checked by the generation above)
                    kept.busy = False
            adj_end = [wp.clone(a.grad) for _, a, _ in self.state_arrays(states[0])] if k0 > 0 else None
            del tapes, states, outs, init_tape, rec
        grads = []
        for (name, a, _), t in zip(ctl_arrays, flat):
            g = wp.to_torch(a.grad).clone()
            grads.append(g.reshape(torch.as_tensor(t).shape))
        return grads

    def _guard(self, s, step: int):
        """Raise SimulationDiverged if a position/velocity is non-finite or left the domain interior:
        checked after every step, because the next P2G would index the grid with it."""
        st = self.st
        self.flag.zero_()
        wp.launch(self.k_guard, dim=self.N, inputs=[s.x, s.v, st.lo, st.hi, self.flag], device=self.dev)
        if self.corners:                # CPDI: the domains' corners too
            wp.launch(self.k_corner_guard, dim=self.N, inputs=[s.x, s.domain, st.lo, st.hi, self.flag], device=self.dev)
        if not self.flag.numpy()[0]:
            return
        npstate = {"x": s.x.numpy().astype(np.float64), "v": s.v.numpy().astype(np.float64)}
        if self.corners:
            npstate["domain"] = s.domain.numpy().astype(np.float64)
        bad = st.locate_failure(npstate)
        p, field, value = bad if bad is not None else (-1, "x", "?")
        raise SimulationDiverged(step, p, field, value, "in the forward pass of observe(); check the controls "
                                                        "(a non-finite or extreme value) and the time step")

    def _flag(self, s, ctl_arrays, flags, slot):
        arrays = [a for _, a, _ in (self.state_arrays(s) if s is not None else []) if a.requires_grad]
        arrays += [a for _, a, _ in ctl_arrays]
        for a in arrays:
            k = self.k_finite["2d"] if (a.ndim == 2 and a.dtype == self.T.scalar) else \
                (self.k_finite.get(a.dtype) if a.ndim == 1 else None)
            if k is not None:
                wp.launch(k, dim=a.shape, inputs=[a.grad, flags, slot], device=self.dev)
            elif not np.all(np.isfinite(a.grad.numpy())):     # other shapes (weights, declared fields): on the host
                f = flags.numpy().copy()
                f[slot] = 1
                flags.assign(f)

    def _raise(self, step, s, ctl_arrays):
        """GradientError at ``step`` naming the first particle whose adjoint is non-finite."""
        if s is not None:
            for field, a, first in self.state_arrays(s):
                if not a.requires_grad:
                    continue
                g = a.grad.numpy().reshape(a.shape[0], -1)
                bad = ~np.all(np.isfinite(g), axis=1)
                if bad.any():
                    raise GradientError(step, first + int(np.argmax(bad)), field)
        for name, a, kind in ctl_arrays:
            g = a.grad.numpy().reshape(a.shape[0], -1)
            bad = ~np.all(np.isfinite(g), axis=1)
            if bad.any():
                i = int(np.argmax(bad))
                if kind == "particle":
                    raise GradientError(step, i, name)
                if isinstance(kind, tuple):
                    raise GradientError(step, self.st.groups[kind[1]].start + i, name)
                raise GradientError(step, -1, name)
        raise GradientError(step, -1, "state")


class _Record(SimpleNamespace):
    """A recorded segment (a class of its own: the path keeps a weak reference to a kept one)."""


def _torch_device(dev) -> str:
    d = str(dev)
    return "cpu" if d.startswith("cpu") else d


# ---- torch bridge --------------------------------------------------------------------------------------
def _function():
    import torch

    class Observe(torch.autograd.Function):
        """Observations of a Warp rollout; backward recomputes segments under ``wp.Tape``s."""

        @staticmethod
        def forward(ctx, path, names, observation, steps, segment, keep, *flat):
            # keep (segment="auto" and it fits): record the forward on tapes now, but only when a gradient
            # can be asked for (a forward under torch.no_grad() records nothing)
            keep = keep and any(ctx.needs_input_grad[6:])
            out, saved = path.forward(names, flat, observation, steps, segment, keep)
            ctx.path, ctx.names, ctx.observation, ctx.steps, ctx.segment = path, names, observation, steps, segment
            ctx.saved = saved
            ctx.save_for_backward(*flat)
            return out

        @staticmethod
        def backward(ctx, grad_out):
            flat = ctx.saved_tensors
            grads = ctx.path.backward(ctx.names, flat, ctx.observation, ctx.steps, ctx.segment, ctx.saved, grad_out)
            grads = [g if need else None for g, need in zip(grads, ctx.needs_input_grad[6:])]
            return (None, None, None, None, None, None, *grads)

    return Observe


_OBSERVE = None


def path_of(stepper) -> GradPath:
    p = stepper.__dict__.get("_grad_path")
    if p is None:
        p = stepper.__dict__["_grad_path"] = GradPath(stepper)
    return p


def controls(stepper) -> dict:
    """The differentiable inputs of a rollout (``AbstractStepper.controls``) as torch tensors."""
    return path_of(stepper).controls()


def observe(stepper, c: dict, observation, steps, segment: int | str | None = None):
    """[T, L, d] torch tensor: ``observation`` of the rollout from controls ``c`` after each of ``steps``
    (sorted; 0 = the initial state); differentiable w.r.t. every control tensor that requires grad.

    ``segment``: steps per recomputed segment of the backward pass (None: ``DEFAULT_SEGMENT``), or
    ``"auto"``: when every step's buffers fit the memory budget (``mpmlab.core.budget.resolve_segment``
    with :meth:`GradPath.bytes_per_step`), the forward pass records the whole rollout on tapes and the
    backward pass recomputes nothing (cost forward + adjoint instead of 2 forwards + adjoint); else
    segments of ``DEFAULT_SEGMENT``."""
    import torch

    global _OBSERVE
    if _OBSERVE is None:
        _OBSERVE = _function()
    path = path_of(stepper)
    s = np.asarray(steps, dtype=np.int64).reshape(-1)
    if s.size == 0 or s[0] < 0 or np.any(np.diff(s) <= 0):
        raise ConfigError("observation steps must be non-empty, non-negative and strictly increasing.")
    if isinstance(segment, str):
        segment, keep = resolve_segment(segment, int(s[-1]), path.bytes_per_step(), default=DEFAULT_SEGMENT)
    else:
        segment, keep = int(segment or DEFAULT_SEGMENT), False    # 0 / None: the default, as before
        if segment < 1:
            raise ConfigError(f"segment = {segment} must be >= 1 step.")
    names, flat = path.flatten(c)
    flat = [f if isinstance(f, torch.Tensor) else torch.as_tensor(np.asarray(f, float)) for f in flat]
    keep = keep and torch.is_grad_enabled()        # (inside the Function's forward, grad mode is always off)
    return _OBSERVE.apply(path, tuple(names), observation, tuple(int(k) for k in s), segment, keep, *flat)
