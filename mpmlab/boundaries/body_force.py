"""Prescribed body forces b(X, t) per unit mass, evaluated at every particle's reference position X
(its position at t = 0) and the time at the start of each step, on both backends.

``body_force`` is a boundary of stage ``particle_force``: the stepper adds ``m_p b(X_p, t)`` to the
particle's external force in P2G, exactly where gravity-like loads enter (JAX-MPM Eq. 13). A scene
without it compiles no body-force code (DESIGN "Skip what a scene doesn't need").

The force is a registered *field* (``FIELDS``): a closed form written once as ``evaluate(xp, X, t, p)``
for NumPy (the float64 oracle) and JAX, and as a Warp ``@wp.func`` factory (``mpmlab.backends.warp.
body_force``). Built-in fields:

* ``uniform`` -- a constant acceleration ``g`` (a second gravity that may be switched on in a window).
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
  (mpmlab bodies start at F = I; the note's phases 2/3, 4/3 would need an initial F).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field as dc_field
from typing import Any, ClassVar, Mapping, Sequence

import numpy as np

from ..core.errors import ConfigError
from ..core.interfaces import AbstractBoundary

MMS_LAWS = ("fixed_corotated", "hencky")


class UniformField:
    """b = g (constant acceleration, D components)."""

    name = "uniform"
    defaults = {"g": (0.0, 0.0, 0.0)}

    @staticmethod
    def pack(values: Mapping[str, Any], dim: int) -> np.ndarray:
        g = np.asarray(values.get("g", (0.0,) * dim), float)
        if g.shape != (dim,):
            raise ConfigError(f"body_force 'uniform': g needs {dim} components.")
        return g

    @staticmethod
    def evaluate(xp, X, t, p, dim: int, options: Mapping[str, Any]):
        return xp.broadcast_to(p[None, :dim], X.shape) + 0.0 * X


class MMSAxisAligned:
    """Verification note #2a (see the module docstring); ``law`` is ``fixed_corotated`` or ``hencky``."""

    name = "mms_axis_aligned"
    defaults = {"A": 0.05, "c": None, "E": 1.0e4, "nu": 0.3, "density": 1.0, "law": "fixed_corotated",
                "phase": (0.0, 0.0, 0.0), "shift": 0.0}

    @staticmethod
    def lame(E: float, nu: float) -> tuple[float, float]:
        return E / (2.0 * (1.0 + nu)), E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))

    @classmethod
    def resolved(cls, values: Mapping[str, Any]) -> dict[str, Any]:
        unknown = set(values) - set(cls.defaults)
        if unknown:
            raise ConfigError(f"body_force 'mms_axis_aligned': unknown option(s) {sorted(unknown)}; "
                              f"options are {sorted(cls.defaults)}.")
        v = {**cls.defaults, **dict(values)}
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


FIELDS: dict[str, Any] = {"uniform": UniformField, "mms_axis_aligned": MMSAxisAligned}


@dataclass(frozen=True)
class BodyForce(AbstractBoundary):
    """A body force per unit mass ``b(X, t)`` [m/s^2] from the registered ``field`` with options
    ``values``, on every particle (or those of ``bodies``, body indices), during [t_start, t_end).

    ``b`` is evaluated at the particle's reference position X (t = 0) and at the time at the start of
    the step, and enters P2G as the external force m_p b (as gravity and ``particle_load`` do).
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
    def field_impl(self):
        if self.field not in FIELDS:
            raise ConfigError(f"boundary 'body_force': unknown field '{self.field}'; known fields are {sorted(FIELDS)}.")
        return FIELDS[self.field]

    @property
    def options(self) -> dict[str, Any]:
        """Non-numeric options that change the compiled code (the MMS law)."""
        f = self.field_impl
        return {"law": f.resolved(self.values)["law"]} if hasattr(f, "resolved") else {}

    def packed(self, dim: int) -> np.ndarray:
        return self.field_impl.pack(self.values, dim)

    def mask(self, scene) -> np.ndarray:
        """Per particle 1.0 where the force acts (the bodies selected), else 0.0."""
        P = scene.particles()
        if self.bodies is None:
            return np.ones(P.count)
        return np.isin(P.body_id, np.asarray(self.bodies, int)).astype(float)

    def evaluate(self, X: np.ndarray, t: float, dim: int) -> np.ndarray:
        """NumPy float64 reference b(X, t) [N, D] (the conformance oracle; ignores t_start/t_end)."""
        return self.field_impl.evaluate(np, np.asarray(X, float), float(t), self.packed(dim), dim, self.options)

    def validate(self, scene) -> None:
        self.packed(scene.dim)
        if not self.t_end > self.t_start:
            raise ConfigError(f"boundary 'body_force': t_end = {self.t_end} must exceed t_start = {self.t_start}.")
        if self.bodies is not None and not self.mask(scene).any():
            raise ConfigError(f"boundary 'body_force': bodies {list(self.bodies)} select no particle.")
