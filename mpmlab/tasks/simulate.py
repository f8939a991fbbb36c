"""``task=simulate``: build the scene, roll it out, write the run's outputs.

Outputs in the run directory: ``config.yaml`` (composed config, resolved), ``trajectory.h5``
(streamed frame by frame; a run that diverged, was interrupted (SIGINT or SIGTERM) or ran out of disk
keeps the frames before it, ``complete = False`` and the reason recorded), ``recording.rrd`` (made
from trajectory.h5 after the rollout, frame by frame), ``energy.png`` and ``summary.json`` (status
``ok | diverged | interrupted | failed``, the last frame's real step and time, timings, throughput on
the steady-state steps, mass/momentum drift, particles beyond the walls). With the run-out analysis
(``task.runout``; on by default for scenes that declare ``scene.vars.runout``, the granular collapses)
also ``runout.png``, a ``runout`` block in summary.json (L_f, d_n, height at the wall, deposit profile,
whether and when the deposit settled: :mod:`mpmlab.analysis.runout`), the ``metrics/runout_*`` series
and the final ``world/deposit_profile`` in the recording; ``task.runout.stop_when_settled=true`` ends
the run at the first frame where the deposit has settled, every output closed as complete up to that
frame (trajectory.h5 ``steps`` = the steps run, ``steps_planned`` beside it). Every check that can fail is
done before the first step (outputs already there, sizes that cannot fit), and an output that already
exists is refused unless ``output.overwrite=true``; memory stays bounded on any horizon (only
per-frame scalars are kept).
"""
from __future__ import annotations

import logging
import os
import platform
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import List, Optional

import numpy as np

from ..build import build_scene, make_transfer_from_config, shape_options_from_config
from ..config import TaskConfig, check_run_options, register_task_schema
from ..core.errors import ConfigError, SimulationDiverged
from ..core.signals import stop_reason
from ..io.containment import WallPenetration
from .common import (CONFIG, ENERGY_PLOT, RECORDING, SUMMARY, TRAJECTORY, FrameClock, check_outputs, drift,
                     fmt_rate, plot_energy, write_config, write_json)

log = logging.getLogger("mpmlab")


@dataclass
class RunoutOptions:
    """``task.runout``: the run-out analysis (:mod:`mpmlab.analysis.runout`). ``enabled``: null (the
    default) runs it where the scene declares its geometry (``scene.vars.runout``: the granular
    collapse scenes), true runs it on any scene (error if no flow axis is known), false never. A key
    left null here takes the scene's value; the rest has defaults: ``up`` against gravity, ``wall`` and
    ``base`` the domain's lower faces, ``direction`` +1, ``cell`` the grid spacing."""

    enabled: Optional[bool] = None
    #: the flow axis (x|y|z or 0..dim-1) from the wall; or ``center`` for a radial flow
    axis: Optional[str] = None
    #: the axis against gravity
    up: Optional[str] = None
    #: the wall's position along ``axis`` [m]; ``direction`` +1: the flow goes towards larger coordinates
    wall: Optional[float] = None
    direction: Optional[int] = None
    #: the floor's position along ``up`` [m]
    base: Optional[float] = None
    #: radial flow (a cylinder collapse): the horizontal distance from this point
    center: Optional[List[float]] = None
    #: the initial column's length (radial: radius) and height, for d_n = (L_f - L0) / L0 and H_wall / H0
    L0: Optional[float] = None
    H0: Optional[float] = None
    #: cube edge of the deposit's connectivity and the profile's bin width [m] (default: the grid's dx)
    cell: Optional[float] = None
    #: the stop rule: front and wall height moved < tol_cells cells over window_s s, and kinetic energy
    #: below ke_fraction of its peak
    window_s: float = 0.1
    tol_cells: float = 0.1
    ke_fraction: float = 1.0e-3
    #: end the run at the first frame where the rule holds (outputs closed as complete, up to that frame)
    stop_when_settled: bool = False


@dataclass
class SimulateTaskConfig(TaskConfig):
    name: str = "simulate"
    runout: RunoutOptions = field(default_factory=RunoutOptions)


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
    names += [RUNOUT_PLOT] if cfg.output.plots and _runout_wanted(cfg) else []
    return names


