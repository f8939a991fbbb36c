"""``WarpReducedStepper``: the reduced model (Chen et al. 2023, Sec. 3, Alg. 2; ``mpmlab.rom.stepper``)
on the Warp backend. The networks and the projections run in batched torch (``networks_torch``,
``manifold_torch``); the MPM step is the full-order Warp stepper's own (``WarpStepper._step_into``:
its P2G, grid update, walls, grid and particle boundaries and G2P, and the law's ``stress`` kernel
for tau), fed with the pseudo-particles g(X; x_hat), dg/dx_hat v_hat, F = dg/dX and the Lagrangian
quadrature's masses, written into Warp arrays (zero-copy from torch where the device allows).

What it has of the JAX ``ReducedStepper``: both quadratures, both projections (Algs. 3-7) and both tangents, the seeded
sample draws with the kinematic boundaries' forced points, Eq. 19's initial state, ``rollout`` with the
full-order guard's test and ``to_numpy``. The Lagrangian quadrature steps the scene's own Warp stepper;
the Eulerian one a second Warp stepper of the same scene over its fixed-size point set (the JAX stepper's budget of
lattice points, then the samples; the torch inverse map ``manifold_torch.inverse_map``), the scene's kinematic
boundaries applied to the samples, its grid update over the samples' windows' nodes only (``nodes="compact"``,
the default: ``backends/warp/node_list.py``; ``"scene"``: the bounding box of the nodes reached). Same inputs give the same steps: the conformance test replays the
JAX stepper's draws (``draws=``) and compares the latent trajectories.

``rollout_fn`` is the reduced rollout as a torch function, differentiable by autograd in x_hat_0 and the
law parameters: torch through g and the projections, and each Warp step a ``torch.autograd.Function``
over the stepper's tape-safe path (``backends/warp/grad.py``), as ``ReducedStepper.rollout_fn`` is by
``jax.grad``.
The sample draws are numpy's (``default_rng((seed, step))``), not JAX's: a Warp and a JAX run with the
same seed draw different points unless ``draws`` replays one's on the other.
"""
from __future__ import annotations

import contextlib
from types import SimpleNamespace

import numpy as np

from ..core.errors import ConfigError
from .kinematic import hold
from .stepper import EULER_CAPACITY, ReducedState, _ReducedBase


@contextlib.contextmanager
def _torch_threads(n):
    """torch's intra-op thread count set to ``n`` inside (None: unchanged), restored after."""
    import torch

    if n is None:
        yield
        return
    old = torch.get_num_threads()
    torch.set_num_threads(int(n))
    try:
        yield
    finally:
        torch.set_num_threads(old)


def _row_major_strides(shape):
    """The strides of a C-ordered array of ``shape`` (an int64 tensor): (s_1 s_2 .., .., s_{d-1}, 1)."""
    import torch

    return torch.cat([shape[1:], torch.ones(1, dtype=shape.dtype, device=shape.device)]).flip(0).cumprod(0).flip(0)


