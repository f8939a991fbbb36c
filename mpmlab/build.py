"""Config -> objects: the one place a composed config (:mod:`mpmlab.config`) becomes mpmlab objects.

:func:`build_scene` turns ``cfg.scene`` + ``cfg.material`` into a :class:`mpmlab.Scene` (bodies,
boundaries, domain, time step), :func:`make_transfer_from_config` turns ``cfg.transfer`` into a transfer
scheme (:func:`shape_options_from_config` its shape function, a stepper option) and
:func:`make_boundary_from_config` one ``scene.boundaries`` entry into a boundary. Physics is
chosen by registered name (``material.law``, ``transfer.name``, ``scene.boundaries.<b>.kind``);
parameters are checked by the classes that own them (a law's ``ParamSpec`` ranges, a boundary's
``validate``, the scene's CFL bound) while the objects are built, so an error names the config key.

    from mpmlab.config import compose
    from mpmlab.build import build_scene
    scene = build_scene(compose(["scene=dam_break_2d", "scene.resolution=tiny"]))

(``mpmlab.config`` re-exports these names: ``from mpmlab.config import build_scene`` works too.)
"""
from __future__ import annotations

import math
from typing import Any

from omegaconf import DictConfig, ListConfig, OmegaConf

from .core import registry
from .core.errors import ConfigError


def _plain(node: Any) -> Any:
    """A resolved plain-Python copy (lists -> lists, dicts -> dicts), None for None."""
    if isinstance(node, (DictConfig, ListConfig)):
        return OmegaConf.to_container(node, resolve=True)
    return node


def _tuples(v: Any) -> Any:
    """Lists -> tuples, recursively (boundaries are frozen dataclasses)."""
    if isinstance(v, list):
        return tuple(_tuples(a) for a in v)
    if isinstance(v, dict):
        return {k: _tuples(a) for k, a in v.items()}
    return v


def _shape_dict(shape: Any) -> dict:
    return {k: v for k, v in _plain(shape).items() if v is not None}


def check_resolution(scene_cfg: DictConfig) -> None:
    """Refuse an unknown ``scene.resolution`` with the list of the scene's resolutions."""
    known = list(scene_cfg.resolutions.keys()) or ["default"]
    name = scene_cfg.resolution
    if name not in known:
        raise ConfigError(
            f"scene '{scene_cfg.name}' has no resolution '{name}'; choose one of {', '.join(known)} "
            f"(scene.resolution={known[0]})."
        )


def material_of(cfg: DictConfig, body_cfg: DictConfig | None = None) -> dict:
    """The material a body uses (its own, else the top-level ``material``) as a plain dict."""
    mat = body_cfg.material if body_cfg is not None and body_cfg.material is not None else cfg.material
    return _plain(mat)


def _body(cfg: DictConfig, name: str, b: DictConfig):
    from .core.scene import Body

    where = f"scene '{cfg.scene.name}', body '{name}'"
    if OmegaConf.is_missing(b, "shape") or OmegaConf.is_missing(b.shape, "kind"):
        raise ConfigError(f"{where}: no shape; set scene.bodies.{name}.shape.kind (box, sphere, cylinder, mesh).")
    mat_node = b.material if b.material is not None else cfg.material
    if mat_node is None or OmegaConf.is_missing(mat_node, "law"):
        raise ConfigError(f"{where}: no material; choose one with material=<name> or set scene.bodies.{name}.material.law.")
    mat = _plain(mat_node)
    registry.laws.get(mat["law"])  # unknown law -> the list of known laws
    density = mat.get("density")
    if isinstance(density, bool) or not isinstance(density, (int, float)) or not density > 0 \
            or not math.isfinite(density):
        key = f"scene.bodies.{name}.material.density" if b.material is not None else "material.density"
        raise ConfigError(f"{where}: {key} = {density} must be > 0 kg/m^3; set {key} to the material's "
                          f"rest density (water: 1000).")
    return Body(
        shape=_shape_dict(b.shape), material=mat["law"], params=dict(mat["params"]), density=float(mat["density"]),
        velocity=_plain(b.velocity), angular_velocity=_plain(b.angular_velocity),
        particles_per_cell=int(b.particles_per_cell), sampling=b.sampling, count=b.count,
        particle_volume=b.particle_volume, name=name, options=dict(mat.get("options") or {}),
        lattice=_plain(b.lattice), tracer=bool(b.tracer), F=_plain(b.F), C=_plain(b.C),
    )


