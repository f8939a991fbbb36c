"""``task=rom_eval``: the deformation-map ROM's online stage on a study's test runs (Chen et al. 2023,
Sec. 5): every quadrature x projection x sample-count scheme stepped by ``ReducedStepper`` from each
test run's initial state and compared with its full-order snapshots (``mpmlab.rom.evaluate``):

    mpmlab task=rom_train task.study=beam_2d task.data=data/beam hydra.run.dir=runs/beam_train
    mpmlab task=rom_eval task.study=beam_2d task.data=data/beam task.weights=runs/beam_train/rom_weights.safetensors

Errors (pooled over the test runs, snapshots and points): E about the initial centroid (the paper's,
Tabs. 3-6), and relative to the displacement, the velocity and F - I. ``task.truth_study`` /
``task.truth_data`` compare against other full-order runs of the same parameters (super-resolution:
``torsion_fine``); ``task.tracer_baseline=true`` adds Tab. 4's baseline, the finer points advected as
massless tracers through the coarse full-order runs. Outputs: ``summary.json`` (per scheme and per run, the latent trajectories, ROM and
FOM wall time per simulated second from this process), ``rom_eval.md`` (the table) and
``rom_eval.png`` (E against time per scheme) and ``rom_latent.png`` (Fig. 14: each run's latent trajectory
on its first two principal components; the table's "x̂ return" is |x̂(T) - x̂(0)| over x̂'s largest
excursion from x̂(0), the worst run: near 0 where the body's latent comes back after a poke).
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, List, Optional

import numpy as np

from ..config import TaskConfig, register_task_schema
from ..core.errors import ConfigError
from .common import SUMMARY, save_figure, write_config, write_json, write_text

log = logging.getLogger("mpmlab")
TABLE = "rom_eval.md"
PLOT = "rom_eval.png"
LATENT_PLOT = "rom_latent.png"


@dataclass
class RomEvalConfig(TaskConfig):
    """Run the reduced model of a study's test runs beside their full-order snapshots."""

    name: str = "rom_eval"
    #: the study (mpmlab.rom.snapshots.STUDIES) whose test runs are evaluated
    study: str = ""
    #: the folder of the study's runs (its test runs are read)
    data: str = ""
    #: the networks (rom_weights.safetensors of task=rom_train)
    weights: str = ""
    #: the latent size the weights must have (None: whatever they have)
    latent: Optional[int] = None
    quadratures: List[str] = field(default_factory=lambda: ["lagrangian", "eulerian"])
    projections: List[str] = field(default_factory=lambda: ["linear", "nonlinear"])
    #: sample counts |M|: integers, or "all" (every material point)
    samples: List[Any] = field(default_factory=lambda: [50, "all"])
    #: seed of the sample draws
    seed: int = 0
    #: the Eulerian quadrature's point budget, a multiple of the body's initial footprint
    #: (mpmlab.rom.stepper.EULER_CAPACITY); a step needing more stops with a one-line error
    eulerian_capacity: float = 1.5
    #: where the velocity least squares (Eqs. 21/23) takes dg/dx_hat: "next" (at x_hat_{n+1}) or "current"
    #: (at x_hat_n, as the paper writes it; it gains kinetic energy on a curved manifold): mpmlab.rom.stepper
    tangent: str = "next"
    #: how the reduced model holds the particle_velocity boundaries' points: "position" (at their prescribed
    #: positions, the paper's Eq. 3) or "velocity" (their velocities only, as before): mpmlab.rom.kinematic
    kinematic: str = "position"
    #: the position-level hold closes a held point's position error over this many steps (1: at once, Eq. 3 exactly)
    hold_steps: float = 1.0
    #: the reduced model's time step (None: the full-order run's); it must divide the snapshot interval
    dt: Optional[float] = None
    #: evaluate only the first k test runs
    max_runs: Optional[int] = None
    #: compare against another study's runs of the same parameters (e.g. torsion_fine), in truth_data
    truth_study: str = ""
    truth_data: str = ""
    #: with a truth study: also Tab. 4's baseline, the truth's points advected as tracers in each coarse run
    tracer_baseline: bool = False
    #: full-order steps timed per run (PIC, the same scene, this process), and their backend
    fom_timing_steps: int = 100
    fom_backend: str = "jax"
    #: the reduced model's backend: jax or warp (networks and projections in torch, the step in Warp kernels)
    rom_backend: str = "jax"


