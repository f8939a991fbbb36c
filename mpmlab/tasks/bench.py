"""``task=bench``: one run-time-versus-error point of an analytic-reference scene (issue #5, item 1).

    mpmlab task=bench task.scene=mms task.resolution=16 task.cfl=0.3 task.particles_per_axis=2 \\
        transfer=apic precision=fp64 backend=jax
    mpmlab -m task=bench task.scene=mms task.resolution=8,16,32 transfer=pic,apic,mls \\
        task.out=$PWD/benchmarks/results/pareto_multirun.json

Each job runs :func:`run_point` and appends its record to ``task.out`` (a JSON list, written
atomically under a lock file, so parallel launchers are safe) as well as writing its own
``summary.json``. ``benchmarks/pareto.py`` runs the same function in a loop and makes the table,
plots and convergence orders; ``python benchmarks/pareto.py --from-json FILE`` turns a multirun's
JSON into them.

Scenes and their error (against the analytic reference; the definitions of ``benchmarks/validation.py``):

* ``bar`` -- vibrating bar 1a (1D strip), |T / T1 - 1| of the centre-of-mass velocity period over 2
  periods; resolution = cells along L = 25 m.
* ``ritter`` -- dam break 3a (H0 = 0.1, 1.6 m tank), the largest |x_sim - x_R| / (2 sqrt(g H0) t) over
  heights 2dx..0.4 H0 and frames in [0.2, 0.3] s (metric C of benchmarks/validation.md); resolution = dx [m].
* ``hydrostatic`` -- hydrostatic column 3c (0.04 m wide, 0.1 m high, PIC-damped for 40 T1, 4-T1 mean),
  |sigma_yy(base) / (-rho g h) - 1|; resolution = dx [m].
* ``mms`` -- manufactured solution 2a, free-floating variant (nu = 0, shift 1/2, fixed corotated,
  A = 0.05), L2 particle displacement error / A at t = 0.015 s (3/4 period); resolution = cells per unit.
* ``mms_slip`` -- the note's 2a with nu = 0.3 and slip walls on the faces X_i = 0, 1.

Timing: the point's rollout (with its frames) is the first call and includes compilation
(``first_s``); then the same steps are advanced again from ``init()`` with the compiled stepper in the
same chunks and no frame output, ``repeats`` times, and the best is ``wall_s`` (steady state, as
``benchmarks/throughput.py``). ``compile_s`` = first_s - wall_s (compilation plus frame output).
"""
from __future__ import annotations

import json
import logging
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional

from ..config import TaskConfig, register_task_schema

log = logging.getLogger("mpmlab")


@dataclass
class BenchTaskConfig(TaskConfig):
    """One run-time-versus-error point (``mpmlab.tasks.bench``; ``benchmarks/pareto.py``). The backend,
    transfer and precision are the top-level groups."""

    name: str = "bench"
    #: bar | ritter | hydrostatic | mms | mms_slip
    scene: str = "mms"
    #: cells (bar: along L; mms: per unit length) or dx in metres (ritter, hydrostatic)
    resolution: Optional[float] = None
    #: time-step factor dt = cfl dx / c (None: the scene's default)
    cfl: Optional[float] = None
    #: k: k^dim particles per cell (None: the scene's default)
    particles_per_axis: Optional[int] = None
    #: steady-state timing repeats (best of)
    repeats: int = 1
    #: JSON list that each job appends its record to (absolute path; empty: summary.json only)
    out: str = ""


register_task_schema("bench", BenchTaskConfig)

SCENES = ("bar", "ritter", "hydrostatic", "mms", "mms_slip")

#: per scene: what ``resolution`` means, and the defaults of cfl and particles per axis
SCENE_INFO = {
    "bar": {"resolution": "cells along L", "cfl": 0.1, "ppa": 2},
    "ritter": {"resolution": "dx [m]", "cfl": 0.3, "ppa": 2},
    "hydrostatic": {"resolution": "dx [m]", "cfl": 0.3, "ppa": 5},
    "mms": {"resolution": "cells per unit length", "cfl": 0.3, "ppa": 2},
    "mms_slip": {"resolution": "cells per unit length", "cfl": 0.3, "ppa": 2},
}


def _steady_time(r: dict, repeats: int) -> float:
    """Best-of-``repeats`` wall time of the point's steps on the compiled stepper, in the rollout's chunks."""
    st, every, steps = r["stepper"], int(r["every"]), int(r["steps"])
    best = float("inf")
    for _ in range(max(1, repeats)):
        s = st.init()
        st._block(s)
        t0 = time.perf_counter()
        done = 0
        while done < steps:
            n = min(every, steps - done)
            s = st._advance(s, n)
            done += n
        st._block(s)
        best = min(best, time.perf_counter() - t0)
    return best