def _runout_wanted(cfg) -> bool:
    """Whether the run-out analysis runs (before the scene is built: the output names are checked first)."""
    opts = cfg.task.get("runout")
    if opts is None:
        return False
    if opts.enabled is not None:
        return bool(opts.enabled)
    vars_ = cfg.scene.get("vars")
    return bool(vars_ is not None and vars_.get("runout"))


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
    shape_opts = shape_options_from_config(cfg, scene, transfer)    # transfer.shape: checked before anything is written
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
    plan = runout_plan(cfg, scene)      # the run-out analysis (task.runout), its options checked here

    options = dict(shape_opts)
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

    keep_frames = writer is None and bool(cfg.output.recording)
    # a run that may stop when its deposit settles keeps the recording's frames itself: the rollout's own
    # trajectory is lost with the exception that ends it
    own_frames: list | None = [] if keep_frames and plan is not None and plan.stop_when_settled else None

    def on_frame(i, npstate):   # runs whole (signals.deferred in the rollout): every output gets the frame
        t0 = time.perf_counter()
        clock(i, npstate, npstate["step"])
        if writer is not None:
            writer(i, apply_derived(npstate, derived, scene.dim) if derived else npstate)
        series(i, npstate)
        walls.update(npstate["x"], int(npstate["step"]))
        if own_frames is not None:
            own_frames.append({k: npstate[k] for k in ("x", "v", *fields) if k in npstate})
        if plan is not None:
            plan.monitor.update(float(npstate["time"]), npstate["x"], npstate["v"])
        clock.output(time.perf_counter() - t0)
        if plan is not None and plan.stop_when_settled and plan.monitor.settled:
            raise _Settled()

    ended: BaseException | None = None     # what stopped the rollout before its last step
    stopped_early = False                  # task.runout.stop_when_settled ended it (a clean stop)
    traj = None
    try:
        traj = stepper.rollout(steps=steps, every=every, fields=fields, progress=ctx.progress, on_frame=on_frame,
                               keep_frames=keep_frames)
    except _Settled:
        stopped_early = True
        if own_frames is not None:
            n = len(own_frames)
            traj = stepper._trajectory(own_frames, list(clock.steps[:n]), fields, list(clock.times_s[:n]))
    except BaseException as exc:           # diverged, interrupted (SIGINT/SIGTERM), disk full, ...
        ended = exc
    if stopped_early and writer is not None and writer._f is not None:
        # a complete file of the steps actually run: 'steps' is what was run, the plan beside it
        a = writer._f.attrs
        a["steps_planned"] = steps
        a["steps"] = int(clock.steps[-1])
        a["stopped_when_settled"] = True
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
    runout = None
    rec_metrics, overlays = metrics, None
    if plan is not None and plan.monitor.times:
        from ..analysis.runout import profile_points, register_metrics

        try:
            runout = runout_result(plan, stopped_early)
            register_metrics()
            n = min(frames, len(plan.monitor.times))
            rec_metrics = {**metrics, **{k: np.concatenate([a[:n], np.full(frames - n, np.nan)])
                                         for k, a in plan.monitor.series().items()}}
            overlays = {"world/deposit_profile": (max(0, min(len(plan.monitor.times), frames) - 1),
                                                  profile_points(runout, plan.monitor.geometry, plan.lateral))}
        except Exception as exc:           # noqa: BLE001 - the analysis must not cost the run its summary
            runout = {"error": f"{type(exc).__name__}: {exc}"}
    try:
        if cfg.output.recording and frames and status in ("ok", "diverged"):
            _write_recording(cfg, ctx, out, scene, traj if not kept else None, rec_metrics, overlays)
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
            if runout is not None and "L_f" in runout:
                plot_runout(out / RUNOUT_PLOT, plan, runout, title, ctx.overwrite)
                outputs["runout_plot"] = RUNOUT_PLOT
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
        "shape": shape_opts.get("shape", "quadratic"),
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
        **({"runout": runout} if runout is not None else {}),
        **({"stopped_when_settled": {"step": int(done), "time": float(time_s[-1]) if frames else 0.0,
                                     "steps_planned": steps}} if stopped_early else {}),
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
    if runout is not None:
        _log_runout(runout)
    if stopped_early:
        log.info("run stopped at step %d of %d (t = %.4g s): the deposit settled (task.runout.stop_when_settled); "
                 "%d frames, %.2f s.", done, steps, summary["last_frame"]["time"], frames, summary["wall_time_s"])
    else:
        log.info("run completed: %d steps, %d frames, %.2f s.", steps, frames, summary["wall_time_s"])
    print(f"mpmlab: {scene.name} {backend}/{transfer.name}/{precision}: {P.count} particles x {summary['steps_done']} "
          f"steps in "
          f"{timing['rollout_time_s']:.2f} s ("
          + (f"compile {timing['compile_time_s']:.2f} s" if timing["compile_time_s"] is not None else "incl. compile")
          + "), "
          f"{fmt_rate(timing['particle_steps_per_second'])} particle-steps/s -> {out}", flush=True)
    return summary


