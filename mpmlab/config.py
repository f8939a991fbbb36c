"""Typed configuration: the root Hydra schema of ``mpmlab``, its registration, and composing it.

The YAML config tree (``mpmlab/conf``, also reachable as the top-level ``conf/``) is validated against
the dataclasses below, which are registered in Hydra's ``ConfigStore``: a misspelled key or a value of
the wrong type fails while Hydra composes the config, before anything runs. A task's options are a
``TaskConfig`` subclass that lives in the task's own module (``mpmlab.tasks.<name>``: schema, ``run``
and registration with :func:`register_task_schema`); :func:`register_configs` imports the built-in
task modules so that their schemas are stored before anything is composed.

Physics is chosen by registered name (``material.law``, ``transfer.name``, ``backend.name``,
``scene.boundaries.<b>.kind``); parameters are checked by the classes that own them (a law's
``ParamSpec`` ranges, a boundary's ``validate``, the scene's CFL bound) when
:func:`mpmlab.build.build_scene` turns the config into a ``Scene`` (:mod:`mpmlab.build` is the one
module that turns config into objects; its names are re-exported here). ``_target_`` is left for
generic objects (optimisers, networks) that later tasks instantiate.

Layout of the composed config::

    backend:   {name, check_every, device, devices}   # config group backend/ (jax, warp)
    transfer:  {name, flip_ratio, pic_time, shape}     # transfer/ (pic, flip, apic, mls, tpic); shape:
                                                       # quadratic (default), cubic, ugimp
    precision: {name}                                  # precision/ (fp32, fp64)
    material:  {law, params, density, label}           # material/: the default material of the scene
    scene:     {name, dim, dx, domain, gravity, dt, bodies{...}, boundaries{...}, resolution, ...}
    task:      {name, ...}                             # task/ (simulate, replay, inverse, bench, plugins')
    output:    {trajectory, recording, record_every, color_by, fields, plots, overwrite}
    steps, frame_every, seed, input, debug, progress   # top-level keys

Python use (no Hydra app needed)::

    from mpmlab.config import compose, build_scene
    cfg = compose(["scene=dam_break_2d", "scene.resolution=tiny"])
    scene = build_scene(cfg)
"""
from __future__ import annotations

import dataclasses
import difflib
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional, Union

from omegaconf import II, MISSING, DictConfig, ListConfig, OmegaConf

from .core import registry
from .core.errors import ConfigError

#: The packaged config tree (the repository's top-level ``conf/`` links here).
CONF_DIR = Path(__file__).resolve().parent / "conf"
#: Name of the primary config in :data:`CONF_DIR`.
PRIMARY = "config"
#: ConfigStore name of the root schema (the primary config's first default).
SCHEMA_NAME = "mpmlab_schema"


# ---------------------------------------------------------------------------------------------
# schema
# ---------------------------------------------------------------------------------------------
@dataclass
class BackendConfig:
    """A registered backend (``mpmlab.backends`` entry points: ``jax``, ``warp``)."""

    name: str = "jax"
    #: steps between divergence guards (None: at every kept frame)
    check_every: Optional[int] = None
    #: Warp device (``cpu``, ``cuda:0``); None = the backend's default
    device: Optional[str] = None
    #: JAX: shard one simulation's particles over this many devices (None or 1: one device)
    devices: Optional[int] = None


@dataclass
class TransferConfig:
    """A registered transfer scheme (``pic``, ``flip``, ``apic``, ``mls``, ``tpic``), its options and its
    shape function (``transfer: {name: apic, shape: cubic}``)."""

    name: str = "mls"
    #: FLIP/PIC blend of ``flip`` (1 = pure FLIP); None = the scheme's default
    flip_ratio: Optional[float] = None
    #: ``flip``'s blend as a time constant [s] (flip_ratio = exp(-dt / pic_time) per step); None = per-step flip_ratio
    pic_time: Optional[float] = None
    #: the grid shape function (``mpmlab.shapes``: ``quadratic`` B-spline, ``cubic`` B-spline, ``ugimp``);
    #: a stepper option, not one of the scheme's (``mpmlab.build.shape_options_from_config``)
    shape: str = "quadratic"


@dataclass
class PrecisionConfig:
    name: str = "fp32"


