"""``ReducedStepper``: MPM time-stepping of the latent x_hat only (Chen et al. 2023, Sec. 3, Alg. 2):
each step evaluates the full-space kinematics from the deformation map g at quadrature points, runs
one MPM step (P2G, grid update, boundaries, G2P) at a few sample points M, and projects the trial
positions and velocities back onto the manifold.

Built on a full-order JAX stepper of the same scene (``build_stepper(scene, "jax", "pic", ...)``): its
own pure ``step_fn`` is the MPM step, fed with pseudo-particles -- positions g(X; x_hat), velocities
dg/dx_hat v_hat, deformation gradients F = dg/dX as the law state, and per-step masses and volumes --
so P2G, the grid update, every boundary, G2P and the law's ``kirchhoff`` are the backend's, not copies.

* **Quadrature** ``lagrangian`` (Alg. 3): the material points that share a grid node with a sample
  point (their B-spline stencils, base nodes within 2 cells per axis, overlap), with their own mass and
  volume; every other point gets zero mass, so the nodes the samples read carry exactly what the full
  P2G puts there. Its cost grows with the body (every point's position is needed to find the
  neighbours), as the paper says.
* **Quadrature** ``eulerian`` (Alg. 4, Eq. 20): 2 points per axis in each grid cell whose points reach
  a node of the samples' stencils (10 per axis around each sample, deduplicated), V_q = V_c / 2^d, at
  the cell's quarter points. Each point's undeformed X_q solves g(X_q; x_hat) = x_q (Newton with
  backtracking, ``manifold.inverse_map``, from the nearest sample's linearisation); its F and v come
  from g at X_q, its mass is rho_0 V_q / J_q and its reference volume V_q / J_q (so V^0 tau = V_q
  sigma). Points whose X_q lies outside the reference body (the voxels of side V_p^{1/d} of the
  material points) or whose inversion did not converge get zero mass and are counted
  (``ReducedState.outside`` / ``unconverged``). The cost is set by |M|, not by the body, up to a
  fixed budget of min(|M| 10^d, ``eulerian_capacity`` x the body's footprint at t = 0) point slots (the
  samples' cells overlap: at |M| = 50 most of the 50 10^d slots were padding, each costing an inverse
  map); a step needing more stops the rollout with a ConfigError. P2G, the grid update (with every grid
  boundary) and G2P run on a compact node set (``nodes="compact"``, the default): one window of 7^d nodes
  per sample, holding its points' stencils, the copies of a node shared by windows summed
  (``backends/jax/node_windows.py``), so a step costs nothing of the grid's size and its time does not
  grow with the body (``benchmarks/rom_speed.py``); ``nodes="scene"`` runs them on the scene's grid (the
  same steps to round-off). The Warp stepper's Eulerian quadrature still uses the scene's grid.
* **Projection** ``linear`` (Alg. 7, Eq. 23) or ``nonlinear`` (Alg. 6, Eqs. 21-22: Gauss-Newton with
  Armijo backtracking from 2 x_hat_n - x_hat_{n-1}); ``mpmlab.rom.manifold``.
* **Tangent** of the velocity least squares: ``next`` (default) fits v_hat_{n+1} with dg/dx_hat at the
  new latent x_hat_{n+1}, the tangent space in which the next step evaluates v = dg/dx_hat v_hat (as
  RATTLE projects a constrained velocity at the new position); ``current`` uses dg/dx_hat(x_hat_n) as the
  paper's Eqs. 21 and 23 write it ("the discretization of the Jacobian is explicit"). With the explicit
  Jacobian the carried velocity changes by (dg/dx_hat(x_hat_{n+1}) - dg/dx_hat(x_hat_n)) v_hat each step
  with no force doing it: as dt -> 0 the scheme tends to x_hat_ddot = J^+ a, without the -J^+ J_dot
  x_hat_dot term of the reduced Euler-Lagrange equation, so on a curved manifold it gains or loses
  kinetic energy at any dt (benchmarks/rom.md, "The explicit Jacobian gains energy"). The linear projection still steps
  x_hat_{n+1} = x_hat_n + dt v_hat with the explicit fit (Alg. 7), then refits v_hat at x_hat_{n+1}.
* **Samples** M: ``samples`` points drawn anew every step, uniformly without replacement from a seeded
  key, plus at least ``per_boundary`` (5) points of each kinematic boundary (Sec. 3.3; a boundary that
  declares ``kinematic``): a particle_velocity region, or the particles initially inside a grid_velocity
  box (a grip or a poke).
* **Initial state** (Eq. 19): x_hat(0), v_hat(0) fitted to the scene's initial positions and
  velocities, from the encoder's latent when the weights have one (else zero).
* PIC only and hyperelastic laws only (F must be a function of the deformation map): others refused.

One reduced step is one compiled JAX program (``jax.jit``); ``rollout`` keeps x_hat and the points'
positions every ``every`` steps; ``to_numpy(state, X)`` gives x, F and v at any reference points.
The Warp counterpart is ``mpmlab.rom.stepper_warp.WarpReducedStepper`` (Lagrangian quadrature);
``reduced_stepper(fom, weights, ...)`` picks the one of the full-order stepper's backend.
"""
from __future__ import annotations

import inspect
import math
from types import SimpleNamespace
from typing import NamedTuple

import numpy as np

from ..core.errors import ConfigError
from ..core.interfaces import AbstractStepper
from . import manifold as Mf
from . import networks as N
from .kinematic import Holds, hold