def _log_runout(r: dict) -> None:
    if "error" in r:
        log.warning("run-out analysis failed: %s", r["error"])
        return
    dn = f" (d_n = {r['d_n']:.3f})" if r.get("d_n") is not None else ""
    how = (f"settled at t = {r['settled_time']:.4g} s" if r["settled"] else
           "NOT settled: the front moved "
           + (f"{r['front_moved_last_window_cells']:.2f} cells" if r["front_moved_last_window_cells"] is not None
              else "(the run is shorter than the window)")
           + f" over the last {r['stop_rule']['window_s']:g} s, so L_f is not final")
    at = "the centre" if "center" in r["geometry"] else "the wall"
    log.info("run-out at t = %.4g s: L_f = %.4g m%s, height at %s %.4g m; %s; %d particle(s) left out of "
             "the deposit.", r["time"], r["L_f"], dn, at, r["H_wall"], how, r["particles_left_out"])


def _write_recording(cfg, ctx, out: Path, scene, traj, metrics, overlays=None) -> None:
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
                            overwrite=ctx.overwrite, line_strips=overlays)


# ---- run-out analysis (task.runout; mpmlab.analysis.runout) -------------------------------------
RUNOUT_PLOT = "runout.png"
_RUNOUT_SCENE_KEYS = ("axis", "up", "wall", "direction", "base", "center", "L0", "H0")


class _Settled(Exception):
    """Raised from on_frame to end a rollout whose deposit has settled (task.runout.stop_when_settled)."""


@dataclass
class RunoutPlan:
    monitor: "object"
    L0: Optional[float]
    H0: Optional[float]
    stop_when_settled: bool
    lateral: list


def runout_plan(cfg, scene) -> RunoutPlan | None:
    """The run-out monitor this run feeds, or None (``task.runout.enabled`` false, or null on a scene
    without ``scene.vars.runout``). Every option is checked here, before anything is written."""
    from omegaconf import OmegaConf

    from ..analysis.runout import RunoutGeometry, RunoutMonitor, axis_index

    opts = cfg.task.get("runout")
    if opts is None:
        return None
    vars_ = cfg.scene.get("vars") or {}
    declared = vars_.get("runout") if hasattr(vars_, "get") else None
    if declared is not None and not OmegaConf.is_dict(declared):
        raise ConfigError(f"scene.vars.runout must be a mapping of {', '.join(_RUNOUT_SCENE_KEYS)} "
                          f"(got {declared!r}).")
    declared = OmegaConf.to_container(declared, resolve=True) if declared is not None else {}
    unknown = sorted(set(declared) - set(_RUNOUT_SCENE_KEYS))
    if unknown:
        raise ConfigError(f"scene.vars.runout: unknown key(s) {unknown}; the run-out geometry takes "
                          f"{', '.join(_RUNOUT_SCENE_KEYS)}.")
    enabled = opts.enabled if opts.enabled is not None else bool(declared)
    if not enabled:
        if opts.stop_when_settled:
            raise ConfigError("task.runout.stop_when_settled=true needs the run-out analysis: set "
                              "task.runout.enabled=true (and its geometry, task.runout.axis=..., on a scene "
                              "without scene.vars.runout).")
        return None

    def get(key):
        v = opts.get(key)
        return declared.get(key) if v is None else (OmegaConf.to_container(v) if OmegaConf.is_config(v) else v)

    dim = int(scene.dim)
    lo, hi = (list(cfg.scene.domain.lo), list(cfg.scene.domain.hi))
    g = np.asarray(scene.gravity, dtype=np.float64)
    up = get("up")
    if up is None:
        if not np.any(g):
            raise ConfigError(f"task.runout: scene '{scene.name}' has no gravity; give the up axis "
                              f"(task.runout.up=x|y|z).")
        up = int(np.argmax(np.abs(g)))
        if g[up] > 0:
            raise ConfigError(f"task.runout: gravity points along +{'xyz'[up]}; the run-out measures heights "
                              f"above a floor at the lower face, so set task.runout.up and task.runout.base.")
    up = axis_index(up, dim, "task.runout.up")
    # the mode (a wall or a centre) given in task.runout wins over the scene's
    if opts.center is not None and opts.axis is not None:
        raise ConfigError("task.runout: give either a flow axis (axis, wall: flow away from a wall) or a center "
                          "(radial flow), not both.")
    if opts.center is not None:
        center, axis = get("center"), None
    elif opts.axis is not None:
        center, axis = None, get("axis")
    else:
        center, axis = declared.get("center"), declared.get("axis")
        if center is not None and axis is not None:
            raise ConfigError("scene.vars.runout: give either a flow axis (axis, wall) or a center, not both.")
    if center is None and axis is None:
        raise ConfigError(f"task.runout: scene '{scene.name}' declares no run-out geometry (scene.vars.runout); "
                          f"give the flow axis (task.runout.axis=x|y|z) or a center (task.runout.center=[...]).")

    def number(key, default):
        v = get(key)
        if v is None:
            return default
        try:
            return float(v)
        except (TypeError, ValueError):
            raise ConfigError(f"task.runout.{key} = {v!r} is not a number.") from None

    direction = get("direction")
    if center is None:
        axis = axis_index(axis, dim, "task.runout.axis")
        direction = 1 if direction is None else direction
        if direction not in (1, -1, "1", "-1", "+1"):
            raise ConfigError(f"task.runout.direction = {direction!r} must be +1 or -1.")
        direction = int(direction)
        wall = number("wall", lo[axis] if direction > 0 else hi[axis])
    else:
        if not isinstance(center, (list, tuple)) or not all(isinstance(c, (int, float)) for c in center):
            raise ConfigError(f"task.runout.center = {center!r} must be a list of numbers.")
        axis, wall, direction = None, 0.0, 1
    base = number("base", lo[up])
    cell = number("cell", float(scene.dx))
    L0, H0 = number("L0", None), number("H0", None)
    for key, v in (("L0", L0), ("H0", H0)):
        if v is not None and not v > 0:
            raise ConfigError(f"task.runout.{key} = {v} must be positive (or null: not known).")
    for key in ("window_s", "tol_cells", "cell"):
        v = cell if key == "cell" else float(opts[key])
        if not (v > 0 and np.isfinite(v)):
            raise ConfigError(f"task.runout.{key} = {v} must be a positive number.")
    if not 0.0 <= float(opts.ke_fraction) <= 1.0:
        raise ConfigError(f"task.runout.ke_fraction = {opts.ke_fraction} must be in [0, 1] (a fraction of the "
                          f"peak kinetic energy).")
    geometry = RunoutGeometry(dim=dim, up=up, axis=axis, wall=wall, direction=direction, base=base,
                              center=None if center is None else tuple(float(c) for c in center))
    P = scene.particles()
    size = np.asarray(P.volume, dtype=np.float64) ** (1.0 / dim)
    monitor = RunoutMonitor(geometry, cell, mass=np.asarray(P.mass, dtype=np.float64), particle_size=size,
                            window_s=float(opts.window_s), tol_cells=float(opts.tol_cells),
                            ke_fraction=float(opts.ke_fraction))
    # where the profile is drawn in 3D: across the middle of the domain's other horizontal axis
    lateral = [0.5 * (a + b) for a, b in zip(lo, hi)]
    return RunoutPlan(monitor, L0, H0, bool(opts.stop_when_settled), lateral)