@dataclass
class MaterialConfig:
    """A registered constitutive law with its parameters (checked by the law's ``ParamSpec``)."""

    law: str = MISSING
    params: Dict[str, float] = field(default_factory=dict)
    #: rest density [kg/m^3]
    density: float = 1000.0
    #: a human name for plots and recordings (``jelly``, ``sand``)
    label: str = ""
    #: the law's configuration (its instance fields, e.g. a network's width or a weights file);
    #: bodies with the same law and options share one law instance and its weights
    options: Dict[str, Any] = field(default_factory=dict)


@dataclass
class ShapeConfig:
    """A body shape: ``box`` (lo, hi), ``sphere`` (center, radius; a disc in 2D), ``cylinder`` (base,
    radius, height, axis) or ``mesh`` (path, scale, translate; a path relative to ``mpmlab/assets``
    or any OBJ/STL/PLY file)."""

    kind: str = MISSING
    lo: Optional[List[float]] = None
    hi: Optional[List[float]] = None
    center: Optional[List[float]] = None
    radius: Optional[float] = None
    base: Optional[List[float]] = None
    height: Optional[float] = None
    axis: Optional[int] = None
    path: Optional[str] = None
    scale: Optional[float] = None
    translate: Optional[List[float]] = None


@dataclass
class BodyConfig:
    """One body of the scene; ``material: null`` takes the top-level ``material``."""

    shape: ShapeConfig = MISSING
    material: Optional[MaterialConfig] = None
    #: initial velocity [m/s]: D numbers, or D entries that may be expression strings in the position
    #: x[k] and pi (``["0.1 * sin(pi * x[0])", 0]``; mpmlab.core.initial_fields)
    velocity: Optional[List[Any]] = None
    #: initial angular velocity about the body's centroid [rad/s]: a number in 2D, a 3-vector in 3D
    angular_velocity: Optional[Any] = None
    #: initial deformation gradient, D rows of D numbers or expressions in x[k] (default: identity); sets
    #: the law's F, or J = det F for a law whose state has J but no F
    F: Optional[List[Any]] = None
    #: initial affine velocity C [1/s], D rows of D numbers or expressions (apic, mls, tpic only)
    C: Optional[List[Any]] = None
    particles_per_cell: int = 1
    #: ``regular``, ``jittered``, ``random`` (with ``count``) or ``lattice`` (with ``lattice``)
    sampling: str = "regular"
    count: Optional[int] = None
    #: ``sampling: lattice`` (box bodies): points per axis, ``np.linspace(lo, hi, n)`` with the faces
    #: included, volume = box volume / point count (NCLaw's training cube: [10, 10, 10])
    lattice: Optional[List[int]] = None
    particle_volume: Optional[float] = None
    #: massless points (mass and volume 0): they follow the grid's velocity and put nothing into it (the
    #: tracer baseline of the deformation-map ROM paper, Tab. 4)
    tracer: bool = False
    #: set false to leave the body out (``scene.bodies.<name>.enabled=false``)
    enabled: bool = True


@dataclass
class BoundaryConfig:
    """A registered boundary (``walls``, ``friction_walls``, ``plane``, ``box_obstacle``,
    ``particle_velocity``, ``particle_load``, or a plugin's) and the options it takes.

    Only the options a boundary declares may be set (the others stay null); ``condition`` is the
    ``plane`` boundary's sticky / slip / separate; ``extra`` passes options of plugin boundaries that
    this schema does not name.
    """

    kind: str = MISSING
    enabled: bool = True
    # walls
    default: Optional[str] = None
    faces: Optional[Dict[str, str]] = None
    thickness: Optional[int] = None
    # friction_walls
    face: Optional[str] = None
    mu: Optional[List[float]] = None
    along: Optional[str] = None
    per_node: Optional[bool] = None
    # plane
    point: Optional[List[float]] = None
    normal: Optional[List[float]] = None
    condition: Optional[str] = None
    friction: Optional[float] = None
    # box_obstacle
    lo: Optional[List[float]] = None
    hi: Optional[List[float]] = None
    # particle_velocity / particle_load
    region: Optional[ShapeConfig] = None
    velocity: Optional[List[float]] = None
    force: Optional[List[float]] = None
    #: particle_velocity's rigid motion v0 + omega x (x - c(t)): omega [rad/s] (a number in 2D, a 3-vector
    #: in 3D) and the centre c0 at t_start (default: the region's centroid)
    angular_velocity: Optional[Any] = None
    center: Optional[List[float]] = None
    t_start: Optional[float] = None
    t_end: Optional[float] = None
    # body_force: a registered field (uniform, mms_axis_aligned, expression, or a plugin's) and its
    # options, e.g. field: expression, values: {b: ['a * t', '0'], constants: {a: 2.0}}
    field: Optional[str] = None
    values: Optional[Dict[str, Any]] = None
    # (dataclasses.field: the option ``field`` above shadows the name in this class body)
    extra: Dict[str, Any] = dataclasses.field(default_factory=dict)


