"""Prescribed body forces b(X, t) per unit mass, evaluated at every particle's reference position X
(its position at t = 0) and the time at the start of each step, on both backends.

``body_force`` is a boundary of stage ``particle_force``: the stepper adds ``m_p b(X_p, t)`` to the
particle's external force in P2G, exactly where gravity-like loads enter (JAX-MPM Eq. 13). A scene
without it compiles no body-force code (DESIGN "Skip what a scene doesn't need").

The force is a registered *field* (``BodyForceField``; registry ``mpmlab.core.registry.body_forces``,
entry-point group ``mpmlab.body_forces``): a closed form written once as ``evaluate(xp, X, t, p, dim,
options)`` for NumPy (the float64 oracle) and JAX, and as a Warp ``@wp.func`` factory ``warp_func(dim,
precision, options)``. A field declares whether b depends on the reference position X (``position =
"reference"``, the particle's position at t = 0) or on the current one x (``"current"``). An unknown
field is refused with the registered names; a field without a Warp implementation is refused by the
Warp stepper (never replaced by another formula). Built-in fields:

* ``uniform`` -- a constant acceleration ``g`` (a second gravity that may be switched on in a window).
* ``expression`` -- one expression string per component (``b``) in ``X[k]`` (or ``x[k]``: then b
  depends on the current position), ``t``, ``pi`` and named ``constants`` (their values are the
  field's differentiable parameters), parsed safely (``mpmlab.core.expressions``) into the NumPy/JAX
  evaluation and generated Warp code: ``values={"b": ["a * t", "c * X[0]"], "constants": {"a": 2, "c": 3}}``.
* ``mms_axis_aligned`` -- the axis-aligned manufactured solution of verification note #2a (Wallstedt &
  Guilkey 2008 JCP 227:9628; Uintah ``MPM/MMS/MMS.cc`` "AxisAligned"; unit cube):
  ``U_i = A sin(pi X_i) sin(pi c t + pi phi_i)``, a diagonal ``F_ii = 1 + A pi cos(pi X_i) sin(.)``,
  and the body force that makes it exact for the chosen law (derived in verification.md #2a,
  re-derived here from ``rho0 U_tt = dP_ii/dX_i + rho0 b_i`` with only ``F_ii`` depending on ``X_i``):

  - fixed corotated (R = I for diagonal F > 0, ``P_ii = 2 mu (F_ii - 1) + lambda (J - 1) J / F_ii``):
    ``b_i = -pi^2 c^2 U_i + pi^2 U_i [2 mu + lambda (J / F_ii)^2] / rho0``;
  - Hencky (``P_ii = (2 mu ln F_ii + lambda ln J) / F_ii``):
    ``b_i = -pi^2 c^2 U_i + pi^2 U_i [(2 mu + lambda) - 2 mu ln F_ii - lambda ln J] / (rho0 F_ii^2)``.

  ``shift`` s replaces X_i by X_i + s in U and F (the formulas for b are unchanged). s = 1/2 puts
  the unit cube's faces where F_ii = 1: with nu = 0 (lambda = 0) every face is then traction free, a
  free-floating body with no wall (see ``mpmlab.scenes.validation.mms_axis_aligned``).

  2D is plane strain (the same formulas with two components). The default phases ``phi = 0`` give
  U = 0 and F = I at t = 0, so the particles start undeformed with velocity ``dU/dt = A pi c sin(pi X)``
  (the note's phases 2/3, 4/3 need the exact initial F: ``Body(F=...)``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field as dc_field
from functools import lru_cache
from typing import Any, ClassVar, Mapping, Sequence

import numpy as np

from ..core import registry
from ..core.errors import ConfigError, MissingImplementationError
from ..core.interfaces import AbstractBoundary

MMS_LAWS = ("fixed_corotated", "hencky")
POSITIONS = ("reference", "current")


class BodyForceField:
    """A body force per unit mass b(position, t) [m/s^2]: subclass, then ``register_field``.

    * ``name``: the registered name (``BodyForce(field=name)``, ``scene.boundaries.<b>.extra.field``).
    * ``position``: ``"reference"`` (b(X, t), X the particle's position at t = 0: a manufactured
      solution) or ``"current"`` (b(x, t), x its position at the start of the step).
    * ``defaults``: the options ``values`` may set, with their defaults. Numbers (and number lists)
      are packed, in this order, into the parameter array ``p`` both backends read (differentiable:
      ``controls()["boundary"][i]["field"]``); strings are ``options`` that change the compiled code.
    * ``evaluate(xp, X, t, p, dim, options) -> [N, D]``: the formula on ``xp`` = ``numpy`` (the oracle)
      or ``jax.numpy`` (X: ``[N, D]``, t: a scalar, p: the packed array).
    * ``warp_func(dim, precision, options)``: a ``@wp.func (X: vec, t: scalar, p: wp.array(dtype=scalar))
      -> vec`` of the same formula (types from ``mpmlab.backends.warp.types.warp_types(dim, precision)``),
      or a ``"module:function"`` path to such a factory (imported only by the Warp backend); None: the
      field runs on JAX only and the Warp stepper refuses it.
    """

    name: ClassVar[str] = ""
    position: ClassVar[str] = "reference"
    defaults: ClassVar[dict] = {}
    warp_func: ClassVar[Any] = None

    @classmethod
    def resolved(cls, values: Mapping[str, Any]) -> dict[str, Any]:
        unknown = set(values) - set(cls.defaults)
        if unknown:
            raise ConfigError(f"body_force '{cls.name}': unknown option(s) {sorted(unknown)}; "
                              f"options are {sorted(cls.defaults)}.")
        return {**cls.defaults, **dict(values)}

    @classmethod
    def position_of(cls, values: Mapping[str, Any]) -> str:
        return cls.position

    @classmethod
    def options(cls, values: Mapping[str, Any]) -> dict[str, Any]:
        """The string options (they select code: the compiled kernels are keyed on them)."""
        return {k: v for k, v in cls.resolved(values).items() if isinstance(v, str)}

    @classmethod
    def pack(cls, values: Mapping[str, Any], dim: int) -> np.ndarray:
        nums = [np.asarray(v, float).ravel() for v in cls.resolved(values).values() if not isinstance(v, str)]
        # at least one entry: a field without numbers still gets a (dummy) parameter array
        return np.concatenate(nums) if nums and sum(len(a) for a in nums) else np.zeros(1)

    @staticmethod
    def evaluate(xp, X, t, p, dim: int, options: Mapping[str, Any]):
        raise NotImplementedError

    @classmethod
    def check(cls, values: Mapping[str, Any], dim: int) -> None:
        """Refuse bad values before anything is built (default: pack them)."""
        cls.pack(values, dim)


def register_field(field: type, name: str | None = None, provenance: str = "user") -> type:
    """Register a ``BodyForceField`` subclass (under ``name``, default ``field.name``); returns it, so it
    can decorate the class. A built-in name cannot be replaced."""
    name = name or getattr(field, "name", "")
    if not (isinstance(field, type) and issubclass(field, BodyForceField)):
        raise ConfigError(f"body_force field {field!r}: register a subclass of BodyForceField.")
    if not name:
        raise ConfigError(f"body_force field {field.__name__}: give it a name.")
    if name in registry.body_forces and registry.body_forces.provenance(name) == "mpmlab":
        raise ConfigError(f"body_force field '{name}' is built in; register yours under another name.")
    if field.position not in POSITIONS:
        raise ConfigError(f"body_force field '{name}': position = {field.position!r} must be one of {POSITIONS}.")
    registry.body_forces.register(name, field, provenance=provenance)
    return field


class UniformField(BodyForceField):
    """b = g (constant acceleration, D components)."""

    name = "uniform"
    defaults = {"g": (0.0, 0.0, 0.0)}
    warp_func = "mpmlab.backends.warp.body_force:uniform_func"

    @classmethod
    def pack(cls, values: Mapping[str, Any], dim: int) -> np.ndarray:
        cls.resolved(values)
        g = np.asarray(values.get("g", (0.0,) * dim), float)
        if g.shape != (dim,):
            raise ConfigError(f"body_force 'uniform': g needs {dim} components.")
        return g

    @staticmethod
    def evaluate(xp, X, t, p, dim: int, options: Mapping[str, Any]):
        return xp.broadcast_to(p[None, :dim], X.shape) + 0.0 * X


class MMSAxisAligned(BodyForceField):
    """Verification note #2a (see the module docstring); ``law`` is ``fixed_corotated`` or ``hencky``."""

    name = "mms_axis_aligned"
    defaults = {"A": 0.05, "c": None, "E": 1.0e4, "nu": 0.3, "density": 1.0, "law": "fixed_corotated",
                "phase": (0.0, 0.0, 0.0), "shift": 0.0}
    warp_func = "mpmlab.backends.warp.body_force:mms_axis_aligned_func"

    @staticmethod
    def lame(E: float, nu: float) -> tuple[float, float]:
        return E / (2.0 * (1.0 + nu)), E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))

    @classmethod
    def resolved(cls, values: Mapping[str, Any]) -> dict[str, Any]:
        v = super().resolved(values)
        if v["c"] is None:                       # the note's c = sqrt(E / rho0)
            v["c"] = math.sqrt(float(v["E"]) / float(v["density"]))
        if v["law"] not in MMS_LAWS:
            raise ConfigError(f"body_force 'mms_axis_aligned': law '{v['law']}' must be one of {MMS_LAWS}.")
        return v

    @classmethod
    def pack(cls, values: Mapping[str, Any], dim: int) -> np.ndarray:
        """[A, c, mu, lambda, rho0, phi_0, phi_1, phi_2, shift] (the parameter array both backends read)."""
        v = cls.resolved(values)
        mu, lam = cls.lame(float(v["E"]), float(v["nu"]))
        ph = list(np.asarray(v["phase"], float).ravel()) + [0.0] * 3
        return np.asarray([float(v["A"]), float(v["c"]), mu, lam, float(v["density"])] + ph[:3] + [float(v["shift"])],
                          float)

    @staticmethod
    def exact(xp, X, t, p, dim: int):
        """Displacement U [N, D] and the diagonal of F [N, D] at time t."""
        A, c = p[0], p[1]
        pi = math.pi
        s = xp.stack([xp.sin(pi * c * t + pi * p[5 + i]) for i in range(dim)], axis=-1)
        U = A * xp.sin(pi * (X + p[8])) * s
        Fd = 1.0 + A * pi * xp.cos(pi * (X + p[8])) * s
        return U, Fd

    @classmethod
    def evaluate(cls, xp, X, t, p, dim: int, options: Mapping[str, Any]):
        A, c, mu, lam, rho = p[0], p[1], p[2], p[3], p[4]
        pi = math.pi
        U, Fd = cls.exact(xp, X, t, p, dim)
        J = xp.prod(Fd, axis=-1, keepdims=True)
        if options.get("law", "fixed_corotated") == "hencky":
            coef = ((2.0 * mu + lam) - 2.0 * mu * xp.log(Fd) - lam * xp.log(J)) / (Fd * Fd)
        else:
            K = J / Fd
            coef = 2.0 * mu + lam * K * K
        return pi * pi * U * (coef / rho - c * c)

    @classmethod
    def velocity(cls, X, t, p, dim: int) -> np.ndarray:
        """dU/dt = A pi c sin(pi (X_i + shift)) cos(pi c t + pi phi_i)."""
        A, c = p[0], p[1]
        cs = np.stack([np.cos(math.pi * c * t + math.pi * p[5 + i]) for i in range(dim)], axis=-1)
        return A * math.pi * c * np.sin(math.pi * (X + p[8])) * cs