def runout_result(plan: RunoutPlan, stopped_early: bool) -> dict:
    from ..analysis.runout import summarize

    out = summarize(plan.monitor, plan.L0, plan.H0)
    out["stopped_early"] = bool(stopped_early)
    out["stop_when_settled"] = plan.stop_when_settled
    return out


def plot_runout(path: Path, plan: RunoutPlan, result: dict, title: str, overwrite: bool) -> Path:
    """runout.png: the front and the height at the wall over time (the settling time marked) and the
    final deposit profile."""
    from matplotlib.figure import Figure

    from ..io.files import write_atomically

    m = plan.monitor
    fig = Figure(figsize=(11, 4), dpi=110)
    a, b = fig.subplots(1, 2)
    t = np.asarray(m.times)
    where = "the axis" if m.geometry.radial else "the wall"
    at = "the centre" if m.geometry.radial else "the wall"
    a.plot(t, m.fronts, label=f"front L(t) (from {where})")
    a.plot(t, m.heights, label=f"height at {at} H(t)")
    if m.settled:
        a.axvline(m.settled_time, color="k", ls="--", lw=1, label=f"settled, t = {m.settled_time:.3g} s")
    a.set_xlabel("time [s]"); a.set_ylabel("[m]"); a.grid(alpha=0.3); a.legend(fontsize=8)
    a.set_title(f"front and height at {at}")
    p = result["profile"]
    b.step(p["distance"], p["height"], where="mid", label=f"t = {result['time']:.3g} s")
    b.axvline(result["L_f"], color="C3", lw=1, label=f"L_f = {result['L_f']:.4g} m")
    if plan.L0 is not None:
        b.axvline(plan.L0, color="0.5", ls=":", lw=1, label=f"L0 = {plan.L0:.4g} m")
    b.set_xlabel(f"distance from {where} [m]"); b.set_ylabel("deposit height [m]"); b.grid(alpha=0.3)
    b.set_aspect("equal", adjustable="datalim"); b.legend(fontsize=8)
    dn = result.get("d_n")
    b.set_title("final deposit profile" + (f", d_n = {dn:.3f}" if dn is not None else ""))
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return write_atomically(path, lambda tmp: fig.savefig(tmp, format="png", metadata={"Title": title}), overwrite)


def check_output_sizes(cfg, scene, out: Path, steps: int, every: int, fields) -> None:
    """Refuse a run whose outputs cannot fit on the disk of ``out`` (before the first step)."""
    from ..core.budget import output_preflight

    output_preflight(cfg, scene, out, steps=steps, frame_every=every, fields=fields)
