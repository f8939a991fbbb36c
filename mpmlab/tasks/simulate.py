"""``task=simulate``: build the scene, roll it out, write the run's outputs.

Outputs in the run directory: ``config.yaml`` (composed config, resolved), ``trajectory.h5``
(streamed frame by frame; a run that diverged, was interrupted (SIGINT or SIGTERM) or ran out of disk
keeps the frames before it, ``complete = False`` and the reason recorded), ``recording.rrd`` (made
from trajectory.h5 after the rollout, frame by frame), ``energy.png`` and ``summary.json`` (status
``ok | diverged | interrupted | failed``, the last frame's real step and time, timings, throughput on
the steady-state steps, mass/momentum drift, particles beyond the walls). Every check that can fail is
done before the first step (outputs already there, sizes that cannot fit), and an output that already
exists is refused unless ``output.overwrite=true``; memory stays bounded on any horizon (only
per-frame scalars are kept).
"""
from __future__ import annotations

import logging
import os
import platform
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..build import build_scene, make_transfer_from_config
from ..config import TaskConfig, check_run_options, register_task_schema
from ..core.errors import ConfigError, SimulationDiverged
from ..core.signals import stop_reason
from ..io.containment import WallPenetration
from .common import (CONFIG, ENERGY_PLOT, RECORDING, SUMMARY, TRAJECTORY, FrameClock, check_outputs, drift,
                     fmt_rate, plot_energy, write_config, write_json)

log = logging.getLogger("mpmlab")


@dataclass
class SimulateTaskConfig(TaskConfig):
    name: str = "simulate"


register_task_schema("simulate", SimulateTaskConfig)


def known_fields() -> list[str]:
    """Every per-particle field a run can store: ``C`` and the state fields the registered laws declare."""
    from ..core.interfaces import registered_state_fields

    return ["C", *(f for f in registered_state_fields() if f != "C")]


def stored_fields(requested, scene, transfer) -> tuple[str, ...]:
    """The requested per-particle fields that this scene's laws and transfer actually carry; ``all``
    stands for every one of them (C first, then each law's declared fields)."""
    carried = {"C": None} if transfer.needs_affine else {}
    for g in scene.particles().groups:
        carried.update(dict.fromkeys(g.law.state_fields))
    if "all" in requested:
        requested = list(dict.fromkeys([f for f in requested if f != "all"] + list(carried)))
    known = known_fields()
    unknown = [f for f in requested if f not in known and f not in carried]
    if unknown:
        raise ConfigError(f"output.fields: unknown field(s) {unknown}; choose from {['all'] + known}.")
    return tuple(f for f in requested if f in carried)


def _output_names(cfg) -> list[str]:
    names = [CONFIG, SUMMARY]
    names += [TRAJECTORY] if cfg.output.trajectory else []
    names += [RECORDING] if cfg.output.recording else []
    names += [ENERGY_PLOT] if cfg.output.plots else []
    return names