def make_boundary_from_config(name: str, bc: DictConfig):
    """A boundary object from a ``BoundaryConfig`` node (options left null are not passed)."""
    import dataclasses

    spec = _plain(bc)
    kind = spec.pop("kind")
    spec.pop("enabled", None)
    extra = spec.pop("extra", None) or {}
    cls = registry.boundaries.get(kind)
    opts = {k: v for k, v in spec.items() if v is not None}
    if isinstance(opts.get("region"), dict):
        opts["region"] = {k: v for k, v in opts["region"].items() if v is not None}
    opts.update(extra)
    accepted = [f.name for f in dataclasses.fields(cls)] if dataclasses.is_dataclass(cls) else None
    if accepted is not None:
        wrong = sorted(set(opts) - set(accepted))
        if wrong:
            raise ConfigError(
                f"boundary '{name}' ({kind}) does not take option(s) {', '.join(wrong)}; it takes "
                f"{', '.join(accepted) or 'none'}. Remove them from scene.boundaries.{name}."
            )
    opts = {k: (v if k in ("faces", "region") else _tuples(v)) for k, v in opts.items()}
    try:
        return cls(**opts)
    except TypeError as exc:
        raise ConfigError(f"boundary '{name}' ({kind}): {exc}; check scene.boundaries.{name}.") from None


def _builder(name: str):
    if name in registry.scenes:
        return registry.scenes.get(name)
    if ":" in name or "." in name:
        try:
            return registry.load_object(name)
        except (ImportError, AttributeError) as exc:
            raise ConfigError(f"scene builder '{name}' cannot be imported ({exc}); check scene.builder.") from None
    registry.scenes.get(name)  # raises UnknownPluginError with the known names


def build_scene(cfg: DictConfig, validate: bool = True):
    """The ``mpmlab.Scene`` described by a composed config (``cfg.scene`` + ``cfg.material``).

    With ``validate`` (default) every check that can fail before a run is done here: law names and
    parameter ranges, shapes, particles inside the domain, boundary options, the CFL bound of a fixed
    ``dt``. Raises ``ConfigError`` (one sentence: what, where, what to do).
    """
    from .core.scene import Scene

    sc = cfg.scene
    check_resolution(sc)
    seed = int(cfg.get("seed", 0))
    if sc.builder:
        fn = _builder(sc.builder)
        args = _plain(sc.builder_args) or {}
        try:
            scene = fn(**args)
        except TypeError as exc:
            raise ConfigError(f"scene '{sc.name}': builder '{sc.builder}' rejected scene.builder_args ({exc}).") from None
        scene.name = sc.name
    else:
        bodies = [_body(cfg, name, b) for name, b in sc.bodies.items() if b.enabled]
        if not bodies:
            raise ConfigError(f"scene '{sc.name}' has no enabled body; add one under scene.bodies.")
        boundaries = [make_boundary_from_config(name, b) for name, b in sc.boundaries.items() if b.enabled]
        lo = [float(a) for a in sc.domain.lo]
        hi = [float(a) for a in sc.domain.hi]
        if len(lo) != sc.dim or len(hi) != sc.dim:
            raise ConfigError(f"scene '{sc.name}': scene.domain.lo and .hi need {sc.dim} coordinates each (dim = {sc.dim}).")
        pad = int(sc.domain.pad_cells) * float(sc.dx)
        dt = sc.dt
        if isinstance(dt, str) and dt != "auto":
            try:
                dt = float(dt)
            except ValueError:
                raise ConfigError(f"scene '{sc.name}': scene.dt = '{dt}' must be a number of seconds or 'auto'.") from None
        if dt != "auto":
            dt = float(dt)
            if not dt > 0 or not math.isfinite(dt):
                raise ConfigError(f"scene '{sc.name}': scene.dt = {dt:g} must be > 0 (seconds) or auto; "
                                  f"set scene.dt to a positive time step or scene.dt=auto.")
        scene = Scene(
            dim=int(sc.dim), dx=float(sc.dx), domain=([a - pad for a in lo], [b + pad for b in hi]), bodies=bodies,
            gravity=_plain(sc.gravity), boundaries=boundaries, dt=dt, cfl=float(sc.cfl),
            cfl_limit=float(sc.cfl_limit), name=sc.name, seed=seed, dt_every=int(sc.dt_every),
        )
    if validate:
        from .core.budget import memory_preflight

        memory_preflight(cfg, scene)   # before sampling: refuse what cannot fit (issue #12 item 5)
        scene.particles()
        if cfg.get("precision") is not None:           # (build_stepper checks again, for the Python API)
            from .simulator import check_representable

            check_representable(scene, str(cfg.precision.name))
        for b in scene.boundaries:
            b.validate(scene)
        scene.resolve_dt()
    return scene