@dataclass
class DomainConfig:
    """The region inside the walls [m]; the grid extends ``pad_cells`` cells beyond it on every side
    (a wall of ``thickness`` t acts on the nodes with index < t, so ``pad_cells = t - 1`` puts the
    innermost constrained node on the face ``lo`` / ``hi``)."""

    lo: List[float] = MISSING
    hi: List[float] = MISSING
    pad_cells: int = 0


@dataclass
class SceneConfig:
    name: str = MISSING
    description: str = ""
    #: where the scene comes from (paper, section)
    source: str = ""
    dim: int = 3
    #: grid spacing [m]
    dx: float = MISSING
    domain: DomainConfig = field(default_factory=DomainConfig)
    gravity: Optional[List[float]] = None
    #: time step [s], or ``auto`` (CFL number ``cfl``); an integer (``scene.dt=0`` on the command line)
    #: is a number of seconds too
    dt: Union[float, int, str] = "auto"
    cfl: float = 0.3
    #: largest CFL number accepted for a fixed dt
    cfl_limit: float = 0.5
    #: with dt auto: recompute dt from the current max particle speed every this many steps (0: once)
    dt_every: int = 10
    #: default rollout length and frame spacing of the scene (top-level ``steps`` / ``frame_every``)
    steps: int = 1000
    frame_every: int = 10
    bodies: Dict[str, BodyConfig] = field(default_factory=dict)
    boundaries: Dict[str, BoundaryConfig] = field(default_factory=dict)
    #: the chosen entry of ``resolutions`` (values are picked by interpolation in the scene YAML)
    resolution: str = "default"
    resolutions: Dict[str, Dict[str, Any]] = field(default_factory=dict)
    #: scene-specific knobs used by the scene's own interpolations (e.g. ``aspect_ratio``)
    vars: Dict[str, Any] = field(default_factory=dict)
    #: a registered scene builder (``mpmlab.scenes`` entry point or ``module:function``) instead of bodies
    builder: Optional[str] = None
    builder_args: Dict[str, Any] = field(default_factory=dict)


@dataclass
class TaskConfig:
    """Base of every task's options; ``name`` selects the task function (``mpmlab.tasks``)."""

    name: str = MISSING


@dataclass
class OutputConfig:
    """What a run writes into its Hydra run directory."""

    trajectory: bool = True
    recording: bool = True
    #: keep every k-th frame in the recording (thinning)
    record_every: int = 1
    #: particle colours: ``material`` or a scalar (``speed``, ``J``, ``eps_p``, ``stress``)
    color_by: str = "material"
    #: per-particle fields stored in the trajectory besides x and v (kept where the laws carry them)
    fields: List[str] = field(default_factory=lambda: ["all"])
    #: energy-over-time PNG
    plots: bool = True
    #: replace outputs already in the run directory (otherwise that is an error)
    overwrite: bool = False


@dataclass
class MpmlabConfig:
    backend: BackendConfig = field(default_factory=BackendConfig)
    transfer: TransferConfig = field(default_factory=TransferConfig)
    precision: PrecisionConfig = field(default_factory=PrecisionConfig)
    material: MaterialConfig = field(default_factory=MaterialConfig)
    scene: SceneConfig = field(default_factory=SceneConfig)
    task: TaskConfig = field(default_factory=TaskConfig)
    output: OutputConfig = field(default_factory=OutputConfig)
    #: time steps to run (default: the scene's)
    steps: int = II("scene.steps")
    #: steps between kept frames (default: the scene's)
    frame_every: int = II("scene.frame_every")
    seed: int = 0
    #: input file of tasks that read one (``task=replay input=run/trajectory.h5``)
    input: Optional[str] = None
    #: print tracebacks (also: environment variable MPMLAB_DEBUG=1)
    debug: bool = False
    #: progress bar: null = only when stderr is a terminal
    progress: Optional[bool] = None


