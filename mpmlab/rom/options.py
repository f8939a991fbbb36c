"""The ROM training options written once: ``TrainSettings`` holds the fields (and defaults) that both
``mpmlab.rom.train.TrainOptions`` (the library's options, which add the schedule's arithmetic) and
the ``task=rom_train`` schema ``mpmlab.tasks.rom_train.RomTrainConfig`` (a Hydra structured config,
which adds the task's own fields) inherit. Plain dataclasses, no JAX: the task schema is registered
when the CLI starts."""
from __future__ import annotations

import dataclasses
import typing
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, List, Optional


@dataclass
class TrainSettings:
    """Eq. 24's weights, the epoch scale and the sampling of ``mpmlab.rom.train.fit`` (its module doc)."""

    #: latent size d_hat (the paper: 7 torsion, 4 Fig. 9, 6 poke and tower)
    latent: int = 6
    #: weight of Eq. 24's deformation-gradient term
    lambda_F: float = 100.0
    #: weight of Eq. 24's velocity term
    lambda_v: float = 0.01
    #: snapshots per batch (App. B: 8)
    batch: int = 8
    #: [[learning rate, epochs], ...] per Adam stage; None: App. B's 1e-3 / 1e-4 / 1e-5 / 1e-6 for
    #: 500 / 200 / 100 / 50 epochs (``mpmlab.rom.train.PAPER_SCHEDULE``)
    schedule: Optional[List[Any]] = None
    #: scales the epochs of the schedule: 0.2 of the paper's is a 170-epoch run
    schedule_scale: float = 1.0
    #: points per snapshot per batch (None: all)
    points: Optional[int] = None
    #: use every k-th snapshot of each run
    frame_stride: int = 1
    #: seed of the networks' initialisation and of the batches' order and points
    seed: int = 0

    @classmethod
    def from_config(cls, cfg: Any, **more: Any):
        """An instance with ``TrainSettings``' fields read from ``cfg`` (a composed ``cfg.task``, any
        object with those attributes, or a mapping; a field it lacks keeps its default), each converted
        to its field's type (``None`` kept where the field allows it); ``more`` sets the other fields of
        a subclass or overrides a field of ``cfg``."""
        if isinstance(cfg, Mapping):
            given = {k: cfg[k] for k in _NAMES if k in cfg}
        else:
            given = {k: getattr(cfg, k) for k in _NAMES if hasattr(cfg, k)}
        hints = typing.get_type_hints(TrainSettings)
        return cls(**{**{k: _typed(v, hints[k]) for k, v in given.items()}, **more})


_NAMES = tuple(f.name for f in dataclasses.fields(TrainSettings))


def _typed(value: Any, hint: Any) -> Any:
    args = typing.get_args(hint)                       # Optional[int] -> (int, NoneType)
    if value is None and type(None) in args:
        return None
    kind = next((a for a in args if a is not type(None)), hint)
    if typing.get_origin(kind) is list:                # the schedule: TrainOptions checks it, makes it pairs
        return value
    return kind(value)