def make_transfer_from_config(cfg: DictConfig):
    """The transfer scheme of ``cfg.transfer`` (its options; ``transfer.shape`` goes to the stepper:
    :func:`shape_options_from_config`)."""
    from .transfers import make_transfer

    opts = {k: v for k, v in _plain(cfg.transfer).items() if k not in ("name", "shape") and v is not None}
    return make_transfer(cfg.transfer.name, **opts)


def shape_options_from_config(cfg: DictConfig, scene=None, transfer=None) -> dict:
    """The stepper option for ``transfer.shape`` (``transfer: {name: apic, shape: cubic}``; issue 19):
    ``{"shape": name}``, or ``{}`` for the default quadratic B-spline (every backend's default).

    Checked here, before anything is written: an unknown name (the registry lists the registered
    ones), a shape the kernels cannot carry, one the transfer does not declare and, with the
    ``scene``, a particle too large for the shape's window or outside the region its window keeps on
    the grid (``mpmlab.shapes.resolve`` / ``inner_bounds``; ``ConfigError``, one line each)."""
    from .shapes import inner_bounds, make_shape, resolve

    name = cfg.transfer.get("shape", None) or "quadratic"
    shape = make_shape(name)
    shape.check()
    if transfer is None:
        transfer = make_transfer_from_config(cfg)
    if scene is None:
        resolve(shape, transfer, 2, 1.0, ())
    else:
        P = scene.particles()
        resolve(shape, transfer, scene.dim, scene.dx, P.volume)
        domain = None
        if shape.kind == "corners":         # CPDI: the corners of the particles' cubes (the stepper adds F)
            from .shapes.cpdi.reference import initial_domain
            domain = initial_domain(P.volume, scene.dim)
        inner_bounds(shape, scene, P.x, domain)
    return {} if shape.name == "quadratic" else {"shape": shape.name}


def stepper_from_config(cfg: DictConfig):
    """``(scene, stepper)`` of a composed config: its scene, transfer (with ``transfer.shape``), backend and
    precision, with the checks of :func:`build_scene` and :func:`shape_options_from_config`."""
    from .simulator import build_stepper

    scene = build_scene(cfg)
    transfer = make_transfer_from_config(cfg)
    stepper = build_stepper(scene, cfg.backend.name, transfer, cfg.precision.name,
                            **shape_options_from_config(cfg, scene, transfer))
    return scene, stepper


def describe_scene(scene) -> dict:
    """Small JSON-able facts about a built scene (for summaries and logs)."""
    P = scene.particles()
    return {
        "scene": scene.name, "dim": scene.dim, "dx": scene.dx, "grid_cells": list(scene.cells),
        "particles": int(P.count), "laws": [g.law.name for g in P.groups],
        "bodies": [b.name for b in scene.bodies], "boundaries": [b.name for b in scene.boundaries],
        "dt": float(scene.resolve_dt()),
        "cfl_number": float(scene.cfl_number(scene.resolve_dt())) if math.isfinite(scene.wave_speed()) else None,
    }
