"""Backend-neutral scene description: domain, grid, bodies, materials, gravity, boundaries, time step.

A ``Scene`` is plain data (NumPy). ``Scene.particles()`` samples the bodies once and groups the
particles by constitutive law (contiguous blocks), so that a backend compiles exactly the laws
present and launches each law's kernel on its own block -- no per-particle switch over law ids.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any, Mapping, Sequence

import numpy as np

from . import registry
from .errors import ConfigError, TimeStepError
from .geometry import make_shape, sample
from .initial_fields import check_F, law_state_from_F, resolve


@dataclass
class Body:
    """One body: a shape filled with particles of one material.

    Args:
        shape: a ``Shape`` (or a dict ``{"kind": "box", "lo": ..., "hi": ...}``).
        material: registered law name (e.g. ``"fixed_corotated"``).
        params: law parameters by name (units as declared by the law); missing ones take defaults.
        density: rest density [kg/m^3].
        velocity: initial velocity [m/s]: a D-vector (uniform), or per particle: an array [N, D], a
            function of the sampled positions ``f(x [N, D]) -> [N, D]``, or D expression strings in
            ``x[k]`` (``mpmlab.core.initial_fields``).
        angular_velocity: initial angular velocity [rad/s] about the body's centroid (scalar in 2D,
            3-vector in 3D), added to ``velocity``.
        F: initial deformation gradient, in the same forms as ``velocity`` with shape [D, D] (None:
            F = I). It sets the law's state F (the elastic part for a plastic law); a law whose state
            has J but no F gets J = det F; a law with neither refuses it. det F > 0 is required. The
            positions stay the sampled ones: F is a prestrain of the body as sampled.
        C: initial affine velocity field C [1/s] (APIC/MLS/TPIC; [D, D] forms as for F; None: 0). A
            transfer that stores no C (PIC, FLIP) refuses it when the stepper is built.
        particles_per_cell: k^D points per cell (regular / jittered sampling).
        sampling: ``regular``, ``jittered``, ``random`` (then ``count`` particles) or ``lattice`` (a box
            only: ``lattice`` = points per axis, ``np.linspace(lo, hi, n)`` with the faces included,
            volume = box volume / point count; NCLaw's training cube is ``[10, 10, 10]``).
        particle_volume: override of the per-particle volume [m^D] (e.g. Taichi mpm3d's quirk).
        tracer: massless points (mass and volume 0): they move with the grid's velocity (G2P) and put no
            mass, momentum or stress into it (P2G), so they observe a run without changing it (the
            tracer baseline of the deformation-map ROM paper, Tab. 4). A scene needs at least one body
            that is not a tracer. A tracer's law state integrates the grid's velocity gradient as a
            material point's does; where that gradient is steep (next to empty nodes, e.g. the ends of
            a torn bar) its F can fail the J > 0 check and stop the run.
        options: the law's configuration (its instance fields: network widths, a weights file, ...);
            bodies with the same material and options share one law instance and its weights.
    """

    shape: Any
    material: str
    params: Mapping[str, float] = field(default_factory=dict)
    density: float = 1000.0
    velocity: Sequence[float] | None = None
    angular_velocity: Any = None
    particles_per_cell: int = 1
    sampling: str = "regular"
    count: int | None = None
    particle_volume: float | None = None
    name: str = ""
    lattice: Sequence[int] | None = None
    options: Mapping[str, Any] = field(default_factory=dict)
    tracer: bool = False
    F: Any = None
    C: Any = None

    def __post_init__(self):
        if isinstance(self.shape, Mapping):
            spec = dict(self.shape)
            self.shape = make_shape(spec.pop("kind"), **spec)


@dataclass
class MaterialGroup:
    """A contiguous block of particles sharing one law instance: ``params`` is ``[n, P]`` per particle
    in the law's declared order, ``weights`` the law's shared arrays ``{name: array}`` (float64)."""

    law: Any
    start: int
    stop: int
    params: np.ndarray
    weights: dict = field(default_factory=dict)
    #: initial values of law-state fields that differ from the law's declared ones (``{"F": [n, D, D]}``
    #: or ``{"J": [n]}`` from the bodies' initial F); the others start at the declared value
    state: dict = field(default_factory=dict)

    @property
    def count(self) -> int:
        return self.stop - self.start

    def initial_state(self, dim: int) -> dict[str, np.ndarray]:
        """The group's law state at t = 0: the law's ``initial_state`` with the bodies' initial F applied
        (what every stepper starts from)."""
        return {**self.law.initial_state(self.count, dim), **{k: np.array(a) for k, a in self.state.items()}}


@dataclass
class ParticleSet:
    x: np.ndarray           # [N, D] m
    v: np.ndarray           # [N, D] m/s
    mass: np.ndarray        # [N] kg
    volume: np.ndarray      # [N] m^D, reference volume
    body_id: np.ndarray     # [N] int
    material_id: np.ndarray  # [N] int, index into groups
    groups: list[MaterialGroup]
    C: np.ndarray | None = None   # [N, D, D] initial affine field (None: zero)

    @property
    def count(self) -> int:
        return len(self.x)


@dataclass
class Scene:
    """The whole problem statement.

    Args:
        dim: 2 or 3.
        dx: grid spacing [m].
        domain: ``(lo, hi)`` corners [m]; the grid has ``round((hi - lo)/dx)`` cells per axis.
        bodies: list of ``Body``.
        gravity: [m/s^2], length D.
        boundaries: list of boundary objects (``mpmlab.boundaries``).
        dt: time step [s] or ``"auto"`` (CFL with ``cfl`` safety factor).
        cfl: safety factor C used by ``dt: auto``: dt = C dx / (c_p + |v|_max).
        cfl_limit: largest accepted C for a fixed dt; above it the scene is refused.
        substeps: time steps per output frame.
        dt_every: with ``dt: auto``, recompute dt from the current max particle speed every this many
            steps of a rollout (0: compute it once from the initial velocities). Gradient rollouts
            (``observe``) always keep the initial dt.
    """

    dim: int
    dx: float
    domain: tuple[Sequence[float], Sequence[float]]
    bodies: list[Body]
    gravity: Sequence[float] | None = None
    boundaries: list[Any] = field(default_factory=list)
    dt: Any = "auto"
    # Safety factor rule: cfl = min(0.3, C*_min / 2), C*_min = the smallest measured stable CFL factor
    # over transfers x laws x {vibrating bar, falling cube} on both backends (benchmarks/stress.md).
    # Elastic, elastoplastic-Hencky and fluid laws: C* >= 0.89 (PIC/FLIP on the bar), a margin of ~3.
    # A law with a lower measured C* declares stable_cfl, and effective_cfl caps dt: auto at C*/2 there
    # (none does now: drucker_prager_jaumann's C* 0.19-0.20 was fixed in issue 17 item 3).
    cfl: float = 0.3
    cfl_limit: float = 0.5
    substeps: int = 1
    name: str = "scene"
    seed: int = 0
    dt_every: int = 10

    def __post_init__(self):
        if not (isinstance(self.dt_every, (int, np.integer)) and self.dt_every >= 0):
            raise ConfigError(f"scene '{self.name}': dt_every = {self.dt_every!r} must be an integer >= 0 "
                              f"(steps between dt: auto updates; 0 = once at the start).")
        if self.dim not in (2, 3):
            raise ConfigError(f"scene '{self.name}': dim = {self.dim}; mpmlab supports 2 or 3.")
        if not self.dx > 0:
            raise ConfigError(f"scene '{self.name}': grid spacing dx = {self.dx} must be positive.")
        lo, hi = (np.asarray(c, float) for c in self.domain)
        if lo.shape != (self.dim,) or hi.shape != (self.dim,):
            raise ConfigError(f"scene '{self.name}': domain corners must have {self.dim} coordinates each.")
        if np.any(hi <= lo):
            raise ConfigError(f"scene '{self.name}': domain upper corner {hi} must exceed lower corner {lo}.")
        self.domain = (lo, hi)
        self.gravity = np.zeros(self.dim) if self.gravity is None else np.asarray(self.gravity, float)
        if self.gravity.shape != (self.dim,):
            raise ConfigError(f"scene '{self.name}': gravity must have {self.dim} components.")
        if not self.bodies:
            raise ConfigError(f"scene '{self.name}' has no bodies; add at least one.")

    # ---- grid -------------------------------------------------------------------------------
    @property
    def origin(self) -> np.ndarray:
        return self.domain[0]

    @property
    def cells(self) -> tuple[int, ...]:
        n = np.round((self.domain[1] - self.domain[0]) / self.dx).astype(int)
        return tuple(int(c) for c in n)

    @property
    def grid_shape(self) -> tuple[int, ...]:
        """Number of grid nodes per axis (cells + 1)."""
        return tuple(c + 1 for c in self.cells)

    @property
    def inner_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Region a particle may occupy: its 3-node quadratic stencil must stay on the grid."""
        lo = self.origin + 0.5 * self.dx
        hi = self.origin + (np.asarray(self.cells) - 0.5) * self.dx
        return lo, hi

    # ---- particles --------------------------------------------------------------------------
    @cached_property
    def _particles(self) -> ParticleSet:
        xs, vs, ms, vols, bids, law_names, params = [], [], [], [], [], [], []
        Fs, Cs = [], []       # per body: the initial-F law state ({"F": ...} / {"J": ...}) and C, or None
        instances = {}
        for b, body in enumerate(self.bodies):
            where = self._where(b)
            law = self._law(b)        # the configured instance declares the parameters (phase_change)
            prm = law.resolve_params(body.params, where, density=body.density)
            if not body.density > 0:
                raise ConfigError(f"{where}: density = {body.density} must be positive.")
            x, vol = sample(body.shape, self.dim, self.dx, body.particles_per_cell, body.sampling,
                            body.count, seed=self.seed + b, lattice=body.lattice,
                            where=f"{self.name}|scene.bodies.{body.name or b}")
            if len(x) == 0:
                raise ConfigError(f"{where}: the shape contains no particle at dx = {self.dx}; enlarge it or refine dx.")
            if body.particle_volume is not None:
                vol = float(body.particle_volume)
            lo, hi = self.inner_bounds
            outside = np.nonzero(np.any((x < lo) | (x >= hi), axis=1))[0]
            if len(outside):
                raise ConfigError(
                    f"{where}: particle {outside[0]} at {np.round(x[outside[0]], 6).tolist()} lies outside the "
                    f"domain interior [{lo.tolist()}, {hi.tolist()}); move the body or enlarge the domain."
                )
            D = self.dim
            v = np.zeros_like(x)
            if body.velocity is not None:
                v += resolve(body.velocity, x, (D,), "velocity", where)
            F = resolve(body.F, x, (D, D), "F", where)
            if F is not None:
                check_F(F, x, where)
                F = law_state_from_F(law, F, where)
            Fs.append(F)
            Cs.append(resolve(body.C, x, (D, D), "C", where))
            if body.angular_velocity is not None:
                c = x.mean(axis=0)
                r = x - c
                w = np.asarray(body.angular_velocity, float)
                if self.dim == 2:
                    if w.size != 1:
                        raise ConfigError(f"{where}: angular_velocity is a scalar in 2D.")
                    v += float(w) * np.stack([-r[:, 1], r[:, 0]], axis=1)
                else:
                    if w.shape != (3,):
                        raise ConfigError(f"{where}: angular_velocity is a 3-vector in 3D.")
                    v += np.cross(w, r)
            xs.append(x); vs.append(v)
            if body.tracer:
                vol = 0.0
            ms.append(np.full(len(x), body.density * vol)); vols.append(np.full(len(x), vol))
            bids.append(np.full(len(x), b)); law_names.append(law)
            instances.setdefault(law, where)
            params.append(np.tile(np.array([prm[k] for k in law.param_names()]), (len(x), 1)))
        if self.bodies and all(b.tracer for b in self.bodies):
            raise ConfigError(f"scene '{self.name}': every body is a tracer (massless); give at least one body "
                              f"with tracer: false.")
        # group particles by law instance (law and options), in order of first appearance
        order_laws = list(dict.fromkeys(law_names))
        blocks, groups, start = [], [], 0
        mat_id = []
        for g, inst in enumerate(order_laws):
            idx = [b for b, n in enumerate(law_names) if n == inst]
            n = sum(len(xs[b]) for b in idx)
            weights = {k: np.asarray(a, dtype=float) for k, a in inst.initial_weights(self.dim).items()}
            inst.check_weights(weights, self.dim, instances[inst])
            rows = inst.particle_params(np.concatenate([params[b] for b in idx]), np.concatenate([xs[b] for b in idx]))
            state = {}
            if any(Fs[b] is not None for b in idx):   # bodies without an initial F keep the declared one
                rest = inst.initial_state(n, self.dim)
                for k in {k for b in idx if Fs[b] is not None for k in Fs[b]}:
                    parts, at = [], 0
                    for b in idx:
                        m = len(xs[b])
                        parts.append(Fs[b][k] if Fs[b] is not None else rest[k][at:at + m])
                        at += m
                    state[k] = np.concatenate(parts)
            groups.append(MaterialGroup(inst, start, start + n, rows, weights, state))
            blocks.extend(idx); mat_id.append(np.full(n, g)); start += n
        cat = lambda arrs: np.concatenate([arrs[b] for b in blocks])
        C = None
        if any(c is not None for c in Cs):
            C = cat([c if c is not None else np.zeros((len(x), self.dim, self.dim)) for c, x in zip(Cs, xs)])
        return ParticleSet(cat(xs), cat(vs), cat(ms), cat(vols), cat(bids), np.concatenate(mat_id), groups, C)

    def particles(self) -> ParticleSet:
        return self._particles

    def _where(self, b: int) -> str:
        return f"scene '{self.name}', body {self.bodies[b].name or b}"

    @cached_property
    def _law_instances(self) -> dict:
        """``{body index: law instance}``, filled by ``_law`` as the bodies are asked for."""
        return {}

    def _law(self, b: int):
        """The law instance of body ``b`` (an index into ``bodies``): built once from its material and
        options (``from_config``) and kept; bodies whose material and options are equal get the same
        instance. Everything that reads a body's law -- its parameters, state, implementations,
        stable CFL, wave speed -- reads this instance, whose class may depend on the options (a
        ``phase_change`` pair declares the two laws' parameters; the registered class only its own)."""
        cache = self._law_instances
        if b not in cache:
            body = self.bodies[b]
            inst = registry.laws.get(body.material).from_config(body.options, self._where(b))
            cache[b] = next((law for law in cache.values() if law == inst), inst)
        return cache[b]

    def body_laws(self) -> list:
        """The law instance of each body, in body order (``_law``); samples no particle."""
        return [self._law(b) for b in range(len(self.bodies))]

    # ---- time step --------------------------------------------------------------------------
    def wave_speed(self) -> float:
        """Largest elastic wave speed over all bodies [m/s]."""
        c = 0.0
        for b, body in enumerate(self.bodies):
            inst = self._law(b)
            prm = inst.resolve_params(body.params, self._where(b), density=body.density)
            # a law with shared weights sees them (its stiffness may live there: a neural law)
            weights = (next(g.weights for g in self.particles().groups if g.law == inst)
                       if inst.weight_shapes(self.dim) else {})
            c = max(c, inst.instance_wave_speed(prm, body.density, self.dim, weights))
        return c

    def cfl_number(self, dt: float, speed: float | None = None) -> float:
        """C = dt (c_p + |v|_max) / dx (verification note #7)."""
        if speed is None:
            speed = float(np.max(np.linalg.norm(self.particles().v, axis=1), initial=0.0))
        return dt * (self.wave_speed() + speed) / self.dx

    @property
    def adaptive_dt(self) -> bool:
        """True when ``dt: auto`` is recomputed during rollouts (``dt_every`` > 0)."""
        return isinstance(self.dt, str) and self.dt == "auto" and self.dt_every > 0

    def auto_dt(self, speed: float) -> float:
        """The ``dt: auto`` step for a max particle speed [m/s]: the largest dt with
        dt (c_p + speed + |g| n dt) <= cfl dx, n = max(dt_every, 1) -- the CFL bound of verification
        note #7 counting the speed gravity can add before the next update (without it a soft body
        falls several cells per step: c_p -> 0 gives dt -> inf). With g = 0: cfl dx / (c_p + speed)."""
        a = self.wave_speed_cached + speed
        gn = float(np.linalg.norm(self.gravity)) * max(int(self.dt_every), 1)
        Cdx = self.effective_cfl * self.dx
        return 2.0 * Cdx / (a + math.sqrt(a * a + 4.0 * gn * Cdx))   # root of gn dt^2 + a dt - C dx = 0

    @cached_property
    def effective_cfl(self) -> float:
        """The ``dt: auto`` safety factor: ``cfl``, capped at half the measured C* of any law in the scene
        that declares one (``stable_cfl``; benchmarks/stress.md)."""
        caps = [getattr(law, "stable_cfl", None) for law in self.body_laws()]
        caps = [0.5 * c for c in caps if c is not None]
        return min([float(self.cfl)] + caps)

    @cached_property
    def wave_speed_cached(self) -> float:
        return self.wave_speed()

    def resolve_dt(self) -> float:
        """The time step to use: ``dt: auto`` -> C dx/(c+|v|); a fixed dt above ``cfl_limit`` is refused."""
        speed = float(np.max(np.linalg.norm(self.particles().v, axis=1), initial=0.0))
        c = self.wave_speed() + speed
        if self.dt == "auto":
            if c == 0:
                raise TimeStepError(f"scene '{self.name}': dt 'auto' needs a nonzero wave speed; set dt explicitly.")
            return self.auto_dt(speed)
        try:
            dt = float(self.dt)
        except (TypeError, ValueError):
            raise ConfigError(f"scene '{self.name}': dt = {self.dt!r} must be a number of seconds or 'auto'.") from None
        if not dt > 0:
            raise TimeStepError(f"scene '{self.name}': dt = {dt} must be positive.")
        C = dt * c / self.dx
        if C > self.cfl_limit:
            raise TimeStepError(
                f"scene '{self.name}': dt = {dt:g} s gives CFL number {C:.3g} > cfl_limit {self.cfl_limit:g} "
                f"(dx = {self.dx:g} m, wave speed + particle speed = {c:.4g} m/s); use dt <= "
                f"{self.cfl_limit * self.dx / c:.3g} s or dt: auto."
            )
        return dt
