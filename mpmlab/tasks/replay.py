"""``task=replay``: turn an ``mpmlab.trajectory`` HDF5 file into a rerun recording.

    mpmlab task=replay input=outputs/2025-01-01/12-00-00/trajectory.h5 output.color_by=speed

Writes ``recording.rrd``, ``energy.png``, ``summary.json`` and ``config.yaml`` into the run directory.
A missing file, a file that is not HDF5 or an HDF5 file of another schema is refused with one line.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path

from ..config import TaskConfig, register_task_schema
from ..core.errors import ConfigError
from .common import CONFIG, ENERGY_PLOT, RECORDING, SUMMARY, check_outputs, plot_energy, write_config, write_json

log = logging.getLogger("mpmlab")


@dataclass
class ReplayTaskConfig(TaskConfig):
    """Turn an ``mpmlab.trajectory`` HDF5 file (top-level ``input``) into a recording."""

    name: str = "replay"


register_task_schema("replay", ReplayTaskConfig)


def run(cfg, ctx) -> dict:
    from .. import __version__
    from ..io.h5 import read_attrs, read_trajectory
    from ..io.metrics import compute_metrics
    from ..io.rerun import color_choices, unique_recording_id, write_recording

    t0 = time.perf_counter()
    out = Path(ctx.output_dir)
    names = [CONFIG, SUMMARY, RECORDING] + ([ENERGY_PLOT] if cfg.output.plots else [])
    check_outputs(out, names, ctx.overwrite)   # first: a refused rerun changes nothing
    if not cfg.input:
        raise ConfigError("task=replay needs the trajectory to replay: add input=PATH/trajectory.h5.")
    src = Path(str(cfg.input)).expanduser()
    if cfg.output.record_every < 1:
        raise ConfigError(f"output.record_every = {cfg.output.record_every} must be >= 1.")
    attrs = read_attrs(src)  # missing file / not HDF5 / other schema -> ConfigError
    traj = read_trajectory(src)
    if cfg.output.color_by not in color_choices(list(traj.fields)):
        raise ConfigError(f"output.color_by='{cfg.output.color_by}' is not possible for '{src}' (fields "
                          f"{sorted(traj.fields) or 'none'}); choose one of {', '.join(color_choices(list(traj.fields)))}.")
    write_config(out, cfg, ctx.overwrite)
    metrics = compute_metrics(traj) if traj.frame_count else {}
    meta = traj.meta or {}
    write_recording(out / RECORDING, traj, color_by=cfg.output.color_by, every=int(cfg.output.record_every),
                    metrics=metrics, overwrite=ctx.overwrite,
                    # unique: two replays of one scene opened at once would otherwise merge in the viewer
                    recording_id=unique_recording_id("replay", meta.get("scene", "trajectory"), out.name))
    outputs = {"config": CONFIG, "summary": SUMMARY, "recording": RECORDING}
    if cfg.output.plots and metrics:
        title = f"{meta.get('scene', src.name)} (replay of {src.name})"
        dim = int(meta.get("dim", traj.x.shape[-1]))
        if plot_energy(out / ENERGY_PLOT, traj.time, metrics, title, ctx.overwrite, dim=dim) is not None:
            outputs["energy_plot"] = ENERGY_PLOT
    summary = {
        "task": "replay",
        "status": "ok",
        "input": str(src.resolve()),
        "input_complete": bool(attrs.get("complete", False)),
        "scene": meta.get("scene"),
        "backend": meta.get("backend"),
        "transfer": meta.get("transfer"),
        "precision": meta.get("precision"),
        "particles": int(traj.particle_count),
        "frames": int(traj.frame_count),
        "color_by": cfg.output.color_by,
        "record_every": int(cfg.output.record_every),
        "wall_time_s": float(time.perf_counter() - t0),
        "outputs": outputs,
        "mpmlab_version": __version__,
    }
    write_json(out / SUMMARY, summary, ctx.overwrite)
    print(f"mpmlab: replayed {src} ({traj.frame_count} frames, {traj.particle_count} particles) -> {out / RECORDING}",
          flush=True)
    return summary
