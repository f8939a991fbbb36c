"""A per-particle, time-dependent switch between two laws: each particle follows the ``before`` law
until its ``switch_time`` and the ``after`` law from then on (NCLaw Sec. 4.4, Fig. 4b: an ice cream
of PLASTICINE "gradually changing" into SAND from bottom to top, a time-varying phase transition).

Configuration (``material.options``)::

    law: phase_change
    options:
      before: {law: hencky_von_mises}                 # or {law: nclaw, options: {weights_file: ...}}
      after: {law: hencky_drucker_prager}
      switch_axis: 1                                  # optional: switch_time from the initial height
      switch_from: 0.25                               # [s] the lowest particle switches then ...
      switch_until: 0.75                              # [s] ... and the highest one then
    params: {before_E: 3.0e5, before_nu: 0.25, before_yield_stress: 5.0e3,
             after_E: 1.0e6, after_nu: 0.2, after_friction_angle: 25.0}

* **Parameters**: the two laws' own, prefixed ``before_`` and ``after_`` (per particle, differentiable
  like any law parameter), plus ``switch_time`` [s]. With ``switch_axis`` the switch time is set per
  particle from its initial coordinate h along that axis over the whole material group (bodies of one
  material share one threshold): t_s = switch_from + (h - h_min) / (h_max - h_min) (switch_until -
  switch_from), a threshold rising linearly, bottom first (NCLaw: "from bottom to top", over steps 500
  to 1500 of 2000 at dt = 5e-4 s, i.e. 0.25-0.75 s). Without it, ``switch_time`` is the body's value.
* **Shared weights**: the two laws' own, prefixed (``before_e_W1``, ...): a neural law on either side
  keeps its weights file and its gradients.
* **State**: the union of the two laws' fields by name (a field both declare, e.g. F, carries over at
  the switch: the new law starts from the deformation the old one left), plus ``clock``, the time since
  the run started [s], advanced by dt in every update. A field only one law declares is carried
  unchanged while the other law is active.
* **Which law**: a step from t to t + dt uses the law active at t (``clock < switch_time``: before);
  the Kirchhoff stress uses the law active at the particle's clock.

JAX evaluates both laws on every particle and selects (a ``where`` under ``vmap``, as a ``cond`` would
become): twice the law cost. Warp branches per particle. Both are differentiable through the two laws.

The law is one class per pair of law classes (``pair_class``), made when a configuration names them:
its parameters, state and stress symmetry follow the pair, so the stepper, the Warp structs, the
trajectory fields and the conformance kit see an ordinary law.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any, ClassVar, Mapping

import numpy as np

from ...core.errors import ConfigError
from ...core.interfaces import AbstractConstitutiveLaw, ParamSpec, StateField
from .._common import builtin_implementations
from . import reference as _reference

SIDES = ("before", "after")
SWITCH_TIME = ParamSpec("switch_time", "s", 0.0, low=0.0,
                        doc="time at which the particle leaves the 'before' law for the 'after' law")
CLOCK = StateField("clock", (), 0.0, unit="s", doc="time since the run started (phase_change: when to switch)")


def _side_config(spec: Any, side: str) -> tuple[str, dict]:
    where = f"law 'phase_change' option '{side}'"
    if isinstance(spec, str):
        return spec, {}
    if not isinstance(spec, Mapping) or "law" not in spec:
        raise ConfigError(f"{where}: give a law as {{law: NAME, options: {{...}}}} (e.g. {{law: hencky_von_mises}}); "
                          f"got {spec!r}.")
    extra = sorted(set(spec) - {"law", "options"})
    if extra:
        raise ConfigError(f"{where}: unknown key(s) {', '.join(extra)}; the law's parameters go in the material's "
                          f"params as {side}_<name>, its options under {side}.options.")
    return str(spec["law"]), dict(spec.get("options") or {})


def _sub_law(spec: Any, side: str) -> AbstractConstitutiveLaw:
    from ...core import registry

    name, options = _side_config(spec, side)
    if name == "phase_change":
        raise ConfigError(f"law 'phase_change' option '{side}': a phase_change law cannot switch to another one.")
    return registry.laws.get(name).from_config(options, f"law 'phase_change' option '{side}' ({name})")


@dataclass(frozen=True, eq=False)   # equality and hash: AbstractConstitutiveLaw's (the options hold dicts)
class Law(AbstractConstitutiveLaw):
    """Law ``before`` until ``switch_time``, law ``after`` from then on (module doc). Configured
    instances are of ``pair_class(before, after)``, a subclass that declares the pair's parameters
    and state."""

    name: ClassVar[str] = "phase_change"
    params = (SWITCH_TIME,)
    state = (CLOCK,)
    plastic = True
    clock_fields: ClassVar[tuple[str, ...]] = ("clock",)
    #: the capability table's parameters cell (the class's own are only switch_time)
    capability_params: ClassVar[str] = "the two laws' as before_*, after_*; switch_time [s]"
    reference = _reference
    implementations: ClassVar[dict] = builtin_implementations("phase_change")
    #: the exhaustive suites (every law x transfer x dimension) leave it out: its cases are its two laws'.
    #: tests/test_phase_change.py runs the conformance kit on a configured pair
    test_transfers: ClassVar[tuple] = ()
    test_options: ClassVar[Mapping[str, Any]] = {"before": {"law": "hencky_von_mises"},
                                                 "after": {"law": "fixed_corotated"}}

    #: the first law: ``{law: NAME, options: {...}}`` (or just the name)
    before: Any = None
    #: the second law, the same way
    after: Any = None
    #: with an axis (0, 1, 2), switch_time comes from the initial coordinate along it (module doc)
    switch_axis: int | None = None
    #: [s] switch time of the group's lowest particle along switch_axis
    switch_from: float = 0.0
    #: [s] switch time of its highest particle
    switch_until: float = 0.0

    # ---- one class per pair of laws -----------------------------------------------------------
    @classmethod
    def from_config(cls, options, where):
        options = dict(options or {})
        known = [f.name for f in dataclasses.fields(Law)]
        unknown = sorted(set(options) - set(known))
        if unknown:
            raise ConfigError(f"{where}: law 'phase_change' has no option(s) {', '.join(unknown)}; its options are "
                              f"{', '.join(known)}.")
        for side in SIDES:
            if options.get(side) is None:
                raise ConfigError(f"{where}: law 'phase_change' needs option '{side}' (a law: {{law: NAME, options: "
                                  f"{{...}}}}), e.g. material.options.{side}={{law: hencky_von_mises}}.")
        a, b = (_sub_law(options[s], s) for s in SIDES)
        pair = pair_class(type(a), type(b))
        norm = {s: {"law": type(x).name, "options": dict(_side_config(options[s], s)[1])} for s, x in zip(SIDES, (a, b))}
        return pair(**{**options, **norm})

    def __post_init__(self):
        if type(self) is Law:
            raise ConfigError("law 'phase_change': build it with Law.from_config({'before': ..., 'after': ...}, where) "
                              "(or material.options in a scene), which picks the class of the pair.")
        a, b = (_sub_law(getattr(self, s), s) for s in SIDES)
        if (type(a), type(b)) != self._pair:
            raise ConfigError(f"law 'phase_change': this class is for {self._pair[0].name} -> {self._pair[1].name}, "
                              f"the options name {a.name} -> {b.name}; use Law.from_config.")
        object.__setattr__(self, "before_law", a)
        object.__setattr__(self, "after_law", b)
        if self.switch_axis is not None:
            if self.switch_axis not in (0, 1, 2):
                raise ConfigError(f"law 'phase_change': switch_axis = {self.switch_axis!r} must be 0, 1 or 2 (x, y, z).")
            t0, t1 = float(self.switch_from), float(self.switch_until)
            if not (math.isfinite(t0) and math.isfinite(t1) and 0.0 <= t0 <= t1):
                raise ConfigError(f"law 'phase_change': switch_from = {self.switch_from!r} and switch_until = "
                                  f"{self.switch_until!r} must be times [s] with 0 <= switch_from <= switch_until.")

    def __reduce__(self):            # a pair class is made at run time: rebuild it by name on unpickling
        return (_rebuild, ({f.name: getattr(self, f.name) for f in dataclasses.fields(self)},))

    def sides(self):
        """``(("before", law), ("after", law))``."""
        return (("before", self.before_law), ("after", self.after_law))

    def code_key(self):
        """The kernels depend on the two laws' code, not on the switch times (those are parameters)."""
        return tuple((s, law.name, law.code_key()) for s, law in self.sides())

    # ---- per-particle switch times -------------------------------------------------------------
    def particle_params(self, params: np.ndarray, x: np.ndarray) -> np.ndarray:
        if self.switch_axis is None or len(x) == 0:
            return params
        if self.switch_axis >= x.shape[1]:
            raise ConfigError(f"law 'phase_change': switch_axis = {self.switch_axis} in a {x.shape[1]}D scene.")
        h = x[:, self.switch_axis]
        span = float(h.max() - h.min())
        s = (h - h.min()) / span if span > 0 else np.zeros_like(h)
        out = np.array(params, dtype=float, copy=True)
        out[:, self.param_names().index("switch_time")] = (float(self.switch_from)
                                                            + s * (float(self.switch_until) - float(self.switch_from)))
        return out

    # ---- the two laws' parameters and weights, by side --------------------------------------------
    def side_params(self, side: str, params: Mapping[str, Any]) -> dict:
        law = dict(self.sides())[side]
        return {n: params[f"{side}_{n}"] for n in law.param_names()}

    def side_weights(self, side: str, weights: Mapping[str, Any], dim: int) -> dict:
        law = dict(self.sides())[side]
        return {k: weights[f"{side}_{k}"] for k in law.weight_shapes(dim)}

    def weight_shapes(self, dim):
        return {f"{s}_{k}": v for s, law in self.sides() for k, v in law.weight_shapes(dim).items()}

    def weight_views(self, dim):
        return {f"{s}_{k}": (f"{s}_{src}", how) for s, law in self.sides()
                for k, (src, how) in law.weight_views(dim).items()}

    def initial_weights(self, dim):
        return {f"{s}_{k}": a for s, law in self.sides() for k, a in law.initial_weights(dim).items()}

    # ---- time step ---------------------------------------------------------------------------
    @classmethod
    def wave_speed(cls, params, density):
        if cls is Law:
            raise ConfigError("law 'phase_change': its wave speed is its two laws'; configure before and after.")
        return max(law.wave_speed({n: params[f"{s}_{n}"] for n in law.param_names()}, density)
                   for s, law in zip(SIDES, cls._pair))

    def instance_wave_speed(self, params, density, dim, weights):
        return max(law.instance_wave_speed(self.side_params(s, params), density, dim, self.side_weights(s, weights, dim))
                   for s, law in self.sides())