def run_point(scene: str, resolution: float, backend: str = "jax", transfer: str = "apic", precision: str = "fp32",
              cfl: float | None = None, particles_per_axis: int | None = None, repeats: int = 1) -> dict[str, Any]:
    """Run one sweep point and return its record (settings, error, timings)."""
    from ..scenes import validation as V

    if scene not in SCENES:
        raise ValueError(f"scene {scene!r}: use one of {SCENES}")
    info = SCENE_INFO[scene]
    cfl = info["cfl"] if cfl is None else float(cfl)
    k = info["ppa"] if particles_per_axis is None else int(particles_per_axis)
    common = {"backend": backend, "transfer": transfer, "precision": precision}
    extra: dict[str, Any] = {}
    if scene == "bar":
        r = V.run_vibrating_bar(periods=2.0, frames_per_period=50, cells=int(resolution), lateral="strip",
                                cfl=cfl, particles_per_cell=k * k, **common)
        error, metric = abs(r["period_error"]), "|T/T1 - 1|"
        extra = {"period_error": r["period_error"], "amplitude_ratio": r["amplitude_ratio"]}
    elif scene == "ritter":
        r = V.run_dam_break(t_end=0.3, window=(0.2, 0.3), dx=float(resolution), length=1.6, cfl=cfl,
                            particles_per_cell=k * k, **common)
        error, metric = r["max_abs_error_wave"], "max |x - x_R| / (2 sqrt(gH0) t)"
        extra = {"max_abs_error_low": r["max_abs_error_low"]}
    elif scene == "hydrostatic":
        r = V.run_hydrostatic_column(settle_periods=40.0, dx=float(resolution), width=0.04, cfl=cfl,
                                     particles_per_cell=k * k, law="newtonian_fluid", **common)
        error, metric = abs(r["error"]), "|sigma_base / (-rho g h) - 1|"
        extra = {"base_stress": r["base_stress"]}
    else:
        kw = {"boundary": "free", "nu": 0.0} if scene == "mms" else {"boundary": "slip", "nu": 0.3}
        r = V.run_mms(cells=int(resolution), cfl=cfl, particles_per_axis=k, **kw, **common)
        error, metric = r["position_error"], "L2 |x - X - U| / A at t = 0.015 s"
        extra = {"F_error": r["F_error"]}
    first = r["run_s"]
    wall = _steady_time(r, repeats)
    sc = r["scene"]
    rec = {"scene": scene, "resolution": float(resolution), "resolution_meaning": info["resolution"],
           "dx": float(sc.dx), "cfl": cfl, "particles_per_axis": k, "particles_per_cell": k ** sc.dim,
           "backend": backend, "transfer": transfer, "precision": precision, "particles": int(r["particles"]),
           "steps": int(r["steps"]), "dt": float(r["dt"]), "error": float(error), "metric": metric,
           "wall_s": float(wall), "first_s": float(first), "compile_s": float(max(first - wall, 0.0)),
           "build_s": float(r["build_s"]), **{k_: float(v) for k_, v in extra.items()}}
    return rec


def append_json(path: Path, rec: dict) -> None:
    """Append ``rec`` to the JSON list in ``path`` (created if missing), atomically, under a lock file."""
    import fcntl

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(str(path) + ".lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        data = json.loads(path.read_text()) if path.exists() else []
        data.append(rec)
        tmp = path.with_suffix(path.suffix + f".tmp{os.getpid()}")
        tmp.write_text(json.dumps(data, indent=1))
        os.replace(tmp, path)


def run(cfg, ctx) -> dict:
    from ..core.errors import ConfigError
    from .common import CONFIG, SUMMARY, check_outputs, write_config, write_json

    t = cfg.task
    if t.scene not in SCENES:
        raise ConfigError(f"task.scene = '{t.scene}' is not a bench scene; use one of {', '.join(SCENES)}.")
    if t.resolution is None:
        raise ConfigError("task=bench needs task.resolution (cells, or dx in metres for ritter/hydrostatic).")
    out = Path(ctx.output_dir)
    check_outputs(out, [CONFIG, SUMMARY], ctx.overwrite)
    write_config(out, cfg, ctx.overwrite)
    rec = run_point(str(t.scene), float(t.resolution), backend=cfg.backend.name, transfer=cfg.transfer.name,
                    precision=cfg.precision.name, cfl=t.cfl, particles_per_axis=t.particles_per_axis,
                    repeats=int(t.repeats))
    log.info("bench %s res=%g %s/%s/%s: error %.3e, wall %.3f s (compile %.2f s)", rec["scene"], rec["resolution"],
             rec["backend"], rec["transfer"], rec["precision"], rec["error"], rec["wall_s"], rec["compile_s"])
    if t.out:
        append_json(Path(str(t.out)).expanduser(), rec)
    summary = {"task": "bench", "status": "ok", **rec}
    write_json(out / SUMMARY, summary, ctx.overwrite)
    return summary