register_task_schema("rom_eval", RomEvalConfig)


def _samples(values) -> list:
    out = []
    for i, m in enumerate(values):
        if m == "all":
            out.append("all")
            continue
        try:
            out.append(int(m))
        except (TypeError, ValueError):
            raise ConfigError(f"task.samples[{i}] = {m!r}; give an integer or 'all'.") from None
    if not out:
        raise ConfigError("task.samples is empty; give at least one sample count (e.g. [50, all]).")
    return out


def check_not_trained_on(weights, s, test_runs) -> None:
    """Refuse test runs whose parameters are among the weights' training runs (the file's record)."""
    t = weights.training or {}
    if not t or not t.get("params"):
        return
    names = list(s.param_names)
    if not names:        # runs without parameters (e.g. the continual poke's one run) cannot repeat a training run's
        return
    seen = [tuple(float(p[k]) for k in names) for p in t["params"] if all(k in p for k in names)]
    for i in test_runs:
        key = tuple(float(s.runs[i].params[k]) for k in names)
        if any(np.allclose(key, q, rtol=1e-9, atol=1e-12) for q in seen):
            raise ConfigError(f"rom_eval: test run {s.runs[i].name} ({dict(zip(names, key))}) is one of the weights' "
                              f"training runs (study '{t.get('study')}'); evaluate on runs the networks have not seen.")


def run(cfg, ctx) -> dict:
    from .. import __version__
    from ..rom import evaluate as ev
    from ..rom import networks as N
    from ..rom.snapshots import load_snapshots, study

    t_task = time.perf_counter()
    out = Path(ctx.output_dir)
    tc = cfg.task
    if not tc.study or not tc.data or not tc.weights:
        raise ConfigError("task=rom_eval needs task.study=NAME, task.data=DIR (the study's runs) and "
                          "task.weights=FILE (rom_weights.safetensors of task=rom_train).")
    if (out / SUMMARY).exists() and not ctx.overwrite:
        raise ConfigError(f"{out / SUMMARY} exists; choose another hydra.run.dir or set output.overwrite=true.")
    s = study(str(tc.study))
    if not s.test:
        raise ConfigError(f"task.study = '{s.name}' has no test runs.")
    k = None if tc.max_runs is None else int(tc.max_runs)
    if k is not None and k < 1:
        raise ConfigError(f"task.max_runs = {k} must be >= 1 (or null: every test run).")
    test_runs = tuple(s.test)[:k]
    if not Path(str(tc.weights)).is_file():
        raise ConfigError(f"task.weights = '{tc.weights}' is not a file; give rom_weights.safetensors of task=rom_train.")
    for key in ("fom_backend", "rom_backend"):
        if tc[key] not in ("jax", "warp"):
            raise ConfigError(f"task.{key} = '{tc[key]}'; choose jax or warp.")
    precision = cfg.precision.name
    snap = load_snapshots(str(tc.data), s, runs=test_runs)
    dim = snap.x.shape[-1]
    weights = N.load(str(tc.weights), expect_dim=dim, expect_latent=None if tc.latent is None else int(tc.latent))
    check_not_trained_on(weights, s, test_runs)
    truth = None
    if tc.truth_study:
        ts = study(str(tc.truth_study))
        names = [s.runs[i].name for i in test_runs]
        idx = []
        for i in test_runs:
            hit = [j for j, r in enumerate(ts.runs) if r.params == s.runs[i].params]
            if len(hit) != 1:
                raise ConfigError(f"task.truth_study = '{ts.name}' has no run with the parameters of {s.runs[i].name}.")
            idx.append(hit[0])
        truth = load_snapshots(str(tc.truth_data or tc.data), ts, runs=idx)
        truth.names = tuple(names)
    if tc.tracer_baseline and truth is None:
        raise ConfigError("task.tracer_baseline=true needs task.truth_study (and task.truth_data): the finer runs "
                          "whose points the tracers are.")
    sch = ev.schemes(list(tc.quadratures), list(tc.projections), _samples(tc.samples))
    write_config(out, cfg, True)
    log.info("rom_eval: study %s, %d test runs, %d schemes, weights %s (latent %d)", s.name, len(test_runs), len(sch),
             tc.weights, weights.spec.latent)
    res = ev.evaluate(weights, snap, sch, precision=precision, dt=None if tc.dt is None else float(tc.dt),
                      seed=int(tc.seed), truth=truth, fom_timing_steps=int(tc.fom_timing_steps),
                      fom_backend=str(tc.fom_backend), backend=str(tc.rom_backend), progress=ctx.progress, log=log,
                      eulerian_capacity=float(tc.eulerian_capacity), tangent=str(tc.tangent),
                      kinematic=str(tc.kinematic), hold_steps=float(tc.hold_steps))
    if tc.tracer_baseline:
        res["tracer_baseline"] = ev.tracer_baseline(snap, truth, precision=precision, backend=str(tc.fom_backend),
                                                    progress=ctx.progress, log=log)
    diverged = [r for r in res["rows"] if r["status"] != "ok"]
    summary = {"task": "rom_eval", "status": "ok" if not diverged else "diverged", "study": s.name,
               "data": str(tc.data), "weights": str(tc.weights), "latent": weights.spec.latent,
               "training": weights.training, "test_runs": list(snap.names),
               "truth": {"study": tc.truth_study, "data": tc.truth_data or str(tc.data)} if tc.truth_study else None,
               "precision": precision, "seed": int(tc.seed), **res,
               "wall_time_s": float(time.perf_counter() - t_task), "mpmlab_version": __version__}
    write_json(out / SUMMARY, summary, True)
    write_text(out / TABLE, table_markdown(summary), True)
    if cfg.output.plots:
        _plot(out / PLOT, summary)
        _plot_latent(out / LATENT_PLOT, summary)
    best = min((r for r in res["schemes"] if r["E"] is not None), key=lambda r: r["E"], default=None)
    print(f"mpmlab: rom_eval {s.name}: {len(snap.names)} test runs x {len(sch)} schemes"
          + (f"; best {best['scheme']}: E {best['E']:.2%}" if best else "")
          + (f"; {len(diverged)} diverged" if diverged else "") + f" -> {out / TABLE}", flush=True)
    if diverged:
        from ..core.errors import SimulationDiverged

        first = diverged[0]
        raise SimulationDiverged(first["diverged_at_step"], -1, "x_hat", "non-finite or outside the domain",
                                 f"the reduced model of {first['run']} ({first['scheme']}) diverged; lower task.dt "
                                 f"(the other schemes' results are in {out / SUMMARY})")
    return summary