class ExpressionField(BodyForceField):
    """b given as one expression string per component (``b``), in ``X[k]`` *or* ``x[k]`` (the expression
    says which: b(X, t) or b(x, t); both at once is refused), ``t``, ``pi`` and the names of
    ``constants`` (numbers: the packed, differentiable parameters, in sorted name order)."""

    name = "expression"
    position_label = "X or x (as written)"
    defaults = {"b": None, "constants": {}}
    warp_func = "mpmlab.backends.warp.body_force:expression_func"

    @classmethod
    def resolved(cls, values: Mapping[str, Any]) -> dict[str, Any]:
        v = super().resolved(values)
        if not isinstance(v["b"], (list, tuple)) or not v["b"]:
            raise ConfigError("body_force 'expression': b must be a list of one expression per component, "
                              "e.g. b: ['2 * t', '3 * X[0]'].")
        if not isinstance(v["constants"], Mapping):
            raise ConfigError(f"body_force 'expression': constants = {v['constants']!r} must map names to numbers.")
        return v

    @classmethod
    def options(cls, values: Mapping[str, Any]) -> dict[str, Any]:
        v = cls.resolved(values)
        return {"b": tuple(str(e) for e in v["b"]), "constants": tuple(sorted(v["constants"]))}

    @classmethod
    def parsed(cls, options: Mapping[str, Any], dim: int) -> tuple[list, str]:
        """(the component ``Expression``s, their position name ``X`` or ``x``)."""
        return _parse_expression_field(tuple(options["b"]), tuple(options["constants"]), dim)

    @classmethod
    def position_of(cls, values: Mapping[str, Any]) -> str:
        o = cls.options(values)
        return "current" if cls.parsed(o, len(o["b"]))[1] == "x" else "reference"

    @classmethod
    def pack(cls, values: Mapping[str, Any], dim: int) -> np.ndarray:
        v = cls.resolved(values)
        if len(v["b"]) != dim:
            raise ConfigError(f"body_force 'expression': b has {len(v['b'])} components; the scene is {dim}D.")
        cls.parsed(cls.options(values), dim)
        try:
            c = [float(v["constants"][k]) for k in sorted(v["constants"])]
        except (TypeError, ValueError):
            raise ConfigError(f"body_force 'expression': constants {dict(v['constants'])} must be numbers.") from None
        return np.asarray(c or [0.0], float)

    @classmethod
    def evaluate(cls, xp, X, t, p, dim: int, options: Mapping[str, Any]):
        exprs, pos = cls.parsed(options, dim)
        env = {pos: X, "t": t, **{k: p[i] for i, k in enumerate(options["constants"])}}
        return xp.stack([e.evaluate(xp, env, X.shape[0]) for e in exprs], axis=-1)