_REGISTERED = False


def _product(*args: Any) -> float:
    out = 1.0
    for a in args:
        out *= float(a)
    return out


def _int_product(*args: Any) -> int:
    out = 1
    for a in args:
        if isinstance(a, bool) or float(a) != int(float(a)):
            raise ConfigError(f"mpmlab.imul: {a!r} is not an integer; it multiplies integers (a step count).")
        out *= int(float(a))
    return out


def register_resolvers() -> None:
    """``${mpmlab.mul:a,b,...}`` and ``${mpmlab.add:a,b,...}`` for scene geometry derived from
    ``scene.vars`` (e.g. a column height = L0 x aspect ratio); ``${mpmlab.sin:a}`` and
    ``${mpmlab.cos:a}`` (radians) for directions given by angles (the ROM poke's f(theta, phi));
    ``${mpmlab.imul:a,b,...}``, the product of integers, for a step count (snapshots x substeps)."""
    import math

    OmegaConf.register_new_resolver("mpmlab.mul", _product, replace=True)
    OmegaConf.register_new_resolver("mpmlab.add", lambda *a: float(sum(float(x) for x in a)), replace=True)
    OmegaConf.register_new_resolver("mpmlab.imul", _int_product, replace=True)
    OmegaConf.register_new_resolver("mpmlab.sin", lambda a: math.sin(float(a)), replace=True)
    OmegaConf.register_new_resolver("mpmlab.cos", lambda a: math.cos(float(a)), replace=True)


def register_configs() -> None:
    """Store the schemas in Hydra's ConfigStore (idempotent; done on import of this module)."""
    global _REGISTERED
    if _REGISTERED:
        return
    from hydra.core.config_store import ConfigStore

    register_resolvers()
    cs = ConfigStore.instance()
    cs.store(name=SCHEMA_NAME, node=MpmlabConfig)
    # per-task schemas, extended by conf/task/<name>.yaml (defaults: [/mpmlab_task_<name>@_here_, _self_]):
    # each built-in task module registers its own when it is imported
    from .tasks import load_builtin_schemas

    load_builtin_schemas()
    _REGISTERED = True


def register_task_schema(name: str, node: type) -> None:
    """Register a task's option dataclass (a ``TaskConfig`` subclass) as ``mpmlab_task_<name>``; the
    task's YAML ``conf/task/<name>.yaml`` extends it: ``defaults: [/mpmlab_task_<name>@_here_, _self_]``."""
    from hydra.core.config_store import ConfigStore

    ConfigStore.instance().store(name=f"mpmlab_task_{name}", node=node)


# ---------------------------------------------------------------------------------------------
# composing without the CLI (tests, notebooks)
# ---------------------------------------------------------------------------------------------
def compose(overrides: list[str] | tuple[str, ...] = (), config_name: str = PRIMARY,
            return_hydra_config: bool = False) -> DictConfig:
    """Compose the packaged config with Hydra overrides, as ``mpmlab <overrides>`` would.

    Plugin config groups (``mpmlab.configs`` entry points) are on the search path as on the CLI.
    """
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    register_search_path_plugin()
    gh = GlobalHydra.instance()
    was = gh.is_initialized()
    if was:  # a test or notebook already holds a Hydra context: use ours, then put nothing back
        gh.clear()
    try:
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            return hydra_compose(config_name, overrides=list(overrides), return_hydra_config=return_hydra_config)
    finally:
        GlobalHydra.instance().clear()


def recorded_config(text: str) -> DictConfig:
    """A run's recorded config (the resolved YAML a trajectory.h5 keeps) completed by today's schema: a key
    added since the run was recorded takes its default, so old runs rebuild (e.g. their scene). The task
    section is kept as recorded (each task has its own schema)."""
    rec = OmegaConf.create(text)
    task = rec.pop("task", None) if isinstance(rec, DictConfig) else None
    merged = OmegaConf.create(OmegaConf.to_container(OmegaConf.merge(OmegaConf.structured(MpmlabConfig), rec)))
    if task is not None:
        merged.task = task
    return merged