QUADRATURES = ("lagrangian", "eulerian")
#: what the reduced model has per backend (the capability matrix, ``mpmlab.capabilities``): the rollout, and
#: its gradient ("reverse": reverse mode through ``rollout_fn``; "forward": forward mode only; None: none).
#: Both projections are available wherever a quadrature is; the Eulerian inverse map is a Newton loop with
#: a data-dependent end, which JAX differentiates in forward mode only and the Warp path not at all.
CAPABILITIES = {"lagrangian": {"jax": "reverse", "warp": "reverse"},
                "eulerian": {"jax": "forward", "warp": None}}
#: where each backend's Eulerian quadrature runs P2G, the grid update and G2P (the capability matrix)
EULERIAN_NODES = {"jax": "compact node set", "warp": "compact node set"}
#: the Eulerian quadrature's inverse map: Newton iterations and backtracking halvings per iteration
INVERSE_ITERATIONS, INVERSE_HALVINGS = 8, 10
PROJECTIONS = ("linear", "nonlinear")
#: where the velocity least squares (Eqs. 21/23) takes its Jacobian dg/dx_hat: at the new latent x_hat_{n+1}
#: ("next", the default) or at x_hat_n ("current", the paper's explicit Jacobian); module doc
TANGENTS = ("next", "current")


class ReducedState(NamedTuple):
    z: object        # [d_hat] latent x_hat_n
    zdot: object     # [d_hat] latent velocity v_hat_n
    z_prev: object   # [d_hat] x_hat_{n-1} (the nonlinear projection's extrapolation)
    t: object        # time [s]
    key: object      # PRNG key of the sample draws
    outside: object = 0       # Eulerian quadrature, last step: points outside the reference body
    unconverged: object = 0   # ... and points whose inverse map did not converge (both massless)
    overflow: object = 0      # ... and the most quadrature points any step so far lacked room for (EULER_CAPACITY)


#: Eulerian quadrature points per axis around a sample: on the half-cell lattice j (x = (j/2 + 1/4) dx),
#: the points whose B-spline stencil reaches a node of base .. base + 2 have j - 2 base in [-3, 6]
_EULER_REACH = np.arange(-3, 7)
#: the Eulerian quadrature's fixed point budget, as a multiple of the lattice points around the whole body at
#: t = 0 (``eulerian_footprint``): the samples' cells overlap, so |M| 10^d slots are mostly padding (torsion,
#: |M| = 50: 9,700-10,000 distinct points of 50,000 slots), and each slot costs an inverse map. A step that
#: needs more (the body spread) is flagged (``ReducedState.overflow``) and the rollout stops with a ConfigError.
EULER_CAPACITY = 1.5
#: where the Eulerian quadrature's P2G, grid update and G2P run: "compact", a window of nodes per sample
#: (``sample_window``; JAX: stacked dense windows, backends/jax/node_windows.py; Warp: the windows' nodes
#: listed in the scene's grid, backends/warp/node_list.py), or "scene", the scene's grid
NODE_SETS = ("compact", "scene")


#: from this many candidate points on, the samples are drawn by Floyd's algorithm (O(|M|^2), not O(N))
FLOYD_FROM = 10_000


def _floyd_sample(key, n: int, m: int):
    """m distinct indices of range(n), every m-subset equally likely (Floyd's algorithm, Bentley & Floyd
    1987): for j = n - m .. n - 1 take t ~ U{0..j}, or j itself when t is taken already. O(m^2) work."""
    import jax
    import jax.numpy as jnp

    top = jnp.arange(n - m, n)
    t = jax.random.randint(key, (m,), 0, top + 1)

    def add(i, S):
        return S.at[i].set(jnp.where(jnp.any(S == t[i]), top[i], t[i]))

    return jax.lax.fori_loop(0, m, add, jnp.full((m,), -1, top.dtype))


def sample_window(offset: float, width: int) -> tuple[int, int]:
    """(first node relative to the sample's base node, nodes per axis) of a sample's window: its quadrature
    points (j - 2 base in _EULER_REACH, x = (j/2 + 1/4) dx) have stencil bases base + floor(r/2 + 1/4 -
    offset), and their ``width``-node stencils (lowest node floor(x/dx - offset)) end ``width`` - 1 above.
    Quadratic B-splines: base - 2 .. base + 4, 7 nodes."""
    lo, hi = (int(np.floor(r / 2 + 0.25 - offset)) for r in (_EULER_REACH[0], _EULER_REACH[-1]))
    return lo, hi - lo + int(width)


def eulerian_footprint(x, origin, dx, grid_shape) -> int:
    """The number of half-cell lattice points (Alg. 4's quadrature points) whose B-spline stencils reach a
    node of the stencil of any point of ``x`` [N, d]: the Eulerian quadrature's size with every material point
    a sample. A separable box dilation of the points' base cells on the lattice (no N x 10^d array)."""
    x = np.asarray(x, float)
    d = x.shape[1]
    lattice = tuple(2 * int(a) for a in grid_shape)
    base = np.floor((x - np.asarray(origin, float)) / dx - 0.5).astype(np.int64)
    j = np.clip(2 * base, 0, np.asarray(lattice) - 1)
    occ = np.zeros(lattice, bool)
    occ[tuple(j.T)] = True
    lo, hi = int(_EULER_REACH[0]), int(_EULER_REACH[-1])
    for ax in range(d):                    # lattice point k is reached from a base at 2b in [k - hi, k - lo]
        c = np.cumsum(occ, axis=ax, dtype=np.int64)
        c = np.concatenate([np.zeros_like(np.take(c, [0], axis=ax)), c], axis=ax)   # c[i] = sum of occ[< i]
        n = occ.shape[ax]
        k = np.arange(n)
        top = np.clip(k - lo + 1, 0, n)
        bot = np.clip(k - hi, 0, n)
        occ = (np.take(c, top, axis=ax) - np.take(c, bot, axis=ax)) > 0
    return int(occ.sum())