@lru_cache(maxsize=None)
def _parse_expression_field(b: tuple, constants: tuple, dim: int):
    from ..core.expressions import Expression

    exprs = [Expression(e, vectors=("X", "x"), scalars=("t",), constants=constants, dim=dim,
                        where=f"boundary 'body_force' (field 'expression'), b[{i}]") for i, e in enumerate(b)]
    used = set().union(*(e.used for e in exprs)) & {"X", "x"}
    if len(used) == 2:
        raise ConfigError("body_force 'expression': b uses both X (reference position) and x (current "
                          "position); write it in one of them.")
    return exprs, (used.pop() if used else "X")


def warp_func_of(field: type, name: str, dim: int, precision: str, options: Mapping[str, Any]):
    """``field``'s Warp ``@wp.func`` for these code options; a field without one is refused (a visible
    gap: the Warp stepper never falls back to another formula)."""
    impl = field.warp_func
    if impl is None:
        raise MissingImplementationError("body_force field", name, "warp", ["jax"])
    if isinstance(impl, str):
        impl = registry.load_object(impl)
    return impl(dim, precision, dict(options))


@dataclass(frozen=True)
class BodyForce(AbstractBoundary):
    """A body force per unit mass ``b(X, t)`` (or ``b(x, t)``, as the field declares) [m/s^2] from the
    registered ``field`` with options ``values``, on every particle (or those of ``bodies``, body
    indices), during [t_start, t_end).

    ``b`` is evaluated at the particle's reference position X (t = 0) or its current position, and at
    the time at the start of the step, and enters P2G as the external force m_p b (as gravity and
    ``particle_load`` do).
    """

    name: ClassVar[str] = "body_force"
    implementations: ClassVar[dict] = {"jax": "mpmlab.backends.jax.body_force:body_force",
                                       "warp": "mpmlab.backends.warp.body_force:body_force"}
    gradients: ClassVar[tuple] = ("jax", "warp")
    stage: ClassVar[str] = "particle_force"
    field: str = "mms_axis_aligned"
    values: Mapping[str, Any] = dc_field(default_factory=dict)
    bodies: Sequence[int] | None = None
    t_start: float = 0.0
    t_end: float = float("inf")

    @property
    def field_impl(self) -> type:
        if self.field not in registry.body_forces:
            raise ConfigError(f"boundary 'body_force': unknown field '{self.field}'; registered fields: "
                              f"{', '.join(registry.body_forces.names())} (add one with "
                              f"mpmlab.boundaries.body_force.register_field or the mpmlab.body_forces entry point).")
        return registry.body_forces.get(self.field)

    @property
    def options(self) -> dict[str, Any]:
        """Non-numeric options that change the compiled code (the MMS law, an expression's strings)."""
        return self.field_impl.options(self.values)

    @property
    def position(self) -> str:
        """``"reference"``: b(X, t) at the particles' positions at t = 0; ``"current"``: b(x, t)."""
        return self.field_impl.position_of(self.values)

    def warp_func(self, dim: int, precision: str):
        """The field's Warp ``@wp.func`` (the Warp backend's call); a field without one is refused."""
        return warp_func_of(self.field_impl, self.field, dim, precision, self.options)

    def packed(self, dim: int) -> np.ndarray:
        return self.field_impl.pack(self.values, dim)

    def mask(self, scene) -> np.ndarray:
        """Per particle 1.0 where the force acts (the bodies selected), else 0.0."""
        P = scene.particles()
        if self.bodies is None:
            return np.ones(P.count)
        return np.isin(P.body_id, np.asarray(self.bodies, int)).astype(float)

    def evaluate(self, X: np.ndarray, t: float, dim: int) -> np.ndarray:
        """NumPy float64 reference b(X, t) [N, D] (the conformance oracle; ignores t_start/t_end; X is
        the current position for a ``current`` field)."""
        return self.field_impl.evaluate(np, np.asarray(X, float), float(t), self.packed(dim), dim, self.options)

    def validate(self, scene) -> None:
        f = self.field_impl
        f.check(self.values, scene.dim)
        if self.position not in POSITIONS:
            raise ConfigError(f"boundary 'body_force': field '{self.field}' declares position "
                              f"{self.position!r}; it must be one of {POSITIONS}.")
        if not self.t_end > self.t_start:
            raise ConfigError(f"boundary 'body_force': t_end = {self.t_end} must exceed t_start = {self.t_start}.")
        if self.bodies is not None and not self.mask(scene).any():
            raise ConfigError(f"boundary 'body_force': bodies {list(self.bodies)} select no particle.")
