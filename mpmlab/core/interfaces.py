"""Abstract interfaces of mpmlab's plugin kinds.

Concrete classes are final (diffrax pattern): subclass an ``Abstract*`` class, never a concrete one.
Each plugin declares its ``implementations``: backend name -> ``"module:attr"`` of the backend-side
factory, imported only when a stepper for that backend is built. A missing entry is a visible gap in
the capability table (``mpmlab.capabilities.capabilities()``), never a silent fallback.
"""
from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any, ClassVar, Mapping

import numpy as np

from .errors import InvalidParameterError, MissingImplementationError
from .registry import load_object

#: Per-particle law state fields and their shape (``"mat"``: [D, D], ``"scalar"``: []).
STATE_FIELDS = {"F": "mat", "J": "scalar", "sigma": "mat", "eps_p": "scalar"}


@dataclass(frozen=True)
class ParamSpec:
    """One physical parameter: name, unit, default and valid range (bounds may be open)."""

    name: str
    unit: str
    default: float | None
    low: float = -math.inf
    high: float = math.inf
    low_open: bool = False
    high_open: bool = False
    doc: str = ""

    def check(self, value: float, where: str) -> float:
        try:
            v = float(value)
        except (TypeError, ValueError):
            raise InvalidParameterError(f"{where}: parameter '{self.name}' must be a number, got {value!r}.") from None
        too_low = v <= self.low if self.low_open else v < self.low
        too_high = v >= self.high if self.high_open else v > self.high
        if not math.isfinite(v) or too_low or too_high:
            lo = "(" if self.low_open else "["
            hi = ")" if self.high_open else "]"
            raise InvalidParameterError(
                f"{where}: {self.doc or self.name} '{self.name}' = {v:g}{'' if self.unit == '-' else ' ' + self.unit} "
                f"is outside its valid range "
                f"{lo}{self.low:g}, {self.high:g}{hi}; set it inside that range."
            )
        return v


class _Pluggable:
    name: ClassVar[str]
    implementations: ClassVar[Mapping[str, str]] = {}

    @classmethod
    def implementation(cls, backend: str, kind: str) -> Any:
        if backend not in cls.implementations:
            raise MissingImplementationError(kind, cls.name, backend, list(cls.implementations))
        return load_object(cls.implementations[backend])


class AbstractConstitutiveLaw(_Pluggable, ABC):
    """A material's response, written as two pure per-particle functions on every backend.

    * ``kirchhoff(state, params) -> tau``: Kirchhoff stress tau = P F^T = J sigma, used by P2G.
    * ``update(state, grad_v, dt, params) -> state``: advance the law state over dt given the particle
      velocity gradient (elastic predictor + return map for hyperelastic laws, NCLaw Alg. 1; stress
      rate integration for hypo-elastic laws, JAX-MPM Eq. 21).

    ``state_fields`` is the subset of ``STATE_FIELDS`` the law carries: a J-based fluid declares only
    ``J``, so the stepper never stores or updates a full F for it. ``params`` are the user-facing
    parameters (units, ranges); backends receive them as a per-particle array ``[N, len(params)]`` in
    this order and derive moduli inline, so gradients reach E and nu directly.
    ``reference`` is a NumPy float64 module with the same two functions: the conformance oracle. A law
    whose state has no matrix field (J only) takes the dimension as ``kirchhoff(state, params, dim=D)``.
    """

    params: ClassVar[tuple[ParamSpec, ...]]
    state_fields: ClassVar[tuple[str, ...]]
    plastic: ClassVar[bool] = False
    reference: ClassVar[Any]
    #: the smallest stable CFL factor C* measured for this law over the transfers and both backends
    #: (``benchmarks/stress.py --full``), where it is below the library-wide safety margin; ``dt: auto``
    #: then uses at most C*/2 for scenes with this law (``Scene.effective_cfl``). None: no extra limit.
    stable_cfl: ClassVar[float | None] = None

    @classmethod
    def param_names(cls) -> tuple[str, ...]:
        return tuple(p.name for p in cls.params)

    @classmethod
    def resolve_params(cls, given: Mapping[str, Any], where: str, density: float | None = None) -> dict[str, float]:
        """Fill defaults, reject unknown names, check ranges; returns ``{name: float}`` in declared order."""
        known = cls.param_names()
        unknown = sorted(set(given) - set(known))
        if unknown:
            raise InvalidParameterError(
                f"{where}: law '{cls.name}' has no parameter(s) {', '.join(unknown)}; its parameters are "
                f"{', '.join(known)}."
            )
        out = {}
        for spec in cls.params:
            value = given.get(spec.name, spec.default)
            if value is None:
                value = cls.default_from_density(spec.name, density)
            if value is None:
                raise InvalidParameterError(f"{where}: law '{cls.name}' needs parameter '{spec.name}' [{spec.unit}].")
            out[spec.name] = spec.check(value, where)
        cls.check_consistency(out, where)
        return out

    @classmethod
    def default_from_density(cls, name: str, density: float | None) -> float | None:
        """Defaults that depend on the body (e.g. a fluid's rest density); None if there is none."""
        return None

    @classmethod
    def check_consistency(cls, params: Mapping[str, float], where: str) -> None:
        """Cross-parameter checks (override where needed)."""

    @classmethod
    @abstractmethod
    def wave_speed(cls, params: Mapping[str, float], density: float) -> float:
        """Largest elastic wave speed [m/s] (P-wave or sound speed) for the CFL bound."""

    @classmethod
    def initial_state(cls, n: int, dim: int) -> dict[str, np.ndarray]:
        out = {}
        for f in cls.state_fields:
            if STATE_FIELDS[f] == "mat":
                out[f] = np.repeat(np.eye(dim)[None], n, axis=0) if f == "F" else np.zeros((n, dim, dim))
            else:
                out[f] = np.ones(n) if f == "J" else np.zeros(n)
        return out