def _rebuild(options):
    return Law.from_config(options, "phase_change (unpickled)")


def _merged_state(a: type, b: type) -> tuple[StateField, ...]:
    fields: dict[str, StateField] = {}
    for law in (a, b):
        for f in law.state:
            if f.name == CLOCK.name:
                raise ConfigError(f"law 'phase_change': law '{law.name}' declares a state field 'clock', the switch's own.")
            if f.name in fields:
                g = fields[f.name]
                if g.shape != f.shape:
                    raise ConfigError(f"law 'phase_change': state field '{f.name}' is {g.shape} in one law and "
                                      f"{f.shape} in '{law.name}'; a field both laws carry must have one shape.")
                if g.check != f.check:      # the looser guard: either law may leave the field there
                    fields[f.name] = dataclasses.replace(g, check=None)
            else:
                fields[f.name] = f
    return (*fields.values(), CLOCK)


@lru_cache(maxsize=None)
def pair_class(a: type, b: type) -> type:
    """The ``phase_change`` law class of ``a`` -> ``b`` (law classes), one per pair."""
    params = tuple(dataclasses.replace(p, name=f"{s}_{p.name}", doc=f"{s} the switch: {p.doc or p.name}")
                   for s, law in zip(SIDES, (a, b)) for p in law.params) + (SWITCH_TIME,)
    caps = [c for c in (a.stable_cfl, b.stable_cfl) if c is not None]
    test_params = {**{f"{s}_{k}": v for s, law in zip(SIDES, (a, b)) for k, v in law.test_params.items()},
                   "switch_time": 0.0067}   # the kit draws clocks of 0.01 |N| s: about half switch
    qual = f"Law_{a.name}_to_{b.name}"
    ns = {"__qualname__": qual, "__module__": __name__, "params": params, "state": _merged_state(a, b),
          "plastic": bool(a.plastic or b.plastic), "symmetric_stress": bool(a.symmetric_stress and b.symmetric_stress),
          "stable_cfl": min(caps) if caps else None, "test_params": test_params, "_pair": (a, b),
          "__doc__": f"phase_change: '{a.name}' until switch_time, then '{b.name}' (mpmlab.laws.phase_change)."}
    return dataclass(frozen=True, eq=False)(type(qual, (Law,), ns))
