"""``task=simulate``: build the scene, roll it out, write the run's outputs.

Outputs in the run directory: ``config.yaml`` (composed config, resolved), ``trajectory.h5``
(streamed frame by frame; after a divergence it holds the frames before it, ``complete = False``),
``recording.rrd``, ``energy.png`` and ``summary.json`` (timings, throughput on the steady-state steps,
mass/momentum drift). Every check that can fail is done before the first step, and an output that
already exists is refused unless ``output.overwrite=true``.
"""
from __future__ import annotations

import logging
import os
import platform
import time
from pathlib import Path


from ..config import build_scene, check_run_options, make_transfer_from_config
from ..core.errors import ConfigError, SimulationDiverged
from ..core.interfaces import STATE_FIELDS
from .common import (CONFIG, ENERGY_PLOT, RECORDING, SUMMARY, TRAJECTORY, FrameClock, check_outputs, drift,
                     fmt_rate, plot_energy, write_config, write_json)

log = logging.getLogger("mpmlab")

FIELD_NAMES = ("C", *STATE_FIELDS)


def stored_fields(requested, scene, transfer) -> tuple[str, ...]:
    """The requested per-particle fields that this scene's laws and transfer actually carry."""
    unknown = [f for f in requested if f not in FIELD_NAMES]
    if unknown:
        raise ConfigError(f"output.fields: unknown field(s) {unknown}; choose from {list(FIELD_NAMES)}.")
    carried = {"C"} if transfer.needs_affine else set()
    for g in scene.particles().groups:
        carried |= set(g.law.state_fields)
    return tuple(f for f in requested if f in carried)