class AbstractTransfer(_Pluggable, ABC):
    """How velocity (and affine / gradient data) goes particle -> grid -> particle.

    A transfer is described by four choices that the backend kernels specialise on at build time:

    * ``affine``: what the particle carries besides v: ``None`` (PIC/FLIP, no ``C`` stored),
      ``"apic"`` (B D^-1, Jiang et al. 2015; JAX-MPM Eq. B.1), or ``"velocity_gradient"``
      (TPIC, JAX-MPM Eq. B.2).
    * ``force``: ``"gradient"`` (f_i = -sum V tau grad w, JAX-MPM Eq. 12) or ``"mls"`` (Hu et al. 2018,
      f_i = -sum V M^-1 tau (x_i - x_p) w with M^-1 = 4/dx^2 for quadratic B-splines).
    * ``grad_v``: the particle velocity gradient fed to the law: ``"gradient"`` (sum v_i (x) grad w,
      JAX-MPM Eq. 18) or ``"affine"`` (the MLS C).
    * ``flip_ratio``: None for PIC-style G2P, else the FLIP blend (1 = pure FLIP, JAX-MPM Eq. 15).
    """

    affine: ClassVar[str | None] = None
    force: ClassVar[str] = "gradient"
    grad_v: ClassVar[str] = "gradient"
    flip_ratio: float | None = None

    @property
    def needs_affine(self) -> bool:
        return self.affine is not None

    def options(self) -> dict[str, Any]:
        return {"flip_ratio": self.flip_ratio} if self.flip_ratio is not None else {}


class AbstractBoundary(_Pluggable, ABC):
    """A grid post-process step (walls, friction, planes, obstacles) or a particle-set constraint/load.

    ``stage`` says where the step acts: ``"grid"`` (after the grid velocity update, before G2P),
    ``"particle_velocity"`` (overrides particle velocities after G2P) or ``"particle_force"`` (adds a
    force to particles in P2G). Backends look up ``implementations[backend]`` to build it.
    """

    stage: ClassVar[str] = "grid"

    @abstractmethod
    def validate(self, scene) -> None:
        """Raise ConfigError if this boundary does not fit the scene (dimension, extents)."""


class AbstractObservation(_Pluggable, ABC):
    """Maps a state to what an instrument sees (JAX-MPM Eqs. 26-27)."""


class AbstractStepper(ABC):
    """A compiled simulator for one scene and option set, built by a backend.

    ``init() -> state``; ``step(state) -> state``; ``rollout(state, steps, every) -> Trajectory``.
    Backend arrays stay inside; ``to_numpy(state)`` gives a dict of numpy arrays.
    """

    @abstractmethod
    def init(self):
        ...

    @abstractmethod
    def step(self, state):
        ...

    @abstractmethod
    def rollout(self, state, steps: int, every: int = 1, **kw):
        ...

    @abstractmethod
    def to_numpy(self, state) -> dict[str, np.ndarray]:
        ...

    # ---- differentiable entry points (issue #4) ------------------------------------------------
    # Both backends expose the same two calls; arrays are the backend's differentiable arrays (JAX:
    # jax arrays under jax.grad; Warp: torch tensors through a torch.autograd.Function).
    #
    # ``controls()`` -> dict, scene (not storage) order:
    #   x [N, D], v [N, D]    initial particle positions and velocities
    #   law                   tuple, one [count, P] array per material group (law.param_names() order)
    #   boundary              tuple, one dict per scene boundary (e.g. friction_walls {"mu": [S]})
    #   gravity [D], mass [N], volume [N]
    # ``observe(controls, observation, steps, segment=...)`` -> [T, L, d]: the observation operator
    #   applied to the state after each step in ``steps`` (sorted; 0 = initial state), the rollout
    #   run from ``controls``; gradients are recomputed per segment of ``segment`` steps so memory is
    #   O(steps / segment + segment) states. A non-finite gradient raises ``GradientError``.
    def controls(self) -> dict:
        raise NotImplementedError(f"{type(self).__name__} has no differentiable entry points.")

    def observe(self, controls: dict, observation, steps, segment: int | None = None):
        raise NotImplementedError(f"{type(self).__name__} has no differentiable entry points.")


class AbstractBackend(ABC):
    """A registered backend: builds steppers and converts arrays."""

    name: ClassVar[str]

    @abstractmethod
    def build(self, scene, transfer: AbstractTransfer, precision: str = "fp32", **options) -> AbstractStepper:
        ...