def register_search_path_plugin() -> None:
    """Register mpmlab's Hydra search-path plugin explicitly.

    Hydra finds ``hydra_plugins.mpmlab_searchpath`` by scanning the ``hydra_plugins`` namespace; some
    editable installs hide namespace portions from that scan, so the CLI registers it as well
    (``Plugins.register`` ignores a class it already knows).
    """
    try:
        from hydra.core.plugins import Plugins
        from hydra_plugins.mpmlab_searchpath import MpmlabSearchPathPlugin
    except ImportError:  # pragma: no cover - a broken install; Hydra's own scan may still find it
        return
    Plugins.instance().register(MpmlabSearchPathPlugin)


# ---------------------------------------------------------------------------------------------
# keys that nothing reads
# ---------------------------------------------------------------------------------------------
# Hydra's ``+key=value`` (and ``++``) adds a key even where the schema is closed, so a typo such as
# ``+scene.bodies.cube.velocty=[1,2,3]`` composes; ``check_known_keys`` refuses such keys before a run.
_VARS_REF = re.compile(r"scene\.vars\.([A-Za-z_][\w-]*)")
_RESOLUTION_REF = re.compile(r"scene\.resolutions\.(?:\$\{[^}]*\}|[\w-]+)\.([A-Za-z_][\w-]*)")


def _schema_fields(node: Any) -> Optional[list[str]]:
    """Field names of a structured (dataclass-typed) node, None for an open dict or a non-dict."""
    if not isinstance(node, DictConfig) or node._is_none() or node._is_missing() or node._is_interpolation():
        return None
    t = OmegaConf.get_type(node)
    return [f.name for f in dataclasses.fields(t)] if t is not None and dataclasses.is_dataclass(t) else None


def _children(node: DictConfig):
    """(key, child node) without resolving interpolations."""
    for key in node.keys():
        yield str(key), node._get_node(key)


def _boundary_options(node: DictConfig) -> Optional[list[str]]:
    """The options the boundary kind of a ``BoundaryConfig`` node declares (dataclass fields), or None
    when the kind is unknown (``build_scene`` reports it) or its class declares none."""
    kind = node._get_node("kind")
    kind = None if kind is None or kind._is_missing() or kind._is_interpolation() else kind._value()
    if not isinstance(kind, str) or kind not in registry.boundaries:
        return None
    try:
        cls = registry.boundaries.get(kind)
    except Exception:  # noqa: BLE001 - a broken plugin is reported when the scene is built
        return None
    return [f.name for f in dataclasses.fields(cls)] if dataclasses.is_dataclass(cls) else None


def _interpolations(node: Any, out: list[str]) -> list[str]:
    """Every interpolation string in the config (unresolved), for the keys only interpolations read."""
    if isinstance(node, (DictConfig, ListConfig)) and node._is_interpolation():
        out.append(str(node._value()))
    elif isinstance(node, DictConfig) and not node._is_none() and not node._is_missing():
        for _, child in _children(node):
            _interpolations(child, out)
    elif isinstance(node, ListConfig) and not node._is_none() and not node._is_missing():
        for i in range(len(node)):
            _interpolations(node._get_node(i), out)
    elif node is not None and not isinstance(node, (DictConfig, ListConfig)):
        v = node._value()
        if isinstance(v, str) and "${" in v:
            out.append(v)
    return out


