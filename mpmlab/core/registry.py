"""Name -> plugin registries, filled by built-ins and by entry points.

Every plugin kind has one registry keyed by a stable snake_case name (the name also goes into
HDF5 and rerun metadata). Built-ins are registered as ``"module:attr"`` strings and imported only
when asked for, so importing mpmlab never imports JAX or Warp. Third-party packages add plugins
through the entry-point groups ``mpmlab.laws``, ``mpmlab.transfers``, ``mpmlab.shapes``, ``mpmlab.boundaries``,
``mpmlab.body_forces`` (fields of the ``body_force`` boundary), ``mpmlab.observations``,
``mpmlab.backends`` and ``mpmlab.scenes``.
"""
from __future__ import annotations

import importlib
from importlib.metadata import entry_points
from typing import Any

from .errors import ConfigError, UnknownPluginError

KINDS = {
    "law": "mpmlab.laws",
    "transfer": "mpmlab.transfers",
    "shape": "mpmlab.shapes",
    "boundary": "mpmlab.boundaries",
    "body_force_field": "mpmlab.body_forces",
    "observation": "mpmlab.observations",
    "backend": "mpmlab.backends",
    "scene": "mpmlab.scenes",
}


def load_object(path: str) -> Any:
    """Import ``"pkg.module:attr"`` (or ``"pkg.module.attr"``)."""
    if ":" in path:
        module, attr = path.split(":", 1)
    else:
        module, attr = path.rsplit(".", 1)
    obj = importlib.import_module(module)
    for part in attr.split("."):
        obj = getattr(obj, part)
    return obj


class Registry:
    """Registry of one plugin kind."""

    def __init__(self, kind: str):
        self.kind = kind
        self.group = KINDS[kind]
        self._paths: dict[str, str] = {}
        self._objects: dict[str, Any] = {}
        self._provenance: dict[str, str] = {}
        self._entry_points_loaded = False

    def register(self, name: str, target: Any, provenance: str = "mpmlab") -> None:
        """Register ``target`` (an object or a ``"module:attr"`` string) under ``name``."""
        if isinstance(target, str):
            self._paths[name] = target
            self._objects.pop(name, None)
        else:
            self._objects[name] = target
        self._provenance[name] = provenance

    def _load_entry_points(self) -> None:
        if self._entry_points_loaded:
            return
        self._entry_points_loaded = True
        for ep in entry_points(group=self.group):
            if ep.name in self._paths or ep.name in self._objects:
                continue  # built-ins win; a plugin cannot silently replace one
            dist = f"{ep.dist.name} {ep.dist.version}" if ep.dist is not None else "entry point"
            self.register(ep.name, ep.value, provenance=dist)

    def names(self) -> list[str]:
        self._load_entry_points()
        return sorted(set(self._paths) | set(self._objects))

    def __contains__(self, name: str) -> bool:
        return name in self.names()

    def get(self, name: str) -> Any:
        """The plugin object for ``name``; an unknown name raises ``UnknownPluginError``."""
        self._load_entry_points()
        if name in self._objects:
            return self._objects[name]
        if name not in self._paths:
            raise UnknownPluginError(self.kind, name, self.names())
        obj = load_object(self._paths[name])
        self._objects[name] = obj
        return obj

    def build(self, spec) -> Any:
        """An instance from a config mapping ``{"kind": name, **options}`` (boundaries, observations)."""
        spec = dict(spec)
        name = spec.pop("kind", None)
        if name is None:
            raise ConfigError(f"{self.kind} {spec} needs a 'kind'; known: {', '.join(self.names())}.")
        cls = self.get(name)
        try:
            return cls(**spec)
        except TypeError as exc:
            raise ConfigError(f"{self.kind} '{name}': {exc}; check the option names.") from None

    def provenance(self, name: str) -> str:
        self._load_entry_points()
        return self._provenance.get(name, "unknown")


REGISTRIES = {kind: Registry(kind) for kind in KINDS}
laws = REGISTRIES["law"]
transfers = REGISTRIES["transfer"]
shapes = REGISTRIES["shape"]
boundaries = REGISTRIES["boundary"]
body_forces = REGISTRIES["body_force_field"]
observations = REGISTRIES["observation"]
backends = REGISTRIES["backend"]
scenes = REGISTRIES["scene"]


def get(kind: str, name: str) -> Any:
    return REGISTRIES[kind].get(name)


def _register_builtins() -> None:
    for name in ("fixed_corotated", "hencky_drucker_prager", "hencky_von_mises", "weakly_compressible",
                 "newtonian_fluid", "drucker_prager_jaumann", "nclaw", "phase_change"):
        laws.register(name, f"mpmlab.laws.{name}:Law")
    for name in ("pic", "flip", "apic", "mls", "tpic"):
        transfers.register(name, f"mpmlab.transfers.{name}:Transfer")
    for name in ("quadratic", "cubic", "ugimp", "cpdi"):
        shapes.register(name, f"mpmlab.shapes.{name}:Shape")
    backends.register("jax", "mpmlab.backends.jax:JaxBackend")
    backends.register("warp", "mpmlab.backends.warp:WarpBackend")
    for name, cls in (("walls", "Walls"), ("friction_walls", "FrictionWalls"), ("plane", "Plane"),
                      ("box_obstacle", "BoxObstacle"), ("particle_velocity", "ParticleVelocity"),
                      ("grid_velocity", "GridVelocity"), ("particle_load", "ParticleLoad")):
        boundaries.register(name, f"mpmlab.boundaries:{cls}")
    boundaries.register("body_force", "mpmlab.boundaries.body_force:BodyForce")
    for name, cls in (("uniform", "UniformField"), ("mms_axis_aligned", "MMSAxisAligned"),
                      ("expression", "ExpressionField")):
        body_forces.register(name, f"mpmlab.boundaries.body_force:{cls}")
    observations.register("lagrangian", "mpmlab.observations:Lagrangian")
    observations.register("particle_state", "mpmlab.observations:ParticleState")
    observations.register("eulerian", "mpmlab.observations:Eulerian")


_register_builtins()
