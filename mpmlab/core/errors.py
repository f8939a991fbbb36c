"""Errors a user can cause. Each carries one sentence: what is wrong, where, and what to do.

The CLI prints ``str(err)`` without a traceback and exits non-zero (see ``mpmlab.cli``).
"""
from __future__ import annotations


def first_line(text) -> str:
    """The first non-blank line of a (library's multi-line) message, stripped."""
    return next((line.strip() for line in str(text).splitlines() if line.strip()), "")


class MpmlabError(Exception):
    """Base class of every error mpmlab raises for a user mistake or a failed simulation."""


class ConfigError(MpmlabError):
    """A configuration value is wrong (bad type, out of range, inconsistent)."""


class InvalidParameterError(ConfigError):
    """A material or scene parameter lies outside its valid range."""


class UnknownPluginError(ConfigError):
    """A registered name (law, transfer, boundary, observation, backend, scene) does not exist."""

    def __init__(self, kind: str, name: str, known: list[str]):
        self.kind, self.name, self.known = kind, name, known
        super().__init__(
            f"unknown {kind} '{name}'; known {kind}s: {', '.join(sorted(known)) or '(none)'}. "
            f"Pick one of those, or install the plugin package that provides '{name}'."
        )


class MissingImplementationError(ConfigError):
    """A plugin exists but has no implementation for the chosen backend."""

    def __init__(self, kind: str, name: str, backend: str, available: list[str]):
        self.kind, self.name, self.backend = kind, name, backend
        super().__init__(
            f"{kind} '{name}' has no implementation for backend '{backend}' "
            f"(implemented for: {', '.join(sorted(available)) or 'none'}); choose another backend or {kind}."
        )


class TimeStepError(ConfigError):
    """The requested time step exceeds the CFL bound."""


class SimulationDiverged(MpmlabError):
    """A guard found a non-finite value, an inverted element or a particle outside the domain.

    Attributes:
        step: the first step at which the bad value was seen.
        particle: index of the offending particle.
        field: name of the field (``x``, ``v``, ``F``, ``J``, ...).
        value: the offending value (as a Python float or a short string).
        trajectory: the frames produced before the failure (a ``Trajectory``), or None.
        cause: what grew, as classified by ``mpmlab.core.diagnosis`` from the states just before the
            failure: ``cfl``, ``compression``, ``cell_crossing``, ``velocity``, ``law``, ``domain``,
            ``unknown``; None where no diagnosis ran (the initial state, a non-reproduced failure).
        measures: the measured numbers behind ``cause`` (CFL numbers, J, moves per step, J ripple, ...).
    """

    def __init__(self, step: int, particle: int, field: str, value, hint: str = "", trajectory=None,
                 cause: str | None = None, measures: dict | None = None):
        self.step, self.particle, self.field, self.value, self.hint = step, particle, field, value, hint
        self.trajectory = trajectory
        self.cause, self.measures = cause, dict(measures or {})
        msg = f"simulation diverged at step {step}: particle {particle} has {field} = {value}"
        if hint:
            msg += f"; {hint}"
        super().__init__(msg)


class FitDiverged(MpmlabError):
    """The loss of a fit became NaN/Inf (the optimiser pushed the parameters somewhere unstable); the CLI
    exits with the divergence code (3)."""


class GradientError(MpmlabError):
    """A gradient through a rollout became NaN/Inf; names where it arose (never silently zeroed).

    Attributes: step (the step whose backward pass first produced a non-finite adjoint), particle
    (index in scene order, or -1 for a non-particle quantity), field (state field or control name).
    """

    def __init__(self, step: int, particle: int, field: str, hint: str = ""):
        self.step, self.particle, self.field, self.hint = step, particle, field, hint
        where = f"particle {particle}" if particle >= 0 else "a non-particle quantity"
        msg = f"gradient became non-finite in the backward pass of step {step}, at {where}, field '{field}'"
        msg += f"; {hint}" if hint else "; check for J near 0, exactly repeated singular values or a diverging rollout there."
        super().__init__(msg)