def run(cfg, ctx) -> dict:
    from .. import __version__
    from ..io.metrics import MetricSeries
    from ..simulator import build_stepper

    t_task = time.perf_counter()
    out = Path(ctx.output_dir)
    check_outputs(out, _output_names(cfg), ctx.overwrite)   # first: a refused rerun changes nothing
    check_run_options(cfg)
    scene = build_scene(cfg)
    transfer = make_transfer_from_config(cfg)
    backend, precision = cfg.backend.name, cfg.precision.name
    every, steps = int(cfg.frame_every), int(cfg.steps)
    fields = stored_fields(list(cfg.output.fields), scene, transfer)
    # a field asked for by name that a law does not carry but can be made from what it carries
    # (F = J^(1/d) I for a J-only law: mpmlab.io.derived), written with the others and marked as such
    from ..io.derived import apply_derived, derived_metadata, plan_derived

    derived = plan_derived([f for f in cfg.output.fields if f != "all"], scene.particles().groups)
    written = fields + tuple(f for f in derived if f not in fields)
    if cfg.output.recording:
        from ..io.rerun import color_choices

        if cfg.output.color_by not in color_choices(fields):
            raise ConfigError(
                f"output.color_by='{cfg.output.color_by}' is not possible for this run (fields {list(fields) or 'none'}); "
                f"choose one of {', '.join(color_choices(fields))}."
            )
    if 0 < steps < every:  # e.g. steps=20 on a scene that keeps every 100th step: keep the last state
        log.info("frame_every = %d exceeds steps = %d; keeping frames 0 and %d.", every, steps, steps)
        every = steps
    if steps % every:
        log.info("steps = %d is not a multiple of frame_every = %d: frames are kept at steps 0, %d, ..., %d "
                 "and at the last step, %d.", steps, every, every, steps - steps % every, steps)
    check_output_sizes(cfg, scene, out, steps, every, written)

    options = {}
    if cfg.backend.check_every is not None:
        options["check_every"] = int(cfg.backend.check_every)
    if cfg.backend.device is not None or cfg.debug:
        from ..core.registry import backends

        backend_cls = backends.get(backend)
    if cfg.backend.device is not None:
        if "device" not in getattr(backend_cls, "build_options", ()):
            takes = [n for n in backends.names() if "device" in getattr(backends.get(n), "build_options", ())]
            raise ConfigError(f"backend.device = '{cfg.backend.device}' applies to backend={'|'.join(takes) or 'none'} "
                              f"only; {getattr(backend_cls, 'device_note', 'this backend picks its device itself.')}")
        options["device"] = cfg.backend.device
    if cfg.backend.get("devices") not in (None, 1):   # a backend that does not shard: check_run_options refused it
        from ..core.registry import backends

        # before anything is written: more devices than this machine has is refused here
        sizes = [g.count for g in scene.particles().groups]
        options["devices"] = backends.get(backend).check_devices(cfg.backend.devices, sizes)
    if cfg.debug and hasattr(backend_cls, "debug_output"):
        backend_cls.debug_output()      # e.g. Warp's module compile/load lines (quiet by default)

    write_config(out, cfg, ctx.overwrite)
    P = scene.particles()
    log.info("scene %s: %d particles, grid %s, dt %.3g s, %d steps (%s/%s/%s)", scene.name, P.count,
             "x".join(map(str, scene.cells)), scene.resolve_dt(), steps, backend, transfer.name, precision)

    t0 = time.perf_counter()
    stepper = build_stepper(scene, backend, transfer, precision, **options)
    build_time = time.perf_counter() - t0

    # Frames go to disk as they come (trajectory.h5); only per-frame scalars stay in memory, so memory
    # is bounded on any horizon. Without a trajectory the recording needs the frames in memory.
    clock = FrameClock()
    static = stepper._trajectory([], [], ())
    series = MetricSeries(static)
    walls = WallPenetration(scene)
    writer = None
    if cfg.output.trajectory:
        from omegaconf import OmegaConf

        from ..io.h5 import TrajectoryWriter

        meta_derived = derived_metadata(derived, scene.dim)
        writer = TrajectoryWriter(
            out / TRAJECTORY, static, fields=written, every=every,
            config_yaml=OmegaConf.to_yaml(cfg, resolve=True), overwrite=ctx.overwrite,
            # what a consumer checks a dataset against (mpmlab.nclaw.data.load_dataset): the scene, its
            # particle count, the rollout's steps and frame spacing (dt is a schema attribute), the
            # laws per material group (/materials) and the fields synthesised from others
            extra_attrs={"scene": scene.name, "resolution": str(cfg.scene.resolution), "task": "simulate",
                         "seed": int(cfg.seed), "source": str(cfg.scene.source), "particles": int(P.count),
                         "steps": steps, "frame_every": every, "fields_json": list(written),
                         "derived_fields": meta_derived},
            field_attrs={k: {"derived_from": m["source"], "derived_formula": m["formula"],
                             "derived_particles_json": m["particles"]} for k, m in meta_derived.items()},
        )

    def on_frame(i, npstate):   # runs whole (signals.deferred in the rollout): every output gets the frame
        t0 = time.perf_counter()
        clock(i, npstate, npstate["step"])
        if writer is not None:
            writer(i, apply_derived(npstate, derived, scene.dim) if derived else npstate)
        series(i, npstate)
        walls.update(npstate["x"], int(npstate["step"]))
        clock.output(time.perf_counter() - t0)

    ended: BaseException | None = None     # what stopped the rollout before its last step
    traj = None
    try:
        traj = stepper.rollout(steps=steps, every=every, fields=fields, progress=ctx.progress, on_frame=on_frame,
                               keep_frames=writer is None and bool(cfg.output.recording))
    except BaseException as exc:           # diverged, interrupted (SIGINT/SIGTERM), disk full, ...
        ended = exc
    if writer is not None:
        try:
            writer.close(ended)            # frames so far kept, complete = False, the reason recorded
        except BaseException as exc:       # e.g. the disk filled up while closing
            ended = ended or exc
    kept = writer is not None and writer._published is not None
    # an error inside on_frame (a full disk) can stop a frame half way: count the frames every output has
    frames = min(clock.count, len(series), writer.frame_count if kept else clock.count)
    done = clock.steps[frames - 1] if frames else 0
    diverged = ended if isinstance(ended, SimulationDiverged) else None
    interrupted = ended if isinstance(ended, KeyboardInterrupt) else None
    status = "ok" if ended is None else "diverged" if diverged else "interrupted" if interrupted else "failed"

    timing = clock.timing(P.count)
    metrics = {k: a[:frames] for k, a in series.result().items()}
    time_s = np.asarray(clock.times_s[:frames], dtype=np.float64)
    if metrics:
        # wall time per step of the chunk ending at each frame; the chunk 0 -> 1 pays the compilation
        # (summary.json compile_time_s), so it is left out (NaN, as frame 0) instead of setting the scale
        metrics["step_time_ms"] = clock.step_time_per_frame()[:frames] * 1e3
        metrics["step_time_ms"][1:2] = np.nan
    outputs = {"config": CONFIG, "summary": SUMMARY}
    if kept:
        outputs["trajectory"] = TRAJECTORY
    notes = []
    try:
        if cfg.output.recording and frames and status in ("ok", "diverged"):
            _write_recording(cfg, ctx, out, scene, traj if not kept else None, metrics)
            outputs["recording"] = RECORDING
        elif cfg.output.recording and frames:
            notes.append(f"recording.rrd was not written ({status}); make it from the frames kept with "
                         f"`mpmlab task=replay input={out / TRAJECTORY}`" if kept else
                         f"recording.rrd was not written ({status})")
        if cfg.output.plots and metrics and status in ("ok", "diverged"):
            title = f"{scene.name}: {backend}/{transfer.name}/{precision}, {P.count} particles"
            if diverged is not None:
                title += f"\nDIVERGED at step {diverged.step} (frames before it shown)"
            if plot_energy(out / ENERGY_PLOT, time_s, metrics, title, ctx.overwrite, dim=scene.dim) is not None:
                outputs["energy_plot"] = ENERGY_PLOT
    except BaseException as exc:           # the recording or plot could not be written (or a signal)
        if ended is None:
            ended = exc
            interrupted = exc if isinstance(exc, KeyboardInterrupt) else None
            status = "interrupted" if interrupted else "failed"

    summary = {
        "task": "simulate",
        "status": status,
        "scene": scene.name,
        "resolution": str(cfg.scene.resolution),
        "backend": backend,
        **({"devices": options["devices"]} if "devices" in options else {}),   # one run sharded over N devices
        "transfer": transfer.name,
        "transfer_options": transfer.options(),
        "precision": precision,
        "laws": [g.law.name for g in P.groups],
        "dim": scene.dim,
        "particles": int(P.count),
        "grid_cells": list(scene.cells),
        "dx": float(scene.dx),
        "dt": float(stepper.dt),
        "steps": steps,
        "steps_done": int(clock.steps[-1]) if clock.count else 0,
        "steps_saved": int(done) if kept else 0,
        "frame_every": every,
        "frames": int(frames),
        "fields": list(written) if cfg.output.trajectory else list(fields),
        "derived_fields": derived_metadata(derived, scene.dim) if cfg.output.trajectory else {},
        "last_frame": {"step": int(done), "time": float(time_s[-1]) if frames else 0.0},
        "wall_time_s": None,
        "build_time_s": float(build_time),
        **timing,
        **(drift(metrics, time_s, scene.gravity) if metrics else {}),
        "containment": walls.summary(),
        "seed": int(cfg.seed),
        "host": platform.node(),
        "pid": os.getpid(),
        "outputs": outputs,
        "mpmlab_version": __version__,
        "overrides": list(ctx.job.get("overrides", [])),
    }
    if ended is not None:
        summary["error"] = stop_reason(ended) if interrupted else str(ended)
    if diverged is not None:
        summary["diverged_step"] = diverged.step
    if notes:
        summary["notes"] = notes
    summary["wall_time_s"] = float(time.perf_counter() - t_task)
    try:
        write_json(out / SUMMARY, summary, ctx.overwrite)
    except BaseException as exc:           # a full disk: report the first failure, not this one
        if ended is None:
            raise
        del exc

    kept_line = (f"trajectory.h5 keeps {frames} frame(s) up to step {done}, marked incomplete" if kept and ended
                 else "no trajectory was kept" if ended and cfg.output.trajectory else "")
    c = summary["containment"]
    if c["particles_beyond_walls_ever"] or c["particles_in_obstacles_ever"]:
        log.warning("%d particle(s) crossed a wall face or entered an obstacle during the run (at most %d at "
                    "once, %d at the end), the deepest %.3g dx (%.3g m) through %s at step %s; see summary.json "
                    "'containment' (walls constrain grid nodes, not particles: README 'Walls').",
                    c["particles_beyond_walls_ever"] + c["particles_in_obstacles_ever"],
                    max(c["particles_beyond_walls"], c["particles_in_obstacles"]),
                    c["particles_beyond_walls_final"] + c["particles_in_obstacles_final"],
                    c["worst_depth_dx"], c["worst_depth_m"], c["worst_face"], c["worst_step"])
    for n in notes:
        log.info("%s", n)
    if ended is not None:
        detail = f"at step {done} of {steps}" + (f"; {kept_line}" if kept_line else "")
        if interrupted is not None:
            log.warning("run %s %s.", stop_reason(interrupted), detail)
        ended.mpmlab_detail = detail       # the CLI's closing line says what was kept
        raise ended
    log.info("run completed: %d steps, %d frames, %.2f s.", steps, frames, summary["wall_time_s"])
    print(f"mpmlab: {scene.name} {backend}/{transfer.name}/{precision}: {P.count} particles x {steps} steps in "
          f"{timing['rollout_time_s']:.2f} s ("
          + (f"compile {timing['compile_time_s']:.2f} s" if timing["compile_time_s"] is not None else "incl. compile")
          + "), "
          f"{fmt_rate(timing['particle_steps_per_second'])} particle-steps/s -> {out}", flush=True)
    return summary


def _write_recording(cfg, ctx, out: Path, scene, traj, metrics) -> None:
    """recording.rrd from the frames in memory (``traj``) or, frame by frame, from trajectory.h5."""
    import contextlib
    import warnings

    from ..io.h5 import open_trajectory
    from ..io.rerun import unique_recording_id, write_recording

    source = contextlib.nullcontext(traj) if traj is not None else open_trajectory(out / TRAJECTORY)
    with warnings.catch_warnings():   # "trajectory.h5 is incomplete" after a divergence: known, and reported
        warnings.filterwarnings("ignore", message=".* is incomplete", category=UserWarning)
        with source as t:
            write_recording(out / RECORDING, t, color_by=cfg.output.color_by, every=int(cfg.output.record_every),
                            metrics=metrics, recording_id=unique_recording_id(scene.name, out.name),
                            overwrite=ctx.overwrite)


def check_output_sizes(cfg, scene, out: Path, steps: int, every: int, fields) -> None:
    """Refuse a run whose outputs cannot fit on the disk of ``out`` (before the first step)."""
    from ..core.budget import output_preflight

    output_preflight(cfg, scene, out, steps=steps, frame_every=every, fields=fields)
