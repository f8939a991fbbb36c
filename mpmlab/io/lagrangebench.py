"""LagrangeBench export: ``mpmlab.trajectory`` files (or ``Trajectory`` objects) as a LagrangeBench
dataset (tumaer/lagrangebench): ``{split}.h5`` with one group per trajectory and ``metadata.json``.
Both files are published atomically (:func:`mpmlab.io.files.write_atomically`).
"""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from ..core.errors import ConfigError
from ..core.state import Trajectory
from .files import write_atomically
from .h5 import _frame_spacing, _json_default, read_trajectory


def _as_trajectories(src) -> list[Trajectory]:
    if isinstance(src, (Trajectory, str, os.PathLike)):
        src = [src]
    out = []
    for s in src:
        out.append(s if isinstance(s, Trajectory) else read_trajectory(s))
    if not out:
        raise ConfigError("export_lagrangebench needs at least one trajectory.")
    return out


def _stats(arrays: list[np.ndarray], dim: int) -> tuple[list, list]:
    """Per-dimension mean and std over all frames and particles (std < 1e-7 -> 1, as LagrangeBench)."""
    arrays = [a.reshape(-1, dim) for a in arrays if a.size]
    if not arrays:
        return [0.0] * dim, [1.0] * dim
    a = np.concatenate(arrays).astype(np.float64)
    mean, std = a.mean(0), a.std(0)
    std = np.where(std < 1e-7, 1.0, std)
    return mean.tolist(), std.tolist()


def export_lagrangebench(traj_or_path: Trajectory | str | os.PathLike | Iterable, out_dir: str | os.PathLike,
                         split: str = "train", case: str | None = None, overwrite: bool = False) -> Path:
    """Export trajectories in the LagrangeBench dataset layout (tumaer/lagrangebench).

    Writes ``out_dir/{split}.h5`` with one group per trajectory (``"00000"``, ``"00001"``, ...) holding
    ``position`` [T, N, D] float32 and ``particle_type`` [N] (= material_id), and ``out_dir/metadata.json``
    with ``case, solver, dim, dx (grid spacing), dt (solver step), write_every (steps per frame),
    sequence_length (T - 1), sequence_length_<split>, num_trajs_<split>, num_particles_max, bounds,
    periodic_boundary_conditions, default_connectivity_radius (1.45 x particle spacing),
    vel_mean/vel_std, acc_mean/acc_std``. As in LagrangeBench, velocities and accelerations are
    per-frame position differences (not divided by dt), and a std below 1e-7 is stored as 1.
    An existing metadata.json (another split) is updated; the statistics come from the ``train`` split
    when it is exported, else from this split if none are stored yet.

    Args:
        traj_or_path: a ``Trajectory``, an ``mpmlab.trajectory`` file, or a list of them.
        out_dir: dataset folder (created).
        split: ``train``, ``valid`` or ``test`` (the file name).
        case: the case name (default: the scene name, upper case).
        overwrite: replace an existing ``{split}.h5``.
    """
    import h5py

    trajs = _as_trajectories(traj_or_path)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    first = trajs[0]
    meta = first.meta or {}
    dim = int(meta.get("dim", first.x.shape[-1]))
    dx = float(meta.get("dx", np.nan))
    for t in trajs:
        if t.x.shape[-1] != dim:
            raise ConfigError(f"export_lagrangebench: trajectories mix dimensions ({dim} and {t.x.shape[-1]}); "
                              f"export them to separate datasets.")

    def write(tmp: Path) -> None:
        with h5py.File(tmp, "w") as f:
            for i, t in enumerate(trajs):
                g = f.create_group(f"{i:05d}")
                g.create_dataset("position", data=np.asarray(t.x, dtype=np.float32), compression="gzip")
                g.create_dataset("particle_type", data=np.asarray(t.material_id, dtype=np.int64))

    h5_path = write_atomically(out_dir / f"{split}.h5", write, overwrite)

    md_path = out_dir / "metadata.json"
    md: dict[str, Any] = {}
    if md_path.exists():
        try:
            md = json.loads(md_path.read_text())
        except (OSError, ValueError):
            md = {}
    if "grid_origin" in meta and "grid_shape" in meta and np.isfinite(dx):
        lo = np.asarray(meta["grid_origin"], dtype=float)
        hi = lo + (np.asarray(meta["grid_shape"], dtype=float) - 1.0) * dx
    else:
        allx = np.concatenate([t.x.reshape(-1, dim) for t in trajs])
        lo, hi = allx.min(0), allx.max(0)
    spacing = float(np.median(first.volume) ** (1.0 / dim)) if len(first.volume) else dx
    seq = [t.frame_count - 1 for t in trajs]
    md.update({
        "case": case or str(meta.get("scene", "mpmlab")).upper(),
        "solver": "mpmlab",
        "backend": meta.get("backend", ""), "transfer": meta.get("transfer", ""),
        "dim": dim, "dx": dx, "dt": float(meta.get("dt", np.nan)),
        "write_every": _frame_spacing(first.step),
        "sequence_length": int(min(seq)),
        f"sequence_length_{split}": int(min(seq)), f"num_trajs_{split}": len(trajs),
        "num_particles_max": int(max(max(t.particle_count for t in trajs), md.get("num_particles_max", 0))),
        "periodic_boundary_conditions": [False] * dim,
        "bounds": np.stack([lo, hi], axis=1).tolist(),
        "particle_spacing": spacing,
        "default_connectivity_radius": 1.45 * spacing,
    })
    if split == "train" or "vel_mean" not in md:
        x32 = [np.asarray(t.x, dtype=np.float32).astype(np.float64) for t in trajs]
        vel = [np.diff(x, axis=0) for x in x32]
        acc = [np.diff(u, axis=0) for u in vel]
        md["vel_mean"], md["vel_std"] = _stats(vel, dim)
        md["acc_mean"], md["acc_std"] = _stats(acc, dim)

    write_atomically(md_path, lambda tmp: tmp.write_text(json.dumps(md, indent=2, default=_json_default)),
                     overwrite=True)
    return h5_path