class WarpReducedStepper(_ReducedBase):
    """The reduced model of a scene on Warp (module doc). ``fom``: a Warp full-order stepper of the scene
    with the ``pic`` transfer; ``weights``: ``mpmlab.rom.networks.RomWeights``; ``draws``: optional sample
    rows, one array per step (e.g. ``ReducedStepper.draws``), instead of the seeded numpy draws;
    ``torch_threads``: torch's intra-op threads during a step (default 1: a reduced step's tensors are
    small, and on the CPU torch's thread pool made them up to 40x slower on a busy machine, measured;
    None leaves torch's setting)."""

    backend_name = "warp"

    def __init__(self, fom, weights, *, samples: int = 50, quadrature: str = "lagrangian",
                 projection: str = "linear", per_boundary: int = 5, seed: int = 0, draws=None,
                 torch_threads: int | None = 1, eulerian_capacity: float = EULER_CAPACITY, tangent: str = "next",
                 nodes: str = "compact", kinematic: str = "position", hold_steps: float = 1.0):
        import torch
        import warp as wp

        from . import networks_torch as NT

        self._check(fom, weights, samples, quadrature, projection, per_boundary, seed, eulerian_capacity, tangent, nodes,
                    kinematic, hold_steps)
        self._threads = None if torch_threads is None or fom.device.startswith("cuda") else int(torch_threads)
        self.tdtype = torch.float64 if fom.precision == "fp64" else torch.float32
        self.tdevice = torch.device("cuda", wp.get_device(fom.device).ordinal) if fom.device.startswith("cuda") \
            else torch.device("cpu")
        kw = {"dtype": self.tdtype, "device": self.tdevice}
        self.params = NT.to_torch(weights.params, **kw)
        self.norm = NT.to_torch(weights.norm, **kw)
        P = fom.particles
        self.X = torch.as_tensor(np.asarray(P.x), **kw)
        self._base0 = torch.as_tensor(np.asarray(self.scene.origin), **kw)
        self._mass0 = torch.as_tensor(np.asarray(P.mass), **kw)
        self._vol0 = torch.as_tensor(np.asarray(P.volume), **kw)
        self._forced_t = torch.as_tensor(self._forced, device=self.tdevice)
        self._free_t = torch.as_tensor(self._free_np, device=self.tdevice)
        self._hold_of = torch.as_tensor(self._holds.which, device=self.tdevice)
        self._hold_params = [{k: torch.as_tensor(np.asarray(v, float), **kw) for k, v in
                              (("velocity", b.velocity), ("angular_velocity", b.angular_velocity), ("center", c))
                              if v is not None} for b, c in zip(self._holds.bcs, self._holds.centers)]
        self._draws = None if draws is None else [np.array(m, np.int64) for m in draws]
        # one input and one output Warp state for every step: the stepper's recorded launches are reused.
        # The input's ``order`` carries this step's quadrature masses (P2G reads order.mass / order.vol).
        self._in, self._out = fom._alloc(), fom._alloc()
        self._in.order = SimpleNamespace(perm=None, mass=wp.empty_like(fom.mass), vol=wp.empty_like(fom.vol),
                                         params=fom.law_params)
        self._in.age = 0
        if quadrature == "eulerian":
            self._setup_eulerian()

    def _setup_eulerian(self):
        """Alg. 4's fixed parts (``_eulerian_layout``) as torch tensors, and a second Warp stepper of the same
        scene over the quadrature's fixed-size point set (its budget of lattice points, then the samples): the
        same kernels and walls, no particle boundaries (the step applies the scene's to the samples)."""
        import copy
        import dataclasses

        import torch
        import warp as wp

        from ..backends.warp.stepper import WarpStepper
        from ..core.scene import MaterialGroup, ParticleSet

        e = self._eulerian_layout()
        kw = {"dtype": self.tdtype, "device": self.tdevice}
        d, Q = self.dim, e.q_size + self.samples
        self._eu = SimpleNamespace(
            rho0=e.rho0, Vq=e.Vq, h=e.h, vox_lo=torch.as_tensor(e.vox_lo, device=self.tdevice),
            vox_shape=torch.as_tensor(e.vox_shape, device=self.tdevice), occupied=torch.as_tensor(e.occupied, device=self.tdevice),
            box=(torch.as_tensor(e.box_lo, **kw), torch.as_tensor(e.box_hi, **kw)),
            q_off=torch.as_tensor(e.q_off, device=self.tdevice), q_lattice=torch.as_tensor(e.q_lattice, device=self.tdevice),
            q_size=e.q_size, inv_tol=e.inv_tol)
        g = self.fom.groups[0]
        sc = copy.copy(self.scene)
        # the grid boundaries as the scene's: a grid grip (grid_velocity) takes its rotation centre and its
        # "holds a particle" check from the particles at t = 0, which the pseudo-particles are not, so its
        # centre is pinned to the real one and the pseudo-particles start on the real particles' positions,
        # one of each grip's first (they are massless, and every step overwrites them)
        X = np.asarray(self.fom.particles.x)
        sc.boundaries, first = [], []
        for b in self.scene.boundaries:
            if getattr(b, "stage", "") == "particle_velocity":
                continue
            if getattr(b, "stage", "") == "grid" and hasattr(b, "rotation_center"):
                first.append(int(np.asarray(b.select(X))[0]))
                b = dataclasses.replace(b, center=tuple(float(c) for c in b.rotation_center(X)))
            sc.boundaries.append(b)
        order = np.concatenate([first, np.setdiff1d(np.arange(len(X)), first)]).astype(np.int64)
        zeros = np.zeros(Q)
        sc.__dict__["_particles"] = ParticleSet(
            x=np.resize(X[order], (Q, d)), v=np.zeros((Q, d)), mass=zeros, volume=zeros,
            body_id=np.zeros(Q, np.int64), material_id=np.zeros(Q, np.int64),
            groups=[MaterialGroup(g.law, 0, Q, np.tile(np.asarray(e.law_row, float), (Q, 1)), g.weights)])
        fom = self.fom
        self._pseudo = ps = WarpStepper(sc, fom.transfer, fom.precision, device=fom.device, threads=1)
        ps._set_dt(fom.dt)
        if self.nodes == "compact":     # the grid update over the samples' windows' nodes only (node_list.py)
            from ..backends.warp.node_list import NodeList
            from .stepper import sample_window

            low, width = sample_window(ps.shape.offset, ps.shape.width)
            self._window_low = low
            ps.node_list = NodeList(d, self.scene.grid_shape, width, self.samples, device=ps.device)
        self._q_in, self._q_out = ps._alloc(), ps._alloc()
        self._q_in.order = SimpleNamespace(perm=None, mass=wp.empty_like(ps.mass), vol=wp.empty_like(ps.vol),
                                           params=ps.law_params)
        self._q_in.age = 0
        # the samples' kinematic boundaries run on scene-indexed scratch arrays (start, end positions, velocity),
        # allocated once and never cleared: a step writes the sample rows and the boundaries' kernels touch
        # their own points only, so a step costs O(|M| + prescribed points), not O(N); the rows it reads
        # back (M) are always freshly written, and the other rows only ever hold finite values
        n = fom.particles.count
        self._kb = [wp.zeros(n, dtype=fom.T.vec, device=fom.device) for _ in range(3)] if fom.particle_bcs else None

    # ---- torch <-> warp ---------------------------------------------------------------------------
    def _write(self, dst, src):
        import warp as wp

        wp.copy(dst, wp.from_torch(src.contiguous(), dtype=dst.dtype))

    def _np(self, a):
        return a.detach().cpu().numpy() if hasattr(a, "detach") else np.asarray(a)

    # ---- state ------------------------------------------------------------------------------------
    def init(self):
        """Eq. 19 from the scene's initial positions and velocities."""
        import torch

        from . import manifold_torch as MT
        from . import networks_torch as NT

        P = self.fom.particles
        kw = {"dtype": self.tdtype, "device": self.tdevice}
        x0, v0 = torch.as_tensor(np.asarray(P.x), **kw), torch.as_tensor(np.asarray(P.v), **kw)
        with torch.no_grad(), _torch_threads(self._threads):
            if self.weights.spec.n_points == len(P.x) and "e_fc1_W" in self.params:
                guess = NT.encode(self.params, self.norm, x0.T)
            else:
                guess = torch.zeros(self.weights.spec.latent, **kw)
            s = MT.initial_state(self.params, self.norm, self.X, x0, v0, guess)
        zero = torch.zeros((), dtype=torch.int32)
        return ReducedState(s.z, s.zdot, s.z, 0.0, 0, zero, zero, zero)

    def _q_budget(self):
        return self._eu.q_size

    def _sample(self, k: int):
        """The sample rows of step ``k`` (module doc)."""
        import torch

        if self._draws is not None:
            if k >= len(self._draws):
                raise ConfigError(f"WarpReducedStepper: step {k + 1} has no sample rows ({len(self._draws)} draws given).")
            return torch.as_tensor(self._draws[k], device=self.tdevice)
        pick = np.random.default_rng((self.seed, k)).choice(len(self._free_np), self._n_random, replace=False)
        return torch.cat([self._forced_t, self._free_t[torch.as_tensor(pick, device=self.tdevice)]])

    def _lagrangian(self, s, M):
        """Alg. 3 and Alg. 5 on the scene's own stepper: every material point at g(X; x_hat), its own mass
        where it shares a node with a sample; returns the samples' trial (x, v) and the point counts."""
        import torch
        import warp as wp

        from . import networks_torch as NT

        fom, dx = self.fom, self.scene.dx
        x, F, v = NT.g_state(self.params, self.norm, self.X, s.z[None, :], s.zdot)
        base = torch.floor((x - self._base0) / dx - 0.5).to(torch.int64)
        near = torch.all(torch.abs(base[:, None, :] - base[M][None, :, :]) <= 2, dim=-1)
        quad = torch.any(near, dim=1).to(self.tdtype)
        a = self._in
        self._write(a.x, x)
        self._write(a.v, v)
        self._write(a.order.mass, self._mass0 * quad)
        self._write(a.order.vol, self._vol0 * quad)
        for i, (g, k) in enumerate(zip(fom.groups, fom.k_laws)):
            st = a.law[i]
            self._write(st["F"], F[g.start:g.stop])
            wp.launch(k.stress, dim=g.count, inputs=[*fom._law_args(i, st), g.start, a.tau], device=fom.device)
        a.t = float(s.t)
        fom._step_into(a, self._out)              # P2G, grid update, boundaries, G2P (Alg. 5)
        return x[M], wp.to_torch(self._out.x)[M], wp.to_torch(self._out.v)[M], (s.outside, s.unconverged, 0)

    def _eulerian(self, s, M):
        """Alg. 4 and Alg. 5 on the quadrature's stepper (as ``ReducedStepper._eulerian_points``): lattice
        points on the cells around the samples, X_q by the inverse map, m_q = rho_0 V_q / J_q; the samples
        are massless rows after them; then the scene's kinematic boundaries on the samples."""
        import torch
        import warp as wp

        from . import manifold_torch as MT
        from . import networks_torch as NT
        from .stepper import INVERSE_HALVINGS, INVERSE_ITERATIONS

        e, d, dx, z = self._eu, self.dim, self.scene.dx, s.z
        dev = self.tdevice
        XM = self.X[M]
        xM, FM, vM = NT.g_state(self.params, self.norm, XM, z[None, :], s.zdot)
        base = torch.floor((xM - self._base0) / dx - 0.5).to(torch.int64)
        j = (2 * base[:, None, :] + e.q_off[None]).reshape(-1, d)
        inside_grid = torch.all((j >= 0) & (j < e.q_lattice), dim=1)
        strides = _row_major_strides(e.q_lattice)
        sentinel = int(torch.prod(e.q_lattice))
        ids = torch.where(inside_grid, (j * strides).sum(1), sentinel)
        uniq, inv = torch.unique(ids, sorted=True, return_inverse=True)
        pos = torch.arange(ids.shape[0], device=dev)
        first = torch.full(uniq.shape, ids.shape[0], dtype=torch.int64, device=dev).scatter_reduce(0, inv, pos, "amin")
        distinct = int(uniq.shape[0]) - int(bool(uniq[-1] == sentinel))
        uniq, first = uniq[:e.q_size], first[:e.q_size]          # beyond the budget: dropped and counted
        pad = e.q_size - uniq.shape[0]
        uniq = torch.cat([uniq, torch.full((pad,), sentinel, dtype=torch.int64, device=dev)])
        first = torch.cat([first, torch.zeros(pad, dtype=torch.int64, device=dev)])
        real = uniq < sentinel
        flat = torch.where(real, uniq, 0)
        jq = torch.stack([(flat // strides[k]) % e.q_lattice[k] for k in range(d)], -1)
        xq = self._base0 + (jq.to(self.tdtype) / 2 + 0.25) * dx
        src = first // e.q_off.shape[0]                                           # the sample it came from
        guess = XM[src] + torch.linalg.solve(FM[src], (xq - xM[src])[..., None])[..., 0]
        iv = MT.inverse_map(self.params, self.norm, xq, z, guess, iterations=INVERSE_ITERATIONS, tol=e.inv_tol,
                            halvings=INVERSE_HALVINGS, bounds=e.box)
        vox = torch.floor((iv.X - self._base0) / e.h).to(torch.int64) - e.vox_lo
        in_box = torch.all((vox >= 0) & (vox < e.vox_shape), dim=1)
        vstr = _row_major_strides(e.vox_shape)
        vflat = (torch.minimum(torch.clamp(vox, min=0), e.vox_shape - 1) * vstr).sum(1)
        in_body = in_box & e.occupied[vflat]
        _, Fq, vq = NT.g_state(self.params, self.norm, iv.X, z[None, :], s.zdot)
        Jq = torch.linalg.det(Fq)
        converged = iv.converged & (Jq > 0)
        ok = real & in_body & converged
        V0 = torch.where(ok, e.Vq / torch.where(ok, Jq, torch.ones_like(Jq)), torch.zeros_like(Jq))
        x = torch.cat([xq, xM])
        v = torch.cat([vq, vM])
        eye = torch.eye(d, dtype=self.tdtype, device=dev)
        F = torch.cat([torch.where(ok[:, None, None], Fq, eye), FM])
        vol = torch.cat([V0, torch.zeros(M.shape[0], dtype=self.tdtype, device=dev)])
        ps, a = self._pseudo, self._q_in
        self._write(a.x, x)
        self._write(a.v, v)
        self._write(a.order.mass, e.rho0 * vol)
        self._write(a.order.vol, vol)
        st = a.law[0]
        self._write(st["F"], F)
        wp.launch(ps.k_laws[0].stress, dim=x.shape[0], inputs=[*ps._law_args(0, st), 0, a.tau], device=ps.device)
        a.t = float(s.t)
        self._pseudo_step(base)
        rows = slice(e.q_size, e.q_size + M.shape[0])
        x0, v_tr = x[rows], wp.to_torch(self._q_out.v)[rows]
        x_tr = x0 + self.dt * v_tr
        if self._kb is not None:                  # the scene's particle_velocity boundaries on the samples
            xs, xe, vs = self._kb
            wp.to_torch(xs)[M] = x0
            wp.to_torch(xe)[M] = x_tr
            wp.to_torch(vs)[M] = v_tr
            for bc in self.fom.particle_bcs:
                bc.apply_particles(vs, xs, xe, float(s.t) + self.dt)
            x_tr, v_tr = wp.to_torch(xe)[M], wp.to_torch(vs)[M]
        counts = (torch.sum(real & ~in_body).to(torch.int32), torch.sum(real & in_body & ~converged).to(torch.int32),
                  torch.tensor(max(distinct - e.q_size, 0), dtype=torch.int32))
        return x0, x_tr, v_tr, counts

    def _pseudo_step(self, base) -> None:
        """Alg. 5 on the quadrature's pseudo-particles (written into ``_q_in``): the Warp MPM step into ``_q_out``.
        On the compact node set its grid update visits the windows around the samples' base nodes ``base``
        ([|M|, D] ints) only: every point's stencil lies in its sample's window (``sample_window``)."""
        nl = self._pseudo.node_list
        if nl is not None:
            nl.claim_windows(base + self._window_low)
        self._pseudo._step_into(self._q_in, self._q_out)
        if nl is not None:
            nl.release()

    def step(self, s: ReducedState) -> ReducedState:
        import torch

        from . import manifold_torch as MT

        M = self._sample(int(s.key))
        with torch.no_grad(), _torch_threads(self._threads):
            points = self._eulerian if self.quadrature == "eulerian" else self._lagrangian
            x_M, x_tr, v_tr, counts = points(s, M)
            x_tr, v_step = self._held(M, x_M, x_tr, v_tr, float(s.t) + self.dt)
            z, vhat = self._project(MT, self.X[M], s.z, s.z_prev, x_tr, v_tr, v_step)
        return ReducedState(z, vhat, s.z, float(s.t) + self.dt, int(s.key) + 1, counts[0], counts[1],
                            torch.maximum(torch.as_tensor(s.overflow, dtype=torch.int32), torch.as_tensor(counts[2], dtype=torch.int32)))

    # ---- the differentiable reduced rollout (issue 16, item 7) ---------------------------------------
    @property
    def law_params(self):
        """The scene's law parameters as torch tensors, one [count, P] per material group: the ``law``
        argument of :meth:`rollout_fn`."""
        import torch

        return tuple(torch.as_tensor(np.asarray(g.params), dtype=self.tdtype, device=self.tdevice)
                     for g in self.fom.groups)

    def rollout_fn(self, steps: int, every: int = 1):
        """The reduced rollout as a torch function ``f(z0, zdot0, law) -> z [steps // every + 1, d_hat]``,
        differentiable by torch autograd in the initial latent state and the law parameters (``law``: as
        :attr:`law_params`), as ``ReducedStepper.rollout_fn`` is by ``jax.grad``. Each Warp step is one
        ``torch.autograd.Function`` over the stepper's tape-safe path (``backends/warp/grad.py``: P2G,
        grid update, boundaries, G2P, the law's stress), recorded on a ``wp.Tape`` and replayed backward;
        g, the quadrature and the projections are torch. The sample draws are the stepper's (seeded or
        ``draws``), so f is deterministic. Lagrangian quadrature only (the Eulerian one's inverse map is
        forward-mode only on JAX too)."""
        import torch

        if self.quadrature != "lagrangian":
            raise ConfigError("ReducedStepper.rollout_fn: the differentiable reduced rollout uses the Lagrangian "
                              "quadrature (the Eulerian inverse map is a data-dependent Newton loop); build the "
                              "stepper with quadrature 'lagrangian'.")
        steps, every = int(steps), max(1, int(every))
        if steps < every or steps % every:
            raise ConfigError(f"ReducedStepper.rollout_fn: steps = {steps} must be a positive multiple of every = {every}.")
        self._diff_setup()

        def f(z0, zdot0, law):
            with _torch_threads(self._threads):
                z, zdot, zp, out = z0, zdot0, z0, [z0]
                for k in range(steps):
                    zn, zdot = self._diff_step(z, zdot, zp, k * self.dt, self._sample(k), tuple(law))
                    zp, z = z, zn
                    if (k + 1) % every == 0:
                        out.append(z)
                return torch.stack(out)

        return f

    def _diff_setup(self):
        from ..backends.warp import grad as WG

        if getattr(self, "_path", None) is None:
            self._path = WG.path_of(self.fom)
            c = self._path.controls()
            self._ctl_defaults = {k: c[k] for k in ("law_weights", "boundary", "gravity")}

    def _diff_step(self, z, zdot, z_prev, t, M, law):
        """One reduced step (Lagrangian quadrature) in torch autograd: (x_hat_{n+1}, v_hat_{n+1})."""
        import torch

        from . import manifold_torch as MT
        from . import networks_torch as NT

        x, F, v = NT.g_state(self.params, self.norm, self.X, z[None, :], zdot)
        with torch.no_grad():                      # the quadrature set: piecewise constant in x
            base = torch.floor((x - self._base0) / self.scene.dx - 0.5).to(torch.int64)
            quad = torch.any(torch.all(torch.abs(base[:, None, :] - base[M][None, :, :]) <= 2, dim=-1), dim=1)
        quad = quad.to(self.tdtype)
        Fs = [F[g.start:g.stop] for g in self.fom.groups]
        x_new, v_new = _warp_step().apply(self, float(t), x, v, self._mass0 * quad, self._vol0 * quad, *Fs, *law)
        x_tr, v_step = self._held(M, x[M], x_new[M], v_new[M], float(t) + self.dt)
        return self._project(MT, self.X[M], z, z_prev, x_tr, v_new[M], v_step)

    def _held(self, M, x_M, x_tr, v_tr, t1):
        """The position-level hold on the samples (``mpmlab.rom.kinematic.hold``): the boundaries' own velocities,
        the rotation R(theta) on the host (t1 is a number here), by the Warp boundaries' ``_rotate_host``."""
        import torch

        from ..backends.warp.boundaries import _rotate_host

        def rotation(theta):              # _rotate_host rotates rows: the rotated identity is R^T
            R = _rotate_host(np.eye(self.dim), np.asarray(theta.detach().cpu(), float)).T
            return torch.as_tensor(R, dtype=self.tdtype, device=self.tdevice)
        return hold(self._holds, torch, rotation, self._hold_of[M], self.X[M], x_M, x_tr, v_tr, t1, self._hold_params,
                    self.dt)

    def _positions(self, z):
        import torch

        from . import networks_torch as NT

        with torch.no_grad(), _torch_threads(self._threads):
            zt = torch.as_tensor(z, dtype=self.tdtype, device=self.tdevice)
            x, F = NT.g_F(self.params, self.norm, self.X, zt[None, :])
            return self._np(x), self._np(torch.linalg.det(F))

    def to_numpy(self, state, X=None) -> dict[str, np.ndarray]:
        """x, F, v at reference points ``X`` [Q, d] (default: the scene's material points) and x_hat."""
        import torch

        from . import networks_torch as NT

        with torch.no_grad(), _torch_threads(self._threads):
            Xq = self.X if X is None else torch.as_tensor(np.asarray(X), dtype=self.tdtype, device=self.tdevice)
            x, F, v = NT.g_state(self.params, self.norm, Xq, state.z[None, :], state.zdot)
        return {"x": self._np(x), "F": self._np(F), "v": self._np(v), "z": self._np(state.z), "t": float(state.t)}


_WARP_STEP = None


def _warp_step():
    """``torch.autograd.Function``: one Warp MPM step of pseudo-particles, (x, v, mass, volume, F per group,
    law parameters per group) -> (x, v) after the step, differentiable in all of them (a ``wp.Tape``
    over the full-order stepper's tape-safe path)."""
    global _WARP_STEP
    if _WARP_STEP is not None:
        return _WARP_STEP
    import torch
    import warp as wp

    class WarpStep(torch.autograd.Function):
        @staticmethod
        def forward(ctx, rom, t, x, v, mass, vol, *rest):
            path = rom._path
            G = len(path.st.groups)
            c = dict(rom._ctl_defaults, x=x, v=v, mass=mass, volume=vol, law=tuple(rest[G:]),
                     law_state=tuple({"F": F} for F in rest[:G]))
            names, flat = path.flatten(c)
            ctl = path.to_warp(names, flat, grad=True)
            tape = wp.Tape()
            with tape:
                o = path.step(path.initial(ctl, grad=True), ctl, t, grad=True)
            ctx.tape, ctx.ctl, ctx.o, ctx.G = tape, ctl, o, G
            ctx.shapes = [a.shape for a in (x, v, mass, vol, *rest)]
            return wp.to_torch(o.x).clone(), wp.to_torch(o.v).clone()

        @staticmethod
        def backward(ctx, gx, gv):
            o, ctl, G = ctx.o, ctx.ctl, ctx.G
            tape = ctx.tape
            tape.backward(grads={o.x: wp.from_torch(gx.contiguous(), dtype=o.x.dtype),
                                 o.v: wp.from_torch(gv.contiguous(), dtype=o.v.dtype)})
            arrays = [ctl.x, ctl.v, ctl.mass, ctl.volume, *(d["F"] for d in ctl.law_state), *ctl.law]
            grads = [wp.to_torch(a.grad).reshape(sh).clone() for a, sh in zip(arrays, ctx.shapes)]
            tape.zero()
            ctx.tape = ctx.ctl = ctx.o = None
            return (None, None, *grads)

    _WARP_STEP = WarpStep
    return WarpStep
