"""Built-in boundaries (backend-neutral descriptions; each names its JAX and Warp implementation).

Grid boundaries act on grid velocities after the grid update (JAX-MPM Sec. 2.2.2), in the order
listed in the scene; particle constraints and loads act on particle sets selected at t = 0.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar, Mapping, Sequence

import numpy as np

from ..core.errors import ConfigError
from ..core.geometry import make_shape
from ..core.interfaces import AbstractBoundary

WALL_KINDS = ("sticky", "slip", "separate", "none")


def _impl(name: str) -> dict[str, str]:
    return {"jax": f"mpmlab.backends.jax.boundaries:{name}", "warp": f"mpmlab.backends.warp.boundaries:{name}"}


def _faces(dim: int) -> list[str]:
    return [f"{'xyz'[a]}{s}" for a in range(dim) for s in "-+"]


@dataclass(frozen=True)
class Walls(AbstractBoundary):
    """Domain walls: nodes within ``thickness`` cells of a domain face get that face's condition.

    ``sticky``: v = 0; ``slip``: normal component zeroed; ``separate``: normal component zeroed only
    when moving into the wall (the Taichi mpm3d / NCLaw App. D free-slip box); ``none``: open.
    ``faces`` overrides ``default`` per face, keys ``x-``, ``x+``, ``y-``, ``y+``, ``z-``, ``z+``.

    Walls constrain grid nodes, not particles: a particle moves with its stencil's velocity, which
    includes free nodes, so it may end beyond the face (the innermost constrained node, origin +
    (thickness - 1) dx) until the material pushes it back; for thickness >= 2 by less than 0.5 dx
    (dam_break_2d, cpu, fp64: 12-13 of 4000 particles, <= 0.075 dx, none with PIC; benchmarks/walls.md).
    """

    name: ClassVar[str] = "walls"
    implementations: ClassVar[dict] = _impl("walls")
    gradients: ClassVar[tuple] = ("jax", "warp")
    default: str = "separate"
    faces: Mapping[str, str] = field(default_factory=dict)
    thickness: int = 3

    def face_kinds(self, dim: int) -> list[str]:
        return [self.faces.get(f, self.default) for f in _faces(dim)]

    def validate(self, scene) -> None:
        names = _faces(scene.dim)
        for f, k in list(self.faces.items()) + [("default", self.default)]:
            if f != "default" and f not in names:
                raise ConfigError(f"boundary 'walls': unknown face '{f}' in a {scene.dim}D scene; faces are {names}.")
            if k not in WALL_KINDS:
                raise ConfigError(f"boundary 'walls': face '{f}' kind '{k}' unknown; use one of {WALL_KINDS}.")
        if not 1 <= self.thickness <= min(scene.cells) // 2:
            raise ConfigError(f"boundary 'walls': thickness = {self.thickness} cells must be in [1, {min(scene.cells) // 2}].")


@dataclass(frozen=True)
class FrictionWalls(AbstractBoundary):
    """Coulomb friction on one domain face (JAX-MPM Eqs. 35-36, Bardenhagen 2001).

    Nodes within ``thickness`` cells of ``face`` moving into the wall lose their normal velocity and
    their tangential speed is reduced by mu * v_n (stick if |v_t| <= mu v_n). The coefficient is
    either piecewise constant over ``len(mu)`` equal segments along ``along`` (an axis name), or given
    per node (``per_node=True``: ``mu`` has one entry per grid node along ``along``).
    """

    name: ClassVar[str] = "friction_walls"
    implementations: ClassVar[dict] = _impl("friction_walls")
    gradients: ClassVar[tuple] = ("jax", "warp")
    face: str = "y-"
    mu: Sequence[float] = (0.0,)
    along: str = "x"
    thickness: int = 3
    per_node: bool = False

    @property
    def axis(self) -> int:
        return "xyz".index(self.face[0])

    @property
    def side(self) -> int:
        return -1 if self.face[1] == "-" else 1

    @property
    def along_axis(self) -> int:
        return "xyz".index(self.along)

    def validate(self, scene) -> None:
        if self.face not in _faces(scene.dim):
            raise ConfigError(f"boundary 'friction_walls': face '{self.face}' not one of {_faces(scene.dim)}.")
        if self.along not in "xyz"[: scene.dim] or self.along_axis == self.axis:
            raise ConfigError(f"boundary 'friction_walls': 'along' = '{self.along}' must be a tangential axis of face '{self.face}'.")
        mu = np.asarray(self.mu, float)
        if mu.ndim != 1 or len(mu) == 0 or np.any(mu < 0) or not np.all(np.isfinite(mu)):
            raise ConfigError("boundary 'friction_walls': mu must be a non-empty list of non-negative coefficients.")
        if self.per_node and len(mu) != scene.grid_shape[self.along_axis]:
            raise ConfigError(
                f"boundary 'friction_walls': per_node mu needs {scene.grid_shape[self.along_axis]} entries "
                f"(grid nodes along {self.along}), got {len(mu)}."
            )


@dataclass(frozen=True)
class Plane(AbstractBoundary):
    """A half-space boundary (inclined plane): nodes with (x - point) . normal < 0 are constrained.

    ``normal`` points into the free side. ``condition``: sticky / slip / separate, with optional Coulomb
    ``friction`` for ``separate`` (as ``FrictionWalls``).
    """

    name: ClassVar[str] = "plane"
    implementations: ClassVar[dict] = _impl("plane")
    gradients: ClassVar[tuple] = ("jax", "warp")
    point: Sequence[float] = (0.0, 0.0, 0.0)
    normal: Sequence[float] = (0.0, 1.0, 0.0)
    condition: str = "separate"
    friction: float = 0.0

    def unit_normal(self) -> np.ndarray:
        n = np.asarray(self.normal, float)
        return n / np.linalg.norm(n)

    def validate(self, scene) -> None:
        if len(self.point) != scene.dim or len(self.normal) != scene.dim:
            raise ConfigError(f"boundary 'plane': point and normal need {scene.dim} components.")
        if not np.linalg.norm(self.normal) > 0:
            raise ConfigError("boundary 'plane': normal must be nonzero.")
        if self.condition not in ("sticky", "slip", "separate"):
            raise ConfigError(f"boundary 'plane': condition '{self.condition}' must be sticky, slip or separate.")
        if self.friction < 0:
            raise ConfigError("boundary 'plane': friction must be non-negative.")


@dataclass(frozen=True)
class BoxObstacle(AbstractBoundary):
    """A static rigid box (JAX-MPM Sec. 4.2.1, Eq. 33): grid nodes inside lose the velocity component
    along the outward normal of the nearest face when it points into the box (frictionless slip)."""

    name: ClassVar[str] = "box_obstacle"
    implementations: ClassVar[dict] = _impl("box_obstacle")
    gradients: ClassVar[tuple] = ("jax", "warp")
    lo: Sequence[float] = (0.0, 0.0, 0.0)
    hi: Sequence[float] = (0.0, 0.0, 0.0)

    def validate(self, scene) -> None:
        lo, hi = np.asarray(self.lo, float), np.asarray(self.hi, float)
        if lo.shape != (scene.dim,) or hi.shape != (scene.dim,) or np.any(hi <= lo):
            raise ConfigError(f"boundary 'box_obstacle': lo/hi need {scene.dim} components with hi > lo.")


@dataclass(frozen=True)
class ParticleVelocity(AbstractBoundary):
    """Prescribed motion of the particles inside ``region`` at t = 0, during [t_start, t_end): a
    translation at ``velocity`` or, with ``angular_velocity`` (rad/s: a scalar in 2D, a 3-vector in 3D),
    a rigid motion v = v0 + omega x (x - c(t)) about a centre c(t) = c0 + v0 (t - t_start) moving with
    the translation (``center`` c0; default: the centroid of the region's particles at t = 0). A step
    from t to t + dt moves the particles exactly rigidly, x <- c(t + dt) + R(omega dt) (x - c(t)), and
    gives them the rigid velocity at their new position (ROM paper Sec. 5.2: the pulled and twisted end
    of the torsion cuboid)."""

    name: ClassVar[str] = "particle_velocity"
    implementations: ClassVar[dict] = _impl("particle_velocity")
    gradients: ClassVar[tuple] = ("jax", "warp")
    stage: ClassVar[str] = "particle_velocity"
    kinematic: ClassVar[bool] = True
    region: Mapping[str, Any] = field(default_factory=dict)
    velocity: Sequence[float] = (0.0, 0.0, 0.0)
    t_start: float = 0.0
    t_end: float = float("inf")
    angular_velocity: Any = None
    center: Sequence[float] | None = None

    def select(self, x0: np.ndarray) -> np.ndarray:
        spec = dict(self.region)
        return np.nonzero(make_shape(spec.pop("kind"), **spec).contains(x0))[0]

    @property
    def rotating(self) -> bool:
        """True when an angular velocity is given and nonzero (else a pure translation, as before)."""
        return self.angular_velocity is not None and bool(np.any(np.asarray(self.angular_velocity, float) != 0.0))

    def rotation_center(self, x0: np.ndarray) -> np.ndarray:
        """c0: ``center``, or the centroid of the region's particles at t = 0."""
        if self.center is not None:
            return np.asarray(self.center, float)
        return np.asarray(x0, float)[self.select(x0)].mean(axis=0)

    def _check(self, scene, vector, what: str) -> None:
        if "kind" not in self.region:
            raise ConfigError(f"boundary '{self.name}': region needs a shape 'kind' (box, sphere, ...).")
        if len(vector) != scene.dim:
            raise ConfigError(f"boundary '{self.name}': {what} needs {scene.dim} components.")
        if not self.t_end > self.t_start:
            raise ConfigError(f"boundary '{self.name}': t_end = {self.t_end} must exceed t_start = {self.t_start}.")
        if len(self.select(scene.particles().x)) == 0:
            raise ConfigError(f"boundary '{self.name}': region {dict(self.region)} contains no particle.")

    def validate(self, scene) -> None:
        self._check(scene, self.velocity, "velocity")
        if self.angular_velocity is not None:
            w = np.asarray(self.angular_velocity, float)
            want = () if scene.dim == 2 else (3,)
            if w.shape != want or not np.all(np.isfinite(w)):
                raise ConfigError(f"boundary '{self.name}': angular_velocity = {self.angular_velocity!r} must be "
                                  f"{'a number [rad/s] in 2D' if scene.dim == 2 else 'a 3-vector [rad/s] in 3D'}.")
        if self.center is not None and (len(self.center) != scene.dim or not np.all(np.isfinite(self.center))):
            raise ConfigError(f"boundary '{self.name}': center = {self.center!r} needs {scene.dim} finite components.")


@dataclass(frozen=True)
class GridVelocity(ParticleVelocity):
    """Prescribed rigid motion of the grid: the nodes inside the box ``region``, carried along by the motion,
    take the rigid velocity v0 + omega x (y - c(t)) during [t_start, t_end) (the motion and its centre as
    in ``ParticleVelocity``; a node y is inside when c0 + R(omega (t - t_start))^T (y - c(t)) is in the box).

    A grip through the grid. A ``particle_velocity`` alone moves its particles but leaves the nodes they
    share with the free material to the momentum balance: the material's stress pulls those nodes back,
    the grip is soft, and a pulled end tears off within a few cells of travel (the ROM torsion bar did,
    at every pull speed: ``tests/test_boundaries.py``). Holding the nodes makes the neighbours' positions
    and F follow the prescribed motion alike. Pair it with a ``particle_velocity`` on the same region to
    move the gripped particles exactly rigidly. The region must be a ``box`` (a box in the reference
    frame is a test both backends evaluate per node and time)."""

    name: ClassVar[str] = "grid_velocity"
    implementations: ClassVar[dict] = _impl("grid_velocity")
    gradients: ClassVar[tuple] = ("jax", "warp")
    stage: ClassVar[str] = "grid"

    def box(self, dim: int) -> tuple[np.ndarray, np.ndarray]:
        return np.asarray(self.region["lo"], float)[:dim], np.asarray(self.region["hi"], float)[:dim]

    def validate(self, scene) -> None:
        if self.region.get("kind") != "box" or "lo" not in self.region or "hi" not in self.region:
            raise ConfigError(f"boundary '{self.name}': region must be {{kind: box, lo: [...], hi: [...]}}, "
                              f"got {dict(self.region)}.")
        lo, hi = self.box(scene.dim)
        if len(self.region["lo"]) != scene.dim or len(self.region["hi"]) != scene.dim or np.any(hi <= lo):
            raise ConfigError(f"boundary '{self.name}': region lo/hi need {scene.dim} components with hi > lo.")
        super().validate(scene)


@dataclass(frozen=True)
class ParticleLoad(ParticleVelocity):
    """A total force ``force`` [N] on the particles inside ``region``, shared in proportion to their
    mass, during [t_start, t_end)."""

    name: ClassVar[str] = "particle_load"
    implementations: ClassVar[dict] = _impl("particle_load")
    gradients: ClassVar[tuple] = ("jax", "warp")
    stage: ClassVar[str] = "particle_force"
    kinematic: ClassVar[bool] = False           # a load, not a prescribed motion
    force: Sequence[float] = (0.0, 0.0, 0.0)

    def validate(self, scene) -> None:
        self._check(scene, self.force, "force")
        if self.angular_velocity is not None or self.center is not None:
            raise ConfigError(f"boundary '{self.name}': angular_velocity and center belong to particle_velocity; "
                              f"a load takes a force only.")

    def shares(self, particles):
        """(indices of the particles in the region, their mass fractions): what both backends apply. A region
        without mass (no particle, or massless tracers only) cannot carry a force: refused in one line."""
        idx = np.asarray(self.select(particles.x))
        total = float(np.sum(particles.mass[idx])) if len(idx) else 0.0
        if not total > 0.0:
            raise ConfigError(f"boundary '{self.name}': its region {self.region} holds "
                              f"{'no particle' if not len(idx) else f'{len(idx)} massless points only'}; the force "
                              f"{list(self.force)} N would act on nothing: move the region onto the body.")
        return idx, particles.mass[idx] / total


def make_boundary(spec: Mapping[str, Any]) -> AbstractBoundary:
    """Build a registered boundary from ``{"kind": name, **options}``."""
    from ..core import registry

    return registry.boundaries.build(spec)