def unknown_keys(cfg: DictConfig) -> list[tuple[str, list[str]]]:
    """Keys of a composed config that no schema and no code reads, each with the keys it could have
    meant (full keys of its siblings): ``[(full_key, candidates), ...]``.

    Checked: every structured node (a key that is not a field of its dataclass); a boundary's options
    (the schema's fields plus those its kind declares, also under ``extra``); ``scene.vars`` and
    ``scene.resolutions.<name>`` entries added with ``+`` (only interpolations read them, so one that
    no interpolation names is read by nothing; entries written in a scene's YAML may be there for
    the tasks that use the scene and are left alone). Open dicts that their readers check themselves
    (a law's ``params``, observation options, ``_target_`` objects, ``builder_args``) are left to them.
    """
    found: list[tuple[str, list[str]]] = []

    def walk(node: DictConfig, path: str) -> None:
        fields = _schema_fields(node)
        prefix = f"{path}." if path else ""
        if fields is not None:
            allowed = list(fields)
            options = _boundary_options(node) if OmegaConf.get_type(node) is BoundaryConfig else None
            if options is not None:
                allowed += [o for o in options if o not in allowed]
            for key, child in _children(node):
                if not path and key == "hydra":  # compose(return_hydra_config=True): Hydra's own node
                    continue
                if key not in allowed:
                    near = fields if options is None else ["kind", "enabled"] + options
                    found.append((prefix + key, [prefix + k for k in near]))
                    continue
                if options is not None and key == "extra" and isinstance(child, DictConfig) \
                        and not child._is_none() and not child._is_interpolation():
                    for k, _ in _children(child):
                        if k not in options:
                            found.append((f"{prefix}extra.{k}", [f"{prefix}extra.{o}" for o in options]))
                    continue
                if isinstance(child, DictConfig):
                    walk(child, prefix + key)
        elif isinstance(node, DictConfig) and not node._is_none() and not node._is_missing() \
                and not node._is_interpolation():
            for key, child in _children(node):  # an open dict: only its structured values are checked
                if isinstance(child, DictConfig):
                    walk(child, prefix + key)

    walk(cfg, "")
    scene = cfg._get_node("scene") if isinstance(cfg, DictConfig) and "scene" in cfg else None
    if _schema_fields(scene) is not None:
        refs = " ".join(_interpolations(cfg, []))
        read_vars = set(_VARS_REF.findall(refs))
        vars_node = scene._get_node("vars")
        if isinstance(vars_node, DictConfig) and not vars_node._is_none() and not vars_node._is_interpolation():
            for key, _ in _children(vars_node):
                if key not in read_vars and _added_with_plus(f"scene.vars.{key}"):
                    found.append((f"scene.vars.{key}", [f"scene.vars.{k}" for k in sorted(read_vars)]))
        read_res = set(_RESOLUTION_REF.findall(refs))
        res_node = scene._get_node("resolutions")
        if isinstance(res_node, DictConfig) and not res_node._is_none() and not res_node._is_interpolation():
            for name, entry in _children(res_node):
                if isinstance(entry, DictConfig) and not entry._is_none() and not entry._is_interpolation():
                    for key, _ in _children(entry):
                        if key not in read_res and _added_with_plus(f"scene.resolutions.{name}.{key}"):
                            found.append((f"scene.resolutions.{name}.{key}",
                                          [f"scene.resolutions.{name}.{k}" for k in sorted(read_res)]))
    return found


def _all_keys(cfg: DictConfig) -> list[str]:
    """Full keys of every schema field in the config (the candidates of a did-you-mean)."""
    out: list[str] = []

    def walk(node: Any, path: str) -> None:
        if not isinstance(node, DictConfig) or node._is_none() or node._is_missing() or node._is_interpolation():
            return
        fields = _schema_fields(node)
        for key, child in _children(node):
            full = f"{path}.{key}" if path else key
            if fields is None or key in fields:
                out.append(full)
                walk(child, full)

    walk(cfg, "")
    return out


def _closest(key: str, siblings: list[str], everything: list[str]) -> Optional[str]:
    """The closest real key: a sibling with a similar name, else any key whose last part is similar
    (``overwrite`` -> ``output.overwrite``)."""
    name = key.rsplit(".", 1)[-1]
    near = difflib.get_close_matches(name, [k.rsplit(".", 1)[-1] for k in siblings], n=1, cutoff=0.6)
    if near:
        return next(k for k in siblings if k.rsplit(".", 1)[-1] == near[0])
    lasts = {}
    for k in everything:
        if k != key:
            lasts.setdefault(k.rsplit(".", 1)[-1], []).append(k)
    near = difflib.get_close_matches(name, list(lasts), n=1, cutoff=0.75)
    if not near:
        return None
    return max(lasts[near[0]], key=lambda k: difflib.SequenceMatcher(None, key, k).ratio())