def _pct(x) -> str:
    return "—" if x is None else f"{100 * x:.2f}"


def table_markdown(s: dict) -> str:
    fom = s["fom"]["wall_s_per_simulated_s"]
    lines = [f"# ROM evaluation: study {s['study']}, latent {s['latent']}, {len(s['test_runs'])} test runs ({s['precision']})", "",
             f"Errors in % (pooled over runs, snapshots and points); reduced model on {s['fom'].get('rom_backend', 'jax')}. "
             f"Full-order model ({s['fom']['backend']}, PIC): "
             f"{fom:.3g} s per simulated s." if fom else "", "",
             "| scheme | E | E (corner) | E (displacement) | E_v | E_F | s per simulated s | speed-up | x̂ return | diverged |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in s["schemes"]:
        sp = r["speedup_vs_fom"]
        lines.append(f"| {r['scheme']} | {_pct(r['E'])} | {_pct(r.get('E_corner'))} | {_pct(r['E_displacement'])} | "
                     f"{_pct(r['E_v'])} | "
                     f"{_pct(r['E_F'])} | {r['wall_s_per_simulated_s']:.3g} | {'—' if sp is None else f'{sp:.2f}x'} | "
                     f"{_pct(r.get('latent_return'))} | {r['diverged']}/{r['runs']} |")
    tb = s.get("tracer_baseline")
    if tb:
        lines.append(f"| tracer baseline (the truth's points advected in the coarse full-order run) | {_pct(tb['E'])} | "
                     f"{_pct(tb.get('E_corner'))} | {_pct(tb['E_displacement'])} | {_pct(tb['E_v'])} | {_pct(tb['E_F'])} | "
                     f"{tb['wall_s_per_simulated_s']:.3g} | — | — | — |")
    early = [r for r in s["rows"] if r.get("before_divergence")]
    if early:
        lines += ["", "Diverged runs, their errors over the snapshots before the divergence:", "",
                  "| run | scheme | diverged at step | snapshots kept | until [s] | E | E (corner) | E (displacement) | E_F |",
                  "|---|---|---|---|---|---|---|---|---|"]
        for r in early:
            b = r["before_divergence"]
            lines.append(f"| {r['run']} | {r['scheme']} | {r['diverged_at_step']} | {b['frames']} | {b['until_s']:.4g} | "
                         f"{_pct(b['E'])} | {_pct(b.get('E_corner'))} | {_pct(b['E_displacement'])} | {_pct(b['E_F'])} |")
    lines += ["", "E = sqrt(sum |x_ROM - x_FOM|^2 / sum |x_FOM - c|^2), c the initial centroid; E (corner): the same "
                  "about the scene domain's lower corner, the kind of origin the paper's numbers are consistent with "
                  "(mpmlab.rom.evaluate)."]
    return "\n".join(lines) + "\n"


def _plot(path: Path, s: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4))
    for sch in s["schemes"]:
        rows = [r for r in s["rows"] if r["scheme"] == sch["scheme"] and r["status"] == "ok"]
        if not rows:
            continue
        num = np.sum([r["per_frame"]["x"] for r in rows], axis=0)
        den = np.sum([r["per_frame"]["x_c"] for r in rows], axis=0)
        t = np.arange(len(num)) * s["snapshot_interval"]
        ax.plot(t, 100 * np.sqrt(num / den), label=sch["scheme"], lw=1.2)
    for r in s["rows"]:                  # a diverged run: its snapshots before the divergence, dashed
        b = r.get("before_divergence")
        if b:
            e = np.sqrt(np.asarray(b["per_frame"]["x"]) / np.asarray(b["per_frame"]["x_c"]))
            ax.plot(np.arange(len(e)) * s["snapshot_interval"], 100 * e, ls="--", lw=1.0,
                    label=f"{r['scheme']}, {r['run']}: diverged at {b['until_s']:.3g} s")
    ax.set_xlabel("time [s]"); ax.set_ylabel("E per snapshot [%]")
    ax.set_title(f"rom_eval {s['study']}: latent {s['latent']}", fontsize=9); ax.legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, path, "rom_eval")


