"""Tasks: what one ``mpmlab`` run does with its composed config (``task=<name>``).

A task is a function ``run(cfg, ctx) -> dict``: it reads the composed config (``DictConfig``), writes
its outputs into ``ctx.output_dir`` (the Hydra run directory) and returns the summary that the CLI
writes as ``summary.json``. Built-in tasks: ``simulate`` (:mod:`mpmlab.tasks.simulate`) and ``replay``
(:mod:`mpmlab.tasks.replay`). Later issues add theirs here (``inverse``, ``rom``, ``bench``) with
:func:`register_task` and a ``conf/task/<name>.yaml``; other packages add tasks through the
``mpmlab.tasks`` entry-point group (and their YAML through ``mpmlab.configs``).

Each task declares its options as a ``TaskConfig`` subclass registered with
:func:`mpmlab.config.register_task_schema`, so that a misspelled task option fails at compose time.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from importlib.metadata import entry_points
from pathlib import Path
from typing import Any, Callable

from ..core.errors import UnknownPluginError
from ..core.registry import load_object

ENTRY_POINT_GROUP = "mpmlab.tasks"

_TASKS: dict[str, Any] = {
    "simulate": "mpmlab.tasks.simulate:run",
    "replay": "mpmlab.tasks.replay:run",
    "inverse": "mpmlab.tasks.inverse:run",
    "bench": "mpmlab.tasks.bench:run",
}
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


__all__ = ["RunContext", "get_task", "register_task", "run_task", "task_names", "ENTRY_POINT_GROUP"]
