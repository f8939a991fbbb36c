"""NCLaw teacher-forcing datasets: what ``experiment=nclaw_datasets`` writes, read back and checked.

NCLaw trains on one trajectory and, at the start of every teacher-forced segment, resets the whole
simulator state -- positions, velocities, the APIC matrix C and the (elastic) deformation gradient F --
to the ground truth (App. D.2; ``nclaw/train/teacher.py``). So a dataset must hold x, v, C and F at
*every* step (``frame_every = 1``). ``mpmlab -m experiment=nclaw_datasets`` writes one such
``trajectory.h5`` per material; for WATER, whose law keeps only J, the file's F is ``J^(1/3) I``
(:mod:`mpmlab.io.derived`, recorded in the file's ``derived_fields``).

    from mpmlab.nclaw.data import load_dataset
    ds = load_dataset("multirun/.../3/trajectory.h5")
    ds.x.shape, ds.F.shape          # (1001, 1000, 3), (1001, 1000, 3, 3)
    ds.check_matches(scene)         # scene name, particle count and dt agree with a built Scene

Every problem is a one-line ``ConfigError`` (exit code 2 on the CLI).
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..core.errors import ConfigError

#: the state NCLaw's teacher forcing resets to (App. D.2), in the order a training task uses it
REQUIRED = ("x", "v", "C", "F")
RERUN = "under teacher forcing the dataset must hold x, v, C, F at every step; rerun experiment=nclaw_datasets"


@dataclass
class Dataset:
    """One NCLaw training trajectory, every step of it.

    Attributes:
        path: the file read.
        scene: the scene's name (``nclaw_jelly``, ...); ``n``: particle count; ``dim``: 2 or 3.
        dt: time step [s]; ``steps``: steps simulated; ``frame_every``: 1 (steps between frames).
        x, v: positions [m] and velocities [m/s], ``[T+1, N, D]``; ``C``: the APIC/MLS affine matrix
            ``[T+1, N, D, D]`` [1/s]; ``F``: the deformation gradient ``[T+1, N, D, D]`` (for a J-only law
            synthesised as J^(1/d) I: ``derived``).
        time [s], step: per frame ``[T+1]``.
        mass [kg], volume [m^D]: per particle ``[N]``.
        laws: per material group ``{law, param_names, start, stop, provenance}``; ``params [N, P]``.
        derived: the fields synthesised from others, ``{field: {source, formula, laws, particles}}``.
        backend, transfer, precision: how the ground truth was simulated.
        attrs: every root attribute of the file.
    """

    path: Path
    scene: str
    n: int
    dim: int
    dt: float
    steps: int
    frame_every: int
    x: np.ndarray
    v: np.ndarray
    C: np.ndarray
    F: np.ndarray
    time: np.ndarray
    step: np.ndarray
    mass: np.ndarray
    volume: np.ndarray
    laws: list
    params: np.ndarray
    derived: dict = field(default_factory=dict)
    backend: str = ""
    transfer: str = ""
    precision: str = ""
    attrs: dict = field(default_factory=dict)

    @property
    def frames(self) -> int:
        """Number of frames, T + 1."""
        return int(self.x.shape[0])

    @property
    def law_names(self) -> list[str]:
        return [m["law"] for m in self.laws]

    def state(self, k: int) -> dict[str, np.ndarray]:
        """The ground-truth state at frame ``k``: ``{x, v, C, F}`` (what a teacher-forced segment starts from)."""
        return {name: getattr(self, name)[k] for name in REQUIRED}

    def check_matches(self, scene=None, *, name: str | None = None, n: int | None = None,
                      dt: float | None = None, steps: int | None = None) -> None:
        """Refuse (``ConfigError``) a dataset that does not belong to ``scene`` (a built ``Scene``: its
        name, particle count, and dt) or to the given values."""
        if scene is not None:
            name = scene.name if name is None else name
            n = scene.particles().count if n is None else n
            dt = float(scene.resolve_dt()) if dt is None else dt
        checks = [("scene", name, self.scene), ("particle count", n, self.n), ("dt", dt, self.dt),
                  ("steps", steps, self.steps)]
        for what, want, have in checks:
            if want is None:
                continue
            same = np.isclose(float(want), float(have), rtol=1e-9, atol=0) if what == "dt" else want == have
            if not same:
                raise ConfigError(f"NCLaw dataset '{self.path}' has {what} {have}, but the training scene has "
                                  f"{want}; train on the scene the dataset was made from, or rerun "
                                  f"experiment=nclaw_datasets scene={name or self.scene}.")


def _json_attr(attrs: dict, key: str) -> Any:
    """A root attribute stored as JSON (``derived_fields``), decoded; {} when absent or unreadable."""
    v = attrs.get(key)
    if isinstance(v, str):
        try:
            return json.loads(v)
        except ValueError:
            return {}
    return v or {}


def load_dataset(path: str | os.PathLike) -> Dataset:
    """Read an NCLaw teacher-forcing dataset (a ``trajectory.h5`` of ``experiment=nclaw_datasets``).

    Refuses, each with a one-line ``ConfigError``: a missing or unreadable file, one that is not
    complete, one without v, C or F (or with a field on only some particles), one that does not keep
    every step (``frame_every`` > 1).
    """
    from ..io.h5 import read_attrs, read_trajectory

    path = Path(path)
    if not path.exists():
        raise ConfigError(f"NCLaw dataset '{path}' does not exist; make it with `mpmlab -m experiment=nclaw_datasets` "
                          f"(trajectory.h5 in each job's run directory) or check the path.")
    attrs = read_attrs(path)                      # not HDF5 / another schema: its own one-line error
    traj = read_trajectory(path, require_complete=True)
    N = int(traj.mass.shape[0])
    have = {"x": traj.x, "v": traj.v, **traj.fields}
    missing = [k for k in REQUIRED if k not in have or np.asarray(have[k]).size == 0 and N]
    if missing:
        stored = ", ".join(k for k in ("x", "v", *traj.fields)) or "none"
        raise ConfigError(f"NCLaw dataset '{path}' has no {', '.join(missing)} (it stores {stored}); {RERUN}.")
    for k in ("C", "F"):
        idx = traj.field_particles.get(k)
        if idx is not None and len(idx) != N:
            raise ConfigError(f"NCLaw dataset '{path}' holds {k} for {len(idx)} of its {N} particles (a law that "
                              f"carries no {k}); {RERUN} with output.fields=[F,C].")
    step = np.asarray(traj.step, dtype=np.int64)
    spacing = np.diff(step)
    every = int(attrs.get("frame_every", spacing[0] if len(spacing) else 1))
    if len(spacing) and (np.any(spacing != 1) or every != 1):
        k = int(spacing.max()) if np.any(spacing != 1) else every
        raise ConfigError(f"NCLaw dataset '{path}' keeps only every {k}-th step (frame_every = {k}); {RERUN} "
                          f"(it sets frame_every=1).")
    if len(step) and step[0] != 0:
        raise ConfigError(f"NCLaw dataset '{path}' starts at step {step[0]}, not at the initial state; {RERUN}.")
    dim = int(attrs.get("dim", traj.x.shape[-1]))
    fl = lambda a: np.asarray(a, dtype=np.result_type(np.asarray(a).dtype, np.float32))
    derived = _json_attr(attrs, "derived_fields")
    return Dataset(
        path=path, scene=str(attrs.get("scene", "")), n=N, dim=dim, dt=float(attrs.get("dt", np.nan)),
        steps=int(attrs.get("steps", step[-1] if len(step) else 0)), frame_every=1,
        x=fl(traj.x), v=fl(traj.v), C=fl(have["C"]), F=fl(have["F"]), time=np.asarray(traj.time),
        step=step, mass=np.asarray(traj.mass), volume=np.asarray(traj.volume), laws=list(traj.materials),
        params=np.asarray(traj.params), derived=derived, backend=str(attrs.get("backend", "")),
        transfer=str(attrs.get("transfer", "")), precision=str(attrs.get("precision", "")), attrs=attrs,
    )