def _plot_latent(path: Path, s: dict) -> None:
    """Fig. 14: per run (first scheme that ran), x̂(t) on its first two principal components, the start
    marked and the step numbers annotated at a few frames."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..rom.evaluate import latent_pca

    for sch in s["schemes"]:
        rows = [r for r in s["rows"] if r["scheme"] == sch["scheme"] and r["status"] == "ok" and r.get("z")][:4]
        if rows:
            break
    else:
        return
    fig, axes = plt.subplots(1, len(rows), figsize=(max(5.5, 3.6 * len(rows)), 3.8), squeeze=False)
    for ax, r in zip(axes[0], rows):
        p, share = latent_pca(r["z"])
        every = max(1, round(r["steps"] / max(1, len(p) - 1)))
        ax.plot(p[:, 0], p[:, 1], lw=0.8)
        ax.plot(p[0, 0], p[0, 1], "ko", ms=5, label="x̂(0)")
        for i in np.linspace(0, len(p) - 1, 7).astype(int)[1:]:
            ax.annotate(str(i * every), p[i], fontsize=6)
        ret = r.get("latent_return")
        ax.set_title(f"{r['run']}: return {'—' if ret is None else f'{100 * ret:.1f} %'}", fontsize=8)
        ax.set_xlabel(f"PC 1 ({100 * share[0]:.0f} %)", fontsize=7)
        ax.set_ylabel(f"PC 2 ({100 * share[1]:.0f} %)", fontsize=7)
        ax.legend(fontsize=6)
    fig.suptitle(f"rom_eval {s['study']}: {rows[0]['scheme']}\nthe latent on its principal components (Fig. 14)", fontsize=8)
    fig.tight_layout()
    save_figure(fig, path, "rom_eval")