def _added_with_plus(key: str) -> bool:
    """Whether a ``+KEY=``/``++KEY=`` override of this run added ``key`` (or a node above it)."""
    try:
        from hydra.core.hydra_config import HydraConfig

        if not HydraConfig.initialized():
            return False
        overrides = list(HydraConfig.get().overrides.task)
    except Exception:  # noqa: BLE001 - no Hydra run context (Python use)
        return False
    for o in overrides:
        if o.startswith("+"):
            k = o.lstrip("+").split("=", 1)[0].strip()
            if key == k or key.startswith(k + "."):
                return True
    return False


def unknown_key_message(key: str, candidates: list[str], everything: list[str] = (),
                        added_with_plus: bool = False) -> str:
    """One sentence for an unknown key: the key, how it got there, the closest real key, what to do."""
    how = "added with +" if added_with_plus else "not a key of the schema"
    best = _closest(key, list(candidates), list(everything))
    hint = f"; did you mean '{best}'? Nothing" if best else "; nothing"
    return (f"unknown key '{key}' ({how}){hint} reads it: fix the name or remove it "
            f"(`mpmlab --cfg job` lists the keys).")


def check_known_keys(cfg: DictConfig) -> None:
    """Refuse a key of the composed config that no schema reads (e.g. added with ``+``), naming the
    full key and the closest real one; ``ConfigError`` (exit code 2 on the CLI)."""
    found = unknown_keys(cfg)
    if not found:
        return
    key, candidates = found[0]
    msg = unknown_key_message(key, candidates, _all_keys(cfg), _added_with_plus(key))
    if len(found) > 1:
        msg = msg[:-1] + f"; also unknown: {', '.join(k for k, _ in found[1:])}."
    raise ConfigError(msg)


def check_run_options(cfg: DictConfig) -> None:
    """Top-level options that no class downstream checks with a clear message, and keys that no
    schema reads (:func:`check_known_keys`)."""
    check_known_keys(cfg)
    if cfg.steps < 0:
        raise ConfigError(f"steps = {cfg.steps} must be >= 0.")
    if cfg.frame_every < 1:
        raise ConfigError(f"frame_every = {cfg.frame_every} must be >= 1.")
    if cfg.output.record_every < 1:
        raise ConfigError(f"output.record_every = {cfg.output.record_every} must be >= 1.")
    if cfg.precision.name not in ("fp32", "fp64"):
        raise ConfigError(f"precision '{cfg.precision.name}' unknown; use precision=fp32 or precision=fp64.")
    from .build import shape_options_from_config

    shape_options_from_config(cfg)    # transfer.shape: a registered shape the kernels carry, declared by the transfer
    if cfg.seed < 0:  # numpy's generators (particle sampling, observation noise) take seeds >= 0
        raise ConfigError(f"seed = {cfg.seed} must be >= 0; use seed=0 or another non-negative integer.")
    if cfg.backend.name == "warp" and cfg.backend.device is not None:
        from .backends.warp import check_device

        check_device(str(cfg.backend.device), "backend.device")
    if cfg.backend.get("devices") not in (None, 1):
        from .simulator import check_devices_option

        check_devices_option(cfg.backend.name, cfg.backend.devices)
        if cfg.task.name != "simulate":
            raise ConfigError(f"backend.devices = {cfg.backend.devices} applies to task=simulate (and to the Python "
                              f"API: build_stepper(..., devices=N)); task={cfg.task.name} runs on one device, so "
                              f"leave backend.devices unset.")


# ---------------------------------------------------------------------------------------------
# config -> objects lives in mpmlab.build; the built-in task schemas in their task modules
# ---------------------------------------------------------------------------------------------
from .build import (build_scene, check_resolution, describe_scene, make_boundary_from_config,  # noqa: E402,F401
                    make_transfer_from_config, material_of, shape_options_from_config, stepper_from_config)

#: names that moved out of this module: ``mpmlab.config.<name>`` still finds them
_MOVED = {"SimulateTaskConfig": "tasks.simulate", "ReplayTaskConfig": "tasks.replay", "BenchTaskConfig": "tasks.bench",
          "FitParameterConfig": "tasks.inverse", "InverseTaskConfig": "tasks.inverse"}


def __getattr__(name: str):
    if name in _MOVED:
        import importlib

        return getattr(importlib.import_module(f".{_MOVED[name]}", __package__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


register_configs()
