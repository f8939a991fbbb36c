"""Tasks: what one ``mpmlab`` run does with its composed config (``task=<name>``).

A task is a function ``run(cfg, ctx) -> dict``: it reads the composed config (``DictConfig``), writes
its outputs into ``ctx.output_dir`` (the Hydra run directory) and returns the summary that the CLI
writes as ``summary.json``. Built-in tasks: ``simulate``, ``replay``, ``inverse``, ``bench``, ``nclaw_train``, ``nclaw_eval``, ``rom_train`` and ``rom_eval`` (:data:`BUILTIN_TASKS`), each
one module ``mpmlab.tasks.<name>`` with a ``conf/task/<name>.yaml``; other packages add tasks with
:func:`register_task` or through the ``mpmlab.tasks`` entry-point group (and their YAML through
``mpmlab.configs``).

Each task declares its options as a ``TaskConfig`` subclass registered with
:func:`mpmlab.config.register_task_schema` (the built-ins: next to their ``run``), so that a
misspelled task option fails at compose time.
"""
from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from importlib.metadata import entry_points
from pathlib import Path
from typing import Any, Callable

from ..core.errors import UnknownPluginError
from ..core.registry import load_object

ENTRY_POINT_GROUP = "mpmlab.tasks"

#: the built-in tasks: each is one module ``mpmlab.tasks.<name>`` holding its option schema, its
#: ``run`` and the schema's registration
BUILTIN_TASKS = ("simulate", "replay", "inverse", "bench", "nclaw_train", "nclaw_eval", "rom_train", "rom_eval")
_TASKS: dict[str, Any] = {name: f"mpmlab.tasks.{name}:run" for name in BUILTIN_TASKS}
_entry_points_loaded = False


@dataclass
class RunContext:
    """What a task knows about its run besides the config.

    Attributes:
        output_dir: the Hydra run directory (exists; the task writes only below it).
        overwrite: replace outputs already present (``output.overwrite``); otherwise refuse them.
        progress: progress bar (None: only when stderr is a terminal).
        multirun: part of a sweep (``mpmlab -m ...``).
        job: Hydra job facts (``name``, ``num``, ``override_dirname``, overrides).
    """

    output_dir: Path
    overwrite: bool = False
    progress: bool | None = None
    multirun: bool = False
    job: dict[str, Any] = field(default_factory=dict)


def load_builtin_schemas() -> None:
    """Import the built-in task modules: each registers its option schema (``mpmlab_task_<name>``)
    with :func:`mpmlab.config.register_task_schema` when imported (:func:`mpmlab.config.register_configs`
    calls this before anything is composed)."""
    for name in BUILTIN_TASKS:
        importlib.import_module(f"{__name__}.{name}")


def register_task(name: str, target: Callable | str) -> None:
    """Register a task function (or ``"module:function"``) under ``name``."""
    _TASKS[name] = target


def _load_entry_points() -> None:
    global _entry_points_loaded
    if _entry_points_loaded:
        return
    _entry_points_loaded = True
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        _TASKS.setdefault(ep.name, ep.value)  # built-ins win


def task_names() -> list[str]:
    _load_entry_points()
    return sorted(_TASKS)


def get_task(name: str) -> Callable:
    """The task function registered as ``name``; an unknown name lists the known tasks."""
    _load_entry_points()
    if name not in _TASKS:
        raise UnknownPluginError("task", name, list(_TASKS))
    target = _TASKS[name]
    if isinstance(target, str):
        target = load_object(target)
        _TASKS[name] = target
    return target


def run_task(cfg, ctx: RunContext) -> dict:
    """Run ``cfg.task.name`` with ``cfg`` and ``ctx``; returns its summary."""
    return get_task(cfg.task.name)(cfg, ctx)


__all__ = ["BUILTIN_TASKS", "RunContext", "get_task", "load_builtin_schemas", "register_task", "run_task", "task_names",
           "ENTRY_POINT_GROUP"]