class _ReducedBase(AbstractStepper):
    """What the JAX and the Warp reduced steppers share: the checks on the full-order stepper, the weights
    and the options (one-line ``ConfigError``s), the kinematic boundaries' forced samples, and the
    rollout with the full-order guard's test. A backend supplies ``_positions(z)`` (g at the material
    points, numpy) and ``_np`` (its arrays to numpy)."""

    backend_name = ""

    def _check(self, fom, weights, samples, quadrature, projection, per_boundary, seed, capacity=EULER_CAPACITY,
               tangent="next", nodes="compact", kinematic="position", hold_steps=1.0):
        if getattr(fom, "backend_name", "") != self.backend_name:
            raise ConfigError(f"{type(self).__name__}: the full-order stepper is on backend "
                              f"'{getattr(fom, 'backend_name', '?')}'; build it with backend '{self.backend_name}' "
                              f"(or use mpmlab.rom.stepper.reduced_stepper, which picks by the stepper's backend).")
        if fom.transfer.name != "pic":
            raise ConfigError(f"ReducedStepper: transfer '{fom.transfer.name}'; the reduced model uses PIC (Sec. 3, "
                              f"Alg. 5): build the full-order stepper with transfer 'pic'.")
        for g in fom.groups:
            if g.law.plastic or "F" not in g.law.state_fields or set(g.law.state_fields) != {"F"}:
                raise ConfigError(f"ReducedStepper: law '{g.law.name}' is not hyperelastic (its state {list(g.law.state_fields)}"
                                  f"{', plastic' if g.law.plastic else ''}); the deformation map gives F only, so only "
                                  f"laws whose whole state is F are supported (e.g. fixed_corotated).")
        if quadrature not in QUADRATURES:
            raise ConfigError(f"ReducedStepper: quadrature '{quadrature}'; choose {' or '.join(QUADRATURES)}.")
        if projection not in PROJECTIONS:
            raise ConfigError(f"ReducedStepper: projection '{projection}'; choose {' or '.join(PROJECTIONS)}.")
        if nodes not in NODE_SETS:
            raise ConfigError(f"ReducedStepper: nodes '{nodes}'; choose {' or '.join(NODE_SETS)} (where the Eulerian "
                              f"quadrature's P2G, grid update and G2P run).")
        #: the Eulerian quadrature's nodes: "compact" (windows around the samples) or "scene" (the scene's grid)
        self.nodes = nodes
        if tangent not in TANGENTS:
            raise ConfigError(f"ReducedStepper: tangent '{tangent}'; choose {' or '.join(TANGENTS)} (where the velocity "
                              f"least squares takes dg/dx_hat: at x_hat_(n+1) or, as the paper, at x_hat_n).")
        spec = weights.spec
        P = fom.particles
        n, d = P.x.shape
        if spec.dim != d:
            raise ConfigError(f"ReducedStepper: the weights are for {spec.dim}D, the scene is {d}D.")
        samples = int(samples)
        if not spec.latent <= samples <= n:
            raise ConfigError(f"ReducedStepper: samples = {samples}; it must be at least the latent size {spec.latent} "
                              f"and at most the {n} material points.")
        self.fom, self.weights, self.scene = fom, weights, fom.scene
        self.quadrature, self.projection, self.tangent = quadrature, projection, tangent
        self.dim, self.dt = d, float(fom.dt)
        # kinematic boundaries: at least per_boundary samples each (Sec. 3.3), prescribed particles or the
        # particles initially inside a grid grip's box (a poke: its nodes move the samples there)
        forced = []
        for b in self.scene.boundaries:
            if getattr(b, "kinematic", False):             # a prescribed motion (AbstractBoundary.kinematic)
                idx = np.asarray(b.select(P.x))
                forced.append(idx[:max(0, min(int(per_boundary), len(idx)))] if len(idx) else idx)
        self._forced = np.unique(np.concatenate(forced)).astype(np.int64) if forced else np.zeros(0, np.int64)
        if len(self._forced) > samples:
            raise ConfigError(f"ReducedStepper: samples = {samples} is fewer than the {len(self._forced)} points the "
                              f"kinematic boundaries need ({per_boundary} each).")
        self.samples, self.seed = samples, int(seed)
        if not float(capacity) >= 1.0:
            raise ConfigError(f"ReducedStepper: eulerian_capacity = {capacity}; it is a multiple of the body's initial "
                              f"footprint and must be at least 1 (default {EULER_CAPACITY}).")
        self._capacity = float(capacity)
        self._free_np = np.setdiff1d(np.arange(n), self._forced)
        self._n_random = samples - len(self._forced)
        #: the particle_velocity boundaries held at the position level (``kinematic``: mpmlab.rom.kinematic)
        self._holds = Holds(self.scene, np.asarray(P.x), kinematic, hold_steps)

    @property
    def kinematic(self) -> str:
        """How the particle_velocity boundaries' points are held: "position" or "velocity" (mpmlab.rom.kinematic)."""
        return self._holds.mode

    def _eulerian_layout(self) -> SimpleNamespace:
        """The fixed parts of Alg. 4, numpy: the quadrature lattice, V_q, rho_0, one law-parameter row and
        the reference body's voxels (module doc); refuses scenes it cannot carry."""
        fom, d, dx = self.fom, self.dim, self.scene.dx
        if len(fom.groups) != 1:
            raise ConfigError(f"ReducedStepper: the Eulerian quadrature needs one material group (its points take "
                              f"rho_0 and the law from it); this scene has {len(fom.groups)}: use 'lagrangian'.")
        if any(getattr(b, "stage", "") == "particle_force" for b in self.scene.boundaries):
            raise ConfigError("ReducedStepper: the Eulerian quadrature does not carry particle loads "
                              "(particle_force boundaries); use 'lagrangian'.")
        prm = np.asarray(fom.groups[0].params)
        rows = prm.reshape(-1, prm.shape[-1]) if prm.ndim else prm.reshape(1, 1)
        if np.ptp(rows, axis=0).max(initial=0.0) > 0:
            raise ConfigError("ReducedStepper: the Eulerian quadrature needs law parameters that are the same for "
                              "every material point; use 'lagrangian'.")
        P = fom.particles
        origin = np.asarray(self.scene.origin, float)
        h = float(np.mean(P.volume)) ** (1.0 / d)
        vox = np.floor((np.asarray(P.x) - origin) / h).astype(np.int64)
        lo = vox.min(0) - 1
        shape = vox.max(0) - lo + 2
        occ = np.zeros(tuple(shape), bool)
        occ[tuple((vox - lo).T)] = True
        # the fixed point budget: min(|M| 10^d slots, eulerian_capacity x the body's footprint at t = 0)
        footprint = eulerian_footprint(P.x, origin, dx, self.scene.grid_shape)
        q_size = int(min(self.samples * len(_EULER_REACH) ** d, math.ceil(self._capacity * footprint)))
        return SimpleNamespace(
            law_row=rows[0], rho0=float(np.sum(P.mass) / np.sum(P.volume)), Vq=dx ** d / 2 ** d,
            h=h, vox_lo=lo, vox_shape=tuple(int(a) for a in shape), occupied=occ.ravel(),
            # the voxels' box: an inverse-map iterate that leaves it is outside the body (no mass), and stops
            box_lo=origin + lo * h, box_hi=origin + (lo + shape) * h,
            q_off=np.stack(np.meshgrid(*[_EULER_REACH] * d, indexing="ij"), -1).reshape(-1, d),
            q_lattice=tuple(2 * int(a) for a in self.scene.grid_shape), q_size=q_size,
            inv_tol=1e-10 if self.fom.precision == "fp64" else 1e-5 * dx)

    def _project(self, mf, XM, z, z_prev, x_tr, v_tr, v_step=None):
        """The samples' trial state back onto the manifold with the backend's ``mf`` (``manifold`` or
        ``manifold_torch``): x_hat by Alg. 7 (linear: x_hat_n + dt v_hat, v_hat fitted with dg/dx_hat at
        x_hat_n) or Alg. 6 / Eq. 22 (nonlinear, from 2 z - z_prev), and v_hat by Eqs. 21/23 with dg/dx_hat
        at x_hat_{n+1} (``tangent`` "next") or x_hat_n ("current"). Returns (x_hat_{n+1}, v_hat_{n+1}).
        ``v_step``: the velocities the linear step fits where they differ from ``v_tr`` (the position-level
        hold of ``mpmlab.rom.kinematic``: held rows reach their prescribed positions); None: ``v_tr``."""
        def fit(at, v=v_tr):                  # Eqs. 21/23 with dg/dx_hat at the latent ``at``
            return mf.project_velocity(self.params, self.norm, XM, at, v)

        if self.projection == "linear":
            vhat = fit(z) if v_step is None else fit(z, v_step)
            z1 = mf.project_linear(z, vhat, self.dt)
            if self.tangent == "next":
                return z1, fit(z1)
            return z1, vhat if v_step is None else fit(z)
        z1 = mf.project_nonlinear(self.params, self.norm, XM, x_tr, z, z_prev)
        return z1, fit(z1 if self.tangent == "next" else z)

    def _np(self, a):
        return np.asarray(a)

    def _q_budget(self) -> int:
        """The Eulerian quadrature's fixed number of point slots."""
        raise NotImplementedError

    def _positions(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(g(X_p; z) [N, d], det dg/dX [N]) at the scene's material points, numpy."""
        raise NotImplementedError

    def rollout(self, state=None, steps: int = 100, every: int = 1, **kw):
        """Run ``steps`` reduced steps; returns ``{"z", "zdot": [T, d_hat], "x": [T, N, d], "time": [T]}`` (frames
        every ``every`` steps, the first one the initial state), and the final state as ``"state"``. At every
        kept frame the full-order guard's test: a non-finite x_hat, a point outside the scene's domain, or
        a folded map (J = det dg/dX <= 0 at a point, the full-order J > 0 check) raises ``SimulationDiverged``
        (an unstable time step, or a latent state the manifold does not cover), whose ``partial`` holds the
        frames kept before it (``{"z", "zdot", "time"}``, or None)."""
        from ..core.errors import SimulationDiverged

        state = self.init() if state is None else state
        every = max(1, int(every))
        lo, hi = (np.asarray(a, float) for a in self.scene.domain)
        zs, vs, xs, ts = [], [], [], []

        def keep(k, s):
            if int(s.overflow) > 0:           # a step dropped quadrature points: its result is not Alg. 4's
                raise ConfigError(f"ReducedStepper: by step {k} the Eulerian quadrature needed {int(s.overflow)} "
                                  f"points more than its {self._q_budget()} (eulerian_capacity = {self._capacity:g} x the "
                                  f"body's initial footprint): the body spread; raise eulerian_capacity.")
            # the full-order guard's test at every kept frame: finite, and every point inside the domain
            z = self._np(s.z)
            n = self.fom.particles.count
            x, J = self._positions(z) if np.all(np.isfinite(z)) else (np.full((n, self.dim), np.nan), np.full(n, np.nan))
            bad = ~np.all(np.isfinite(x) & (x >= lo) & (x <= hi), axis=1)
            if bad.any():
                p = int(np.argmax(bad))
                raise SimulationDiverged(k, p, "x", x[p].tolist(), "the reduced state left the domain or is "
                                         "non-finite; lower the time step")
            if not np.all(J > 0):
                p = int(np.argmin(J))
                raise SimulationDiverged(k, p, "J", float(J[p]), "the deformation map folded (det dg/dX <= 0): the "
                                         "latent state left what the manifold covers; lower the time step")
            zs.append(z); vs.append(self._np(s.zdot)); xs.append(x); ts.append(float(s.t))

        try:
            keep(0, state)
            for k in range(1, int(steps) + 1):
                state = self.step(state)
                if k % every == 0 or k == steps:
                    keep(k, state)
        except SimulationDiverged as e:   # the frames kept before it: what the run got right until then
            e.partial = {"z": np.stack(zs), "zdot": np.stack(vs), "time": np.asarray(ts)} if zs else None
            raise
        z, x = np.stack(zs), np.stack(xs)
        return {"z": z, "zdot": np.stack(vs), "x": x, "time": np.asarray(ts), "state": state}


def reduced_stepper(fom, weights, **kw):
    """The reduced model on the full-order stepper's backend: ``ReducedStepper`` (JAX) or
    ``mpmlab.rom.stepper_warp.WarpReducedStepper`` (Warp, networks in torch)."""
    if getattr(fom, "backend_name", "") == "warp":
        from .stepper_warp import WarpReducedStepper

        return WarpReducedStepper(fom, weights, **kw)
    return ReducedStepper(fom, weights, **kw)


class ReducedStepper(_ReducedBase):
    """The reduced model of a scene (module doc) on JAX. ``fom``: a JAX full-order stepper of the scene
    with the ``pic`` transfer; ``weights``: ``mpmlab.rom.networks.RomWeights`` (``networks.load``)."""

    backend_name = "jax"

    def __init__(self, fom, weights, *, samples: int = 50, quadrature: str = "lagrangian",
                 projection: str = "linear", per_boundary: int = 5, seed: int = 0,
                 eulerian_capacity: float = EULER_CAPACITY, tangent: str = "next", nodes: str = "compact",
                 kinematic: str = "position", hold_steps: float = 1.0):
        import jax
        import jax.numpy as jnp

        self._check(fom, weights, samples, quadrature, projection, per_boundary, seed, eulerian_capacity, tangent, nodes,
                    kinematic, hold_steps)
        self.dtype = dt = fom.dtype
        self.params = N.to_jax(weights.params, dt)
        self.norm = N.to_jax(weights.norm, dt)
        self.X = jnp.asarray(fom.particles.x, dt)
        self._free = jnp.asarray(self._free_np)
        self._forced_j = jnp.asarray(self._forced)
        self._hold_of = jnp.asarray(self._holds.which)
        self._base0 = fom._node_x[0]
        self._fom_params = dict(fom.params)          # made here, outside any trace (it is cached on the stepper)
        if quadrature == "eulerian":
            self._setup_eulerian()
        self._step = jax.jit(self._step_impl)

    def _setup_eulerian(self):
        """Alg. 4's fixed parts (``_eulerian_layout``) as JAX arrays."""
        import jax.numpy as jnp

        e = self._eulerian_layout()
        self._law_row = jnp.asarray(e.law_row, self.dtype)
        self._rho0, self._Vq = e.rho0, e.Vq
        self._vox = (e.h, jnp.asarray(e.vox_lo), e.vox_shape, jnp.asarray(e.occupied))
        self._ref_box = (jnp.asarray(e.box_lo, self.dtype), jnp.asarray(e.box_hi, self.dtype))
        self._q_off = jnp.asarray(e.q_off)
        self._q_lattice, self._q_size, self._inv_tol = e.q_lattice, e.q_size, e.inv_tol
        if self.nodes == "compact":
            from ..backends.jax.node_windows import fits
            self._window = sample_window(self.fom.shape.offset, self.fom.shape.width)
            if not fits(self.scene.grid_shape, self._window[1]):
                raise ConfigError(f"ReducedStepper: the scene's grid {self.scene.grid_shape} is too large for the compact "
                                  f"node set's 32-bit node keys; use nodes='scene'.")
            grid_stage = [b for b in self.scene.boundaries if getattr(b, "stage", "") == "grid"]   # _grid_bcs' order
            for b, bc in zip(grid_stage, self.fom._grid_bcs):
                if "node_ids" not in inspect.signature(bc.apply).parameters:
                    raise ConfigError(f"ReducedStepper: boundary '{b.name}' has no apply(..., node_ids=) for a compact "
                                      f"node set (backends/jax/boundaries.py); use nodes='scene'.")

    # ---- state ------------------------------------------------------------------------------------
    def init(self):
        """Eq. 19 from the scene's initial positions and velocities."""
        import jax
        import jax.numpy as jnp

        P = self.fom.particles
        x0, v0 = jnp.asarray(P.x, self.dtype), jnp.asarray(P.v, self.dtype)
        s = Mf.initial_state(self.params, self.norm, self.X, x0, v0, self._initial_guess(x0))
        zero = jnp.zeros((), jnp.int32)
        return ReducedState(s.z, s.zdot, s.z, jnp.asarray(0.0, self.dtype), jax.random.PRNGKey(self.seed), zero, zero,
                            zero)

    def _q_budget(self):
        return self._q_size

    def _initial_guess(self, x0):
        """Eq. 19's starting latent: the encoder's of the positions x0 when the weights have one for this
        many points, else zero."""
        import jax.numpy as jnp

        if self.weights.spec.n_points == x0.shape[0] and "e_fc1_W" in self.params:
            return N.encode(self.params, self.norm, x0.T)
        return jnp.zeros(self.weights.spec.latent, self.dtype)

    def _sample(self, key):
        import jax
        import jax.numpy as jnp

        n, m = self._free.shape[0], self._n_random
        if n < FLOYD_FROM:
            pick = jax.random.choice(key, n, (m,), replace=False)
        else:                       # choice(replace=False) permutes all n: O(N) per step, 0.55 s at 800k points
            pick = _floyd_sample(key, n, m)
        return jnp.concatenate([self._forced_j, self._free[pick]])

    def draws(self, steps: int, state=None) -> list[np.ndarray]:
        """The sample rows M that the next ``steps`` steps from ``state`` (default: the initial state) draw:
        the same seeded draws ``step`` makes (e.g. to replay them on another backend)."""
        import jax

        key, out = (self.init() if state is None else state).key, []
        for _ in range(int(steps)):
            key, sub = jax.random.split(key)
            out.append(np.asarray(self._sample(sub)))
        return out

    def _lagrangian_points(self, s, M, law=None, fom_params=None):
        """Alg. 3: every material point, with its own mass and volume where it shares a node with a sample
        (else zero); the samples are rows M. Returns (x, v, law state per group, step params, sample rows,
        (outside, unconverged, overflow) counts, zero here, and no compact node set), as ``_eulerian_points`` does."""
        import jax.numpy as jnp

        x, F, v = N.g_state(self.params, self.norm, self.X, s.z[None, :], s.zdot[None, :])
        base = jnp.floor((x - self._base0) / self.scene.dx - 0.5).astype(jnp.int32)
        near = jnp.all(jnp.abs(base[:, None, :] - base[M][None, :, :]) <= 2, axis=-1)   # [N, |M|]
        quad = jnp.any(near, axis=1).astype(self.dtype)
        prm = dict(self._fom_params if fom_params is None else fom_params)
        if law is not None:
            prm["law"] = tuple(law)
        prm["mass"] = prm["mass"] * quad
        prm["volume"] = prm["volume"] * quad
        none = jnp.zeros((), jnp.int32)
        return x, v, tuple({"F": F[g.start:g.stop]} for g in self.fom.groups), prm, M, (none, none, none), None

    def _eulerian_points(self, s, M, law=None, fom_params=None):
        """Alg. 4: quadrature points on the cells around the samples, then the samples (massless rows)."""
        import jax.numpy as jnp

        d, dx, z = self.dim, self.scene.dx, s.z
        xM, FM, vM = N.g_state(self.params, self.norm, self.X[M], z[None, :], s.zdot[None, :])
        base = jnp.floor((xM - self._base0) / dx - 0.5).astype(jnp.int32)
        j = (2 * base[:, None, :] + self._q_off[None]).reshape(-1, d)                 # [|M| 10^d, d]
        lat = jnp.asarray(self._q_lattice)
        inside_grid = jnp.all((j >= 0) & (j < lat), axis=1)
        sentinel = int(np.prod(self._q_lattice))
        ids = jnp.where(inside_grid, jnp.ravel_multi_index(tuple(j.T), self._q_lattice, mode="clip"), sentinel)
        uniq, first = jnp.unique(ids, size=self._q_size, fill_value=sentinel, return_index=True)
        srt = jnp.sort(ids)                                   # how many distinct points there were: beyond the
        distinct = jnp.sum(srt[1:] != srt[:-1]) + 1 - jnp.any(ids == sentinel)      # budget they are dropped
        real = uniq < sentinel
        jq = jnp.stack(jnp.unravel_index(jnp.where(real, uniq, 0), self._q_lattice), -1)
        xq = self._base0 + (jq.astype(self.dtype) / 2 + 0.25) * dx
        src = first // len(_EULER_REACH) ** d                                        # the sample it came from
        guess = self.X[M][src] + jnp.linalg.solve(FM[src], (xq - xM[src])[..., None])[..., 0]
        # from the sample's linearisation Newton needs few iterations; iterates that leave the reference
        # box stop there (they are massless anyway)
        h, lo, shape, occ = self._vox
        inv = Mf.inverse_map(self.params, self.norm, xq, z, guess, iterations=INVERSE_ITERATIONS, tol=self._inv_tol,
                             halvings=INVERSE_HALVINGS, bounds=self._ref_box)
        vox = jnp.floor((inv.X - self._base0) / h).astype(jnp.int32) - lo
        in_box = jnp.all((vox >= 0) & (vox < jnp.asarray(shape)), axis=1)
        in_body = in_box & occ[jnp.ravel_multi_index(tuple(vox.T), shape, mode="clip")]
        _, Fq, vq = N.g_state(self.params, self.norm, inv.X, z[None, :], s.zdot[None, :])
        Jq = jnp.linalg.det(Fq)
        converged = inv.converged & (Jq > 0)
        ok = real & in_body & converged
        V0 = jnp.where(ok, self._Vq / jnp.where(ok, Jq, 1.0), 0.0)
        n_M = M.shape[0]
        x = jnp.concatenate([xq, xM])
        v = jnp.concatenate([vq, vM])
        F = jnp.concatenate([jnp.where(ok[:, None, None], Fq, jnp.eye(d, dtype=self.dtype)), FM])
        prm = dict(self._fom_params if fom_params is None else fom_params)
        prm["volume"] = jnp.concatenate([V0, jnp.zeros(n_M, self.dtype)])
        prm["mass"] = self._rho0 * prm["volume"]
        row = self._law_row if law is None else law[0][0]           # uniform parameters (checked at set-up)
        prm["law"] = (jnp.broadcast_to(row, (x.shape[0],) + row.shape),)
        rows = jnp.arange(self._q_size, self._q_size + n_M)
        counts = (jnp.sum(real & ~in_body).astype(jnp.int32), jnp.sum(real & in_body & ~converged).astype(jnp.int32),
                  jnp.maximum(distinct - self._q_size, 0).astype(jnp.int32))
        windows = None
        if self.nodes == "compact":       # one window per sample: its points' stencils (sample_window)
            from ..backends.jax.node_windows import NodeWindows
            low, width = self._window
            windows = NodeWindows(base + low, jnp.concatenate([jnp.where(real, src, 0), jnp.arange(n_M)]).astype(
                jnp.int32), width)
        return x, v, ({"F": F},), prm, rows, counts, windows

    def _kinematic_boundaries(self, M, x0, v, t_end, boundary):
        """The scene's particle_velocity boundaries on the samples (they address material points by index):
        (trial positions, velocities) at M after the step from x0; ``boundary``: the step's boundary
        parameters (stepper order, as ``fom.params["boundary"]``)."""
        vp = vpic = v
        for bc, bp in zip(self.fom._particle_bcs, self._particle_bc_params(boundary)):
            vp, vpic = bc.apply_particles(x0, vp, vpic, t_end, self.dt, bp, rows=M)   # O(|M|), not O(N)
        return x0 + self.dt * vpic, vp

    def _particle_bc_params(self, boundary):
        """The particle_velocity boundaries' part of the step's boundary parameters (stepper order: grid,
        particle_velocity, particle_force)."""
        nb = len(self.fom._grid_bcs)
        return boundary[nb:nb + len(self.fom._particle_bcs)]

    def _step_impl(self, s: ReducedState, law=None, fom_params=None):
        """One reduced step; ``law``: the law parameters (as ``fom.params["law"]``; default the scene's);
        ``fom_params``: every step parameter of the full-order model (as ``fom.params``: masses, volumes,
        law, boundaries, gravity), e.g. from controls (``observe``); ``law`` then comes from it."""
        import jax
        import jax.numpy as jnp

        key, sub = jax.random.split(s.key)
        M = self._sample(sub)
        points = self._eulerian_points if self.quadrature == "eulerian" else self._lagrangian_points
        if fom_params is not None:
            law = fom_params["law"]
        x, v, state_law, prm, rows, counts, windows = points(s, M, law, fom_params)
        state = {"x": x, "v": v, "law": state_law, "t": s.t}
        if self.quadrature == "eulerian":             # Alg. 5 from the quadrature points; boundaries on M here
            new = self.fom.step_fn(state, prm, particle_bcs=False, update_law=False, nodes=windows)
            x_tr, v_tr = self._kinematic_boundaries(M, x[rows], new["v"][rows], s.t + self.dt, prm["boundary"])
        else:                                         # Alg. 5 over every material point (massless off P)
            new = self.fom.step_fn(state, prm, update_law=False)
            x_tr, v_tr = new["x"][rows], new["v"][rows]
        x_tr, v_step = self._held(M, x[rows], x_tr, v_tr, s.t + self.dt, prm["boundary"])
        z, vhat = self._project(Mf, self.X[M], s.z, s.z_prev, x_tr, v_tr, v_step)
        return ReducedState(z, vhat, s.z, s.t + self.dt, key, counts[0], counts[1], jnp.maximum(s.overflow, counts[2]))

    def _held(self, M, x_M, x_tr, v_tr, t1, boundary):
        """The position-level hold on the samples (``mpmlab.rom.kinematic.hold``), with the step's boundary
        parameters (stepper order, as ``fom.params["boundary"]``)."""
        import jax.numpy as jnp

        from ..backends.jax.boundaries import _rotation

        params = [dict(p, center=jnp.asarray(c, self.dtype))
                  for p, c in zip(self._particle_bc_params(boundary), self._holds.centers)]
        return hold(self._holds, jnp, lambda th: _rotation(th, self.dim), self._hold_of[M], self.X[M], x_M, x_tr, v_tr,
                    t1, params, self.dt)

    def step(self, state):
        return self._step(state)

    @property
    def law_params(self):
        """The scene's law parameters, one array per material group (rows per point, e.g. [E, nu]): the
        ``law`` argument of :meth:`rollout_fn`."""
        return self._fom_params["law"]

    def rollout_fn(self, steps: int, every: int = 1):
        """The reduced rollout as one pure JAX function ``f(z0, zdot0, law) -> z [steps // every + 1, d_hat]``
        (the initial latent first, then every ``every`` steps), differentiable by ``jax.grad`` / ``jax.jvp``
        in the initial latent state and the law parameters (``law``: as :attr:`law_params`). The sample
        draws are the stepper's (seeded), so f is deterministic. One ``lax.scan``: jit it for speed.
        The Eulerian quadrature's inverse map is a data-dependent Newton loop that reverse mode cannot
        run through: its gradients are forward mode only (``jax.jvp`` / ``jax.jacfwd``)."""
        import jax
        import jax.numpy as jnp

        steps, every = int(steps), max(1, int(every))
        if steps < every or steps % every:
            raise ConfigError(f"ReducedStepper.rollout_fn: steps = {steps} must be a positive multiple of every = {every}.")
        key0 = jax.random.PRNGKey(self.seed)
        zero = jnp.zeros((), jnp.int32)

        def f(z0, zdot0, law):
            s = ReducedState(z0, zdot0, z0, jnp.zeros((), self.dtype), key0, zero, zero, zero)

            def frame(s, _):
                s, _ = jax.lax.scan(lambda c, _: (self._step_impl(c, law), None), s, None, length=every)
                return s, s.z

            _, zs = jax.lax.scan(frame, s, None, length=steps // every)
            return jnp.concatenate([z0[None], zs])

        return f

    # ---- the differentiable entry points of AbstractStepper (issue 16, item 7) -------------------------
    #: the inverse workflow's adapter (``mpmlab.core.autodiff``): the JAX one, observing through this stepper
    autodiff_adapter = "mpmlab.rom.autodiff:ReducedJaxAdapter"

    @property
    def particles(self):
        return self.fom.particles

    @property
    def groups(self):
        return self.fom.groups

    @property
    def precision(self):
        return self.fom.precision

    def controls(self) -> dict:
        """The full-order model's controls (``fom.controls()``: x, v, law, boundary, gravity, mass, volume):
        an inverse problem states its unknowns on the scene, and ``observe`` runs them through the reduced
        model, so ``mpmlab.inverse.Fit`` (``task=inverse``) fits in the reduced space unchanged."""
        return self.fom.controls()

    def observe(self, controls, observation, steps, segment=None, health: bool = False):
        """Observations [T, L, d] of the reduced rollout from full-order ``controls`` after each of ``steps``
        (``AbstractStepper.observe``), pure JAX (differentiable by ``jax.grad``). The initial latent state is
        Eq. 19 of ``controls["x"]`` and ``["v"]``; x_hat(0) comes from Gauss-Newton under ``stop_gradient``
        (gradients reach v_hat(0), the law, the boundaries, gravity, masses and volumes, not x). The
        observation operator reads g's state: x = g(X; x_hat), v = dg/dx_hat v_hat, F = dg/dX. Reverse mode
        needs the Lagrangian quadrature (``rollout_fn``). ``health``: also return whether an observed state
        was non-finite or left the domain. ``segment`` is accepted for the interface (a reduced state is a
        few numbers: no rematerialisation)."""
        key = (id(observation), tuple(np.asarray(steps).reshape(-1).tolist()), bool(health))
        cache = self.__dict__.setdefault("_observe_cache", {})
        if key not in cache:
            cache[key] = (observation, self._observe_fn(observation, steps, health))
        return cache[key][1](controls)

    def _observe_fn(self, observation, steps, health):
        import jax
        import jax.numpy as jnp

        from ..backends.jax.differentiable import schedule, split_controls

        impl = observation.implementation("jax", "observation")(observation, self.fom)
        first, g, count, pick = schedule(steps)
        dense = len(pick) != count
        with jax.ensure_compile_time_eval():          # built inside a caller's trace (a fit): constants
            key0 = jax.random.PRNGKey(self.seed)
            zero = jnp.zeros((), jnp.int32)
            lo, hi = (jnp.asarray(a, self.dtype) for a in self.scene.inner_bounds)

        def seen(s):
            x, F, v = N.g_state(self.params, self.norm, self.X, s.z[None, :], s.zdot[None, :])
            law = tuple({"F": F[gr.start:gr.stop]} for gr in self.fom.groups)
            bad = ~jnp.all(jnp.isfinite(x)) | ~jnp.all(jnp.isfinite(v)) | jnp.any((x < lo) | (x >= hi))
            return impl.fn({"x": x, "v": v, "law": law, "t": s.t}), bad

        def fn(c):
            _, prm = split_controls(self.fom, c)
            x0 = jax.lax.stop_gradient(jnp.asarray(c["x"], self.dtype))
            z0 = jax.lax.stop_gradient(Mf.initial_state(self.params, self.norm, self.X, x0, x0,
                                                        self._initial_guess(x0)).z)     # Eq. 19, as init()
            zdot0 = Mf.project_velocity(self.params, self.norm, self.X, z0, jnp.asarray(c["v"], self.dtype))
            s = ReducedState(z0, zdot0, z0, jnp.zeros((), self.dtype), key0, zero, zero, zero)

            def run(s, n):
                return jax.lax.scan(lambda q, _: (self._step_impl(q, fom_params=prm), None), s, None, length=n)[0]

            s = run(s, first) if first else s
            y0, bad0 = seen(s)
            if count == 1:
                return (y0[None], bad0) if health else y0[None]

            def interval(s, _):
                s = run(s, g)
                return s, seen(s)

            _, (ys, bad) = jax.lax.scan(interval, s, None, length=count - 1)
            ys = jnp.concatenate([y0[None], ys], axis=0)
            ys = ys[jnp.asarray(pick)] if dense else ys
            return (ys, bad0 | jnp.any(bad)) if health else ys

        return jax.jit(fn)

    def _positions(self, z):
        import jax.numpy as jnp

        x, F = N.g_F(self.params, self.norm, self.X, jnp.asarray(z)[None, :])
        return np.asarray(x), np.asarray(jnp.linalg.det(F))

    def to_numpy(self, state, X=None) -> dict[str, np.ndarray]:
        """x, F, v at reference points ``X`` [Q, d] (default: the scene's material points) and x_hat."""
        import jax.numpy as jnp

        Xq = self.X if X is None else jnp.asarray(X, self.dtype)
        x, F, v = N.g_state(self.params, self.norm, Xq, state.z[None, :], state.zdot[None, :])
        return {"x": np.asarray(x), "F": np.asarray(F), "v": np.asarray(v),
                "z": np.asarray(state.z), "t": float(state.t)}