def run(cfg, ctx) -> dict:
    from .. import __version__
    from ..io.metrics import compute_metrics
    from ..simulator import build_stepper

    t_task = time.perf_counter()
    out = Path(ctx.output_dir)
    check_run_options(cfg)
    scene = build_scene(cfg)
    transfer = make_transfer_from_config(cfg)
    backend, precision = cfg.backend.name, cfg.precision.name
    every, steps = int(cfg.frame_every), int(cfg.steps)
    fields = stored_fields(list(cfg.output.fields), scene, transfer)
    recording_fields = fields
    if cfg.output.recording:
        from ..io.rerun import color_choices

        if cfg.output.color_by not in color_choices(recording_fields):
            raise ConfigError(
                f"output.color_by='{cfg.output.color_by}' is not possible for this run (fields {list(fields) or 'none'}); "
                f"choose one of {', '.join(color_choices(recording_fields))}."
            )
    names = [CONFIG, SUMMARY]
    names += [TRAJECTORY] if cfg.output.trajectory else []
    names += [RECORDING] if cfg.output.recording else []
    names += [ENERGY_PLOT] if cfg.output.plots else []
    check_outputs(out, names, ctx.overwrite)
    if 0 < steps < every:  # e.g. steps=20 on a scene that keeps every 100th step: keep the last state
        log.info("frame_every = %d exceeds steps = %d; keeping frames 0 and %d.", every, steps, steps)
        every = steps
    if steps % every:
        log.warning("steps = %d is not a multiple of frame_every = %d: the last %d steps run but are not saved.",
                    steps, every, steps % every)

    options = {}
    if cfg.backend.check_every is not None:
        options["check_every"] = int(cfg.backend.check_every)
    if cfg.backend.device is not None:
        if backend != "warp":
            raise ConfigError(f"backend.device = '{cfg.backend.device}' applies to backend=warp only; "
                              f"JAX picks its device itself (JAX_PLATFORMS=cpu|cuda).")
        options["device"] = cfg.backend.device
    if backend == "warp" and cfg.debug:
        import warp

        warp.config.log_level = warp.LOG_INFO  # show Warp's module compile/load lines (quiet by default)

    write_config(out, cfg, ctx.overwrite)
    P = scene.particles()
    log.info("scene %s: %d particles, grid %s, dt %.3g s, %d steps (%s/%s/%s)", scene.name, P.count,
             "x".join(map(str, scene.cells)), scene.resolve_dt(), steps, backend, transfer.name, precision)

    t0 = time.perf_counter()
    stepper = build_stepper(scene, backend, transfer, precision, **options)
    build_time = time.perf_counter() - t0

    clock = FrameClock()
    writer = None
    if cfg.output.trajectory:
        from omegaconf import OmegaConf

        from ..io.h5 import TrajectoryWriter

        writer = TrajectoryWriter(
            out / TRAJECTORY, stepper=stepper, fields=fields, every=every,
            config_yaml=OmegaConf.to_yaml(cfg, resolve=True), overwrite=ctx.overwrite,
            extra_attrs={"scene": scene.name, "resolution": str(cfg.scene.resolution), "task": "simulate",
                         "seed": int(cfg.seed), "source": str(cfg.scene.source)},
        )

    def on_frame(i, npstate):
        clock(i, npstate, i * every)
        if writer is not None:
            writer(i, npstate)

    diverged = None
    try:
        traj = stepper.rollout(steps=steps, every=every, fields=fields, progress=ctx.progress, on_frame=on_frame)
    except SimulationDiverged as exc:
        diverged, traj = exc, exc.trajectory
        if writer is not None:
            writer.close(exc)  # keeps the frames before the failure, complete = False
    except BaseException as exc:
        if writer is not None:
            writer.close(exc)
        raise
    else:
        if writer is not None:
            writer.close()

    timing = clock.timing(P.count)
    metrics = compute_metrics(traj) if traj is not None and traj.frame_count else {}
    if metrics:
        metrics["step_time_ms"] = clock.step_time_per_frame()[: traj.frame_count] * 1e3
    outputs = {"config": CONFIG, "summary": SUMMARY}
    if writer is not None and (out / TRAJECTORY).exists():
        outputs["trajectory"] = TRAJECTORY
    if cfg.output.recording and traj is not None and traj.frame_count:
        from ..io.rerun import write_recording

        write_recording(out / RECORDING, traj, color_by=cfg.output.color_by, every=int(cfg.output.record_every),
                        metrics=metrics, recording_id=f"{scene.name}-{out.name}", overwrite=ctx.overwrite)
        outputs["recording"] = RECORDING
    if cfg.output.plots and metrics:
        title = f"{scene.name}: {backend}/{transfer.name}/{precision}, {P.count} particles"
        if plot_energy(out / ENERGY_PLOT, traj.time, metrics, title, ctx.overwrite) is not None:
            outputs["energy_plot"] = ENERGY_PLOT

    done = int(traj.step[-1]) if traj is not None and traj.frame_count else 0
    summary = {
        "task": "simulate",
        "status": "diverged" if diverged else "ok",
        "scene": scene.name,
        "resolution": str(cfg.scene.resolution),
        "backend": backend,
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
        "steps_saved": done,
        "frame_every": every,
        "frames": int(traj.frame_count) if traj is not None else 0,
        "wall_time_s": None,
        "build_time_s": float(build_time),
        **timing,
        **(drift(metrics, traj.time, scene.gravity) if metrics else {}),
        "seed": int(cfg.seed),
        "host": platform.node(),
        "pid": os.getpid(),
        "outputs": outputs,
        "mpmlab_version": __version__,
        "overrides": list(ctx.job.get("overrides", [])),
    }
    if diverged is not None:
        summary["error"] = str(diverged)
        summary["diverged_step"] = diverged.step
    summary["wall_time_s"] = float(time.perf_counter() - t_task)
    write_json(out / SUMMARY, summary, ctx.overwrite)
    if diverged is not None:
        raise diverged
    print(f"mpmlab: {scene.name} {backend}/{transfer.name}/{precision}: {P.count} particles x {steps} steps in "
          f"{timing['rollout_time_s']:.2f} s ("
          + (f"compile {timing['compile_time_s']:.2f} s" if timing["compile_time_s"] is not None else "incl. compile")
          + "), "
          f"{fmt_rate(timing['particle_steps_per_second'])} particle-steps/s -> {out}", flush=True)
    return summary
