"""``task=nclaw_eval``: a learned law against the ground truth on NCLaw's evaluation scenes (Ma et al.
2023, Sec. 4, Tabs. 1-2), on either backend.

    mpmlab task=nclaw_eval task.material=jelly task.weights=RUN/nclaw_weights.safetensors
    mpmlab task=nclaw_eval task.material=jelly                       # "ours-init": the untrained nets

For each case of :func:`mpmlab.nclaw.scenes.eval_cases` (or given ones), the ground truth (the
material's true law) and the learned law (``material=nclaw`` with the weights) are rolled out from
the same initial state, without teacher forcing, and compared by NCLaw's metric: the mean over frames
0, 5, 10, ... of the per-coordinate position MSE [m^2] (:func:`~mpmlab.nclaw.scenes.position_mse`).
Ground-truth rollouts are kept (``truth/<case>.npz``) and reused by later evaluations in the same
run directory or from ``task.truth_dir``, so ours, ours-init and other weights share them.

Outputs: ``summary.json`` (per case: the metric, the paper's value where Tabs. 1-2 give one, wall
times, particles, steps, status; for a learned law its ``state_range`` every 50 steps and, where the
weight file records its training's range, ``beyond_training``: where the rollout left it, also logged
as a warning, since the metric then measures an extrapolation), ``eval.md`` (the table), ``eval.png`` (MSE per frame), ``<case>_frames.png`` for the qualitative
cases (truth and learned particles side by side at four frames) and the ground-truth cache. A learned rollout that diverges is reported as such; the other cases still run.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List

import numpy as np

from ..config import TaskConfig, register_task_schema
from ..core.errors import ConfigError, SimulationDiverged, TimeStepError
from ..nclaw.probe import RangeTracker, beyond_training, read_state_range
from .common import SUMMARY, save_figure, write_config, write_json, write_text

log = logging.getLogger("mpmlab")
#: the learned law's state range is sampled every this many steps (``nclaw.probe.RangeTracker``)
RANGE_EVERY = 50

#: NCLaw Tab. 1 ("ours", "ours-init") and Tab. 2 ("ours" (a) time, (b) velocity: mean of seeds 1, 7, 8,
#: (c) geometry); JELL-O (a) lost its leading digit in the seed text (None: report only)
PAPER = {
    "ours": {
        "jelly": {"reconstruction": 2.4e-4, "time": None, "velocity": 2.4e-4, "geometry": 4.1e-4},
        "sand": {"reconstruction": 2.6e-5, "time": 4.2e-5, "velocity": 6.5e-5, "geometry": 3.6e-4},
        "plasticine": {"reconstruction": 6.5e-5, "time": 1.4e-4, "velocity": 4.6e-5, "geometry": 2.3e-4},
        "water": {"reconstruction": 2.0e-5, "time": 3.5e-4, "velocity": 1.9e-5, "geometry": 2.4e-4},
    },
    "ours-init": {
        "jelly": {"reconstruction": 1.1e-1, "time": None, "velocity": 6.6e-2, "geometry": 1.2e-1},
        "sand": {"reconstruction": 4.8e-2, "time": 1.5e-1, "velocity": 2.7e-2, "geometry": 5.0e-2},
        "plasticine": {"reconstruction": 4.6e-2, "time": 1.3e-1, "velocity": 2.7e-2, "geometry": 5.8e-2},
        "water": {"reconstruction": 6.8e-2, "time": 3.0e-1, "velocity": 4.1e-2, "geometry": 1.0e-1},
    },
}
DEFAULT_CASES = ["reconstruction", "time", "velocity_seed1", "velocity_seed7", "velocity_seed8", "geometry"]
TABLE = "eval.md"
PLOT = "eval.png"


@dataclass
class NclawEvalConfig(TaskConfig):
    """Roll a learned nclaw law out beside the ground truth on NCLaw's evaluation scenes."""

    name: str = "nclaw_eval"
    #: the training material whose true law is the ground truth: jelly | sand | plasticine | water
    material: str = ""
    #: the trained weights (nclaw_weights.safetensors of task=nclaw_train); empty: the untrained
    #: initialisation (NCLaw's "ours-init")
    weights: str = ""
    #: case names of mpmlab.nclaw.scenes.eval_cases(material) ("all": every one), or mappings
    #: {name, scene, steps, overrides: [...], tags: [qualitative]} for scenes of your own
    cases: List[Any] = field(default_factory=lambda: list(DEFAULT_CASES))
    #: the learned law runs at the case's dt (its plastic step F <- F + alpha R T is per time step): its tangent at
    #: F = I may be stiffer than the truth's, so its run's cfl_limit is raised to at least this (explicit
    #: MPM's bound); a CFL number above it is recorded as status "refused" and the other cases run
    learned_cfl_limit: float = 1.0
    #: Hydra overrides added to every run (both the truth and the learned law)
    overrides: List[str] = field(default_factory=list)
    #: a directory of ground-truth rollouts (truth/<case>.npz) to reuse; default: this run's
    truth_dir: str = ""
    #: instead of weights: the true law with these parameters (NCLaw's sys-id baseline), e.g. {E: 1.0e5}
    law_params: Dict[str, float] = field(default_factory=dict)
    #: a label for the evaluated weights in the table (default: ours, or ours-init without weights)
    label: str = ""
    #: trained weights of other materials, for the cases that mix materials (melting: {sand: FILE})
    partner_weights: Dict[str, str] = field(default_factory=dict)
    #: without weights: the Xavier seed of the untrained networks ("ours-init" of a training from that seed)
    init_seed: int = 0


register_task_schema("nclaw_eval", NclawEvalConfig)


def _plain(node):
    from omegaconf import DictConfig, ListConfig, OmegaConf

    return OmegaConf.to_container(node, resolve=True) if isinstance(node, (DictConfig, ListConfig)) else node


def resolve_cases(material: str, wanted) -> list:
    """The EvalCase list: names from ``eval_cases(material)`` ("all" = every one) or custom mappings."""
    from ..nclaw.scenes import EvalCase, eval_cases

    known = {c.name: c for c in eval_cases(material)}
    wanted = _plain(wanted) or []
    if wanted == ["all"] or wanted == "all":
        return list(known.values())
    out = []
    for i, c in enumerate(wanted):
        if isinstance(c, str):
            if c not in known:
                raise ConfigError(f"task.cases[{i}] = '{c}' is not an NCLaw case for {material}; choose from "
                                  f"{', '.join(known)} or 'all', or give {{name, scene, steps}}.")
            out.append(known[c])
        elif isinstance(c, dict):
            missing = [k for k in ("name", "scene", "steps") if k not in c]
            if missing:
                raise ConfigError(f"task.cases[{i}]: a custom case needs name, scene and steps (missing {missing}).")
            out.append(EvalCase(str(c["name"]), str(c["scene"]), tuple(c.get("overrides", ())), int(c["steps"]),
                                str(c.get("description", "custom case")), material,
                                frame_every=int(c.get("frame_every", 5)), tags=tuple(c.get("tags", ()))))
        else:
            raise ConfigError(f"task.cases[{i}] = {c!r}: give a case name or a mapping {{name, scene, steps}}.")
    if not out:
        raise ConfigError("task.cases is empty; give case names (e.g. [reconstruction]) or 'all'.")
    return out


def rollout(overrides: list[str], steps: int, every: int, cfl_floor: float | None = None, on_frame=None):
    """(positions [T, N, D] every ``every`` steps, wall time s, particles) of one composed run;
    ``cfl_floor`` raises the scene's ``cfl_limit`` to at least that; ``on_frame(i, numpy_state)`` sees
    every kept frame."""
    from omegaconf import open_dict

    from ..config import compose, stepper_from_config

    cfg = compose(overrides)
    if cfl_floor is not None:
        with open_dict(cfg):
            cfg.scene.cfl_limit = max(float(cfg.scene.get("cfl_limit", 0.5)), float(cfl_floor))
    _, stepper = stepper_from_config(cfg)
    t0 = time.perf_counter()
    traj = stepper.rollout(steps=steps, every=every, on_frame=on_frame)
    return np.asarray(traj.x), time.perf_counter() - t0, int(stepper.particles.count)


def run(cfg, ctx) -> dict:
    from .. import __version__
    from ..nclaw.scenes import MATERIALS

    t_task = time.perf_counter()
    out = Path(ctx.output_dir)
    tc = cfg.task
    material = str(tc.material)
    if material not in MATERIALS:
        raise ConfigError(f"task.material = '{material}': give the training material, one of {', '.join(MATERIALS)} "
                          f"(its true law is the ground truth).")
    weights = str(tc.weights or "")
    if weights and not Path(weights).is_file():
        raise ConfigError(f"task.weights = '{weights}' does not exist; give the nclaw_weights.safetensors of a "
                          f"task=nclaw_train run, or leave it empty for the untrained law (ours-init).")
    law_params = _plain(tc.law_params) or {}
    if law_params and weights:
        raise ConfigError("task.law_params (the true law refitted: sys-id) and task.weights (a learned nclaw) exclude "
                          "each other; give one.")
    label = str(tc.label or ("sys-id" if law_params else "ours" if weights else "ours-init"))
    cases = resolve_cases(material, tc.cases)
    partners = {str(k): str(v) for k, v in (_plain(tc.partner_weights) or {}).items()}
    for k, v in partners.items():
        if not Path(v).is_file():
            raise ConfigError(f"task.partner_weights.{k} = '{v}' does not exist; give the nclaw_weights.safetensors of "
                              f"the {k} training.")
    if (out / SUMMARY).exists() and not ctx.overwrite:
        raise ConfigError(f"{out / SUMMARY} exists; choose another hydra.run.dir or set output.overwrite=true.")
    write_config(out, cfg, True)
    common = [f"backend={cfg.backend.name}", f"transfer={cfg.transfer.name}", f"precision={cfg.precision.name}",
              "output.recording=false", *(_plain(tc.overrides) or [])]
    truth_dir = Path(tc.truth_dir) if tc.truth_dir else out / "truth"
    truth_dir.mkdir(parents=True, exist_ok=True)
    from tqdm.auto import tqdm

    trained = read_state_range(weights) if weights else None
    results, curves = {}, {}
    bar = tqdm(cases, disable=None if ctx.progress is None else not ctx.progress, unit="case", leave=False)
    for case in bar:
        bar.set_postfix_str(case.name)
        every = case.frame_every
        missing = [m for m in case.partners if weights and m not in partners]
        if missing or (law_params and case.partners):
            why = ("sys-id refits one material's law; this case mixes materials" if law_params else
                   f"it needs the trained weights of {', '.join(missing)} too (task.partner_weights.{missing[0]}=FILE)")
            results[case.name] = {"scene": case.scene, "steps": case.steps, "particles": None, "frame_every": every,
                                  "description": case.description, "truth_wall_s": None, "tags": list(case.tags),
                                  "status": "skipped", "mse": None, "message": why}
            log.warning("nclaw_eval %s: skipped: %s", case.name, why)
            continue
        cache = truth_dir / f"{case.name}_{cfg.backend.name}_{cfg.precision.name}.npz"
        if cache.exists():
            with np.load(cache) as z:
                xt, t_truth, n = z["x"], float(z["wall_s"]), int(z["x"].shape[1])
        else:
            xt, t_truth, n = rollout(case.truth() + common, case.steps, every)
            tmp = cache.with_name(cache.stem + ".tmp.npz")
            np.savez_compressed(tmp, x=xt, wall_s=t_truth)
            tmp.replace(cache)
        entry: dict[str, Any] = {"scene": case.scene, "steps": case.steps, "particles": n, "frame_every": every,
                                 "description": case.description, "truth_wall_s": t_truth, "tags": list(case.tags)}
        # the learned law's states (every RANGE_EVERY steps): where they leave its training's range, the
        # metric measures an extrapolation (benchmarks/nclaw.md, "WATER (c)", "JELL-O (c)")
        tracker = None if law_params else RangeTracker(every=max(1, RANGE_EVERY // every))
        on_frame = None if tracker is None else (lambda i, st: tracker.update(st["F"]) if "F" in st else None)
        try:
            learned = (case.truth() + [f"material.params.{k}={float(v)!r}" for k, v in law_params.items()]
                       if law_params else case.learned(weights or None, partners))
            if not weights and not law_params and int(tc.init_seed) != 0:
                learned = learned + [f"material.options.seed={int(tc.init_seed)}"]
            xl, t_learned, _ = rollout(learned + common, case.steps, every,
                                       None if law_params else float(tc.learned_cfl_limit), on_frame)
        except TimeStepError as exc:
            entry.update(status="refused", mse=None, message=str(exc).splitlines()[0])
            log.warning("nclaw_eval %s: the learned law's run was refused (%s)", case.name, entry["message"])
        except SimulationDiverged as exc:
            entry.update(status="diverged", mse=None, message=str(exc).splitlines()[0])
            log.warning("nclaw_eval %s: the learned law diverged (%s)", case.name, entry["message"])
        else:
            stride = case.metric_every
            d = (xl[::stride].astype(np.float64) - xt[::stride].astype(np.float64))
            per_frame = np.mean(d * d, axis=(1, 2))
            entry.update(status="ok", mse=case.mse(xl, xt), learned_wall_s=t_learned)
            curves[case.name] = (np.arange(len(per_frame)) * stride * every, per_frame)
            if "qualitative" in case.tags and cfg.output.plots:      # no number in the paper: show it
                _frames_plot(out / f"{case.name}_frames.png", xt, xl, every,
                             f"{case.name}: truth (top) and {label} (bottom), {cfg.backend.name}")
        if tracker is not None and tracker.range is not None:
            entry["state_range"] = tracker.range
            beyond = beyond_training(tracker.range, trained)
            if beyond:
                entry["beyond_training"] = beyond
                log.warning("nclaw_eval %s: the learned law left its training range: %s", case.name, "; ".join(beyond))
        results[case.name] = entry
    bar.close()

    table = _aggregate(results, PAPER.get(label, PAPER["ours"]).get(material, {}))
    summary = {"task": "nclaw_eval", "status": "ok", "material": material, "weights": weights or None,
               "law_params": law_params or None, "label": label,
               "backend": cfg.backend.name, "transfer": cfg.transfer.name, "precision": cfg.precision.name,
               "metric": "mean over frames 0, 5, 10, ... of the per-coordinate position MSE [m^2] (NCLaw Tabs. 1-2)",
               "cases": results, "table": table, "wall_time_s": None, "mpmlab_version": __version__,
               "overrides": list(ctx.job.get("overrides", []))}
    write_text(out / TABLE, _markdown(summary), True)
    if cfg.output.plots and curves:
        _plot(out / PLOT, curves, f"nclaw_eval {material} ({label}) on {cfg.backend.name}")
    summary["wall_time_s"] = float(time.perf_counter() - t_task)
    write_json(out / SUMMARY, summary, True)
    line = ", ".join(f"{k} {_fmt(v['mse'])}" for k, v in table.items())
    print(f"mpmlab: nclaw_eval {material} ({label}) {cfg.backend.name}: {line} -> {out}", flush=True)
    return summary


def _aggregate(results: dict, paper: dict) -> dict:
    """Tab. 1-2 rows: each case, and ``velocity`` = the mean over the seeds (Tab. 2 (b))."""
    table = {}
    for name, r in results.items():
        key = "velocity" if name.startswith("velocity_seed") else name
        if key == "velocity":
            continue
        table[name] = {"mse": r["mse"], "paper": paper.get(key), "ratio": _ratio(r["mse"], paper.get(key))}
    seeds = [r for k, r in results.items() if k.startswith("velocity_seed")]
    if seeds:
        vals = [r["mse"] for r in seeds]
        m = float(np.mean(vals)) if all(v is not None for v in vals) else None
        table["velocity"] = {"mse": m, "paper": paper.get("velocity"), "ratio": _ratio(m, paper.get("velocity")),
                             "seeds": len(seeds)}
    return table


def _ratio(a, b):
    return None if a is None or b is None else float(a / b)


def _fmt(v):
    return "n/a" if v is None else f"{v:.2e}"


def _markdown(s: dict) -> str:
    lines = [f"# NCLaw evaluation: {s['material']} ({s['label']}), {s['backend']}/{s['transfer']}/{s['precision']}", "",
             f"Metric: {s['metric']}. Weights: `{s['weights'] or 'the untrained initialisation'}`.", "",
             "| case | mpmlab | paper | mpmlab / paper |", "|---|---|---|---|"]
    for k, r in s["table"].items():
        ratio = "" if r["ratio"] is None else f"{r['ratio']:.2f}"
        lines.append(f"| {k} | {_fmt(r['mse'])} | {_fmt(r['paper'])} | {ratio} |")
    lines += ["", "| case | particles | steps | status | truth s | learned s | the learned law beyond its training range |",
              "|---|---|---|---|---|---|---|"]
    for k, r in s["cases"].items():
        tt, tl = r.get("truth_wall_s"), r.get("learned_wall_s")
        beyond = "; ".join(r.get("beyond_training", [])) or ("no" if "state_range" in r else "–")
        lines.append(f"| {k} | {r['particles'] if r['particles'] is not None else '–'} | {r['steps']} | {r['status']} | "
                     f"{'–' if tt is None else f'{tt:.1f}'} | {'–' if tl is None else f'{tl:.1f}'} | {beyond} |")
    return "\n".join(lines) + "\n"


def _frames_plot(path: Path, xt: np.ndarray, xl: np.ndarray, every: int, title: str, columns: int = 4,
                 max_points: int = 6000) -> None:
    """A qualitative case side by side: the truth's and the learned law's particles at ``columns``
    evenly spaced frames, seen along z (x right, y up: NCLaw's scenes have gravity along -y); at most
    ``max_points`` particles (the same ones in every panel)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    T, N = xt.shape[0], xt.shape[1]
    frames = np.unique(np.linspace(0, T - 1, columns).round().astype(int))
    pick = np.random.default_rng(0).choice(N, min(N, max_points), replace=False)
    both = np.concatenate([xt[frames][:, pick], xl[frames][:, pick]]).reshape(-1, xt.shape[2])
    both = both[np.all(np.isfinite(both), axis=1)]
    lo, hi = both[:, :2].min(0), both[:, :2].max(0)
    pad = 0.05 * float((hi - lo).max())
    fig, axes = plt.subplots(2, len(frames), figsize=(2.6 * len(frames), 5.4), squeeze=False)
    for row, (x, name) in enumerate(((xt, "truth"), (xl, "learned"))):
        for col, f in enumerate(frames):
            ax = axes[row, col]
            p = x[f][pick]
            colour = {"c": p[:, 2], "cmap": "viridis"} if p.shape[1] > 2 else {"c": "k"}    # 3D: depth
            ax.scatter(p[:, 0], p[:, 1], s=0.3, linewidths=0, **colour)
            ax.set_xlim(lo[0] - pad, hi[0] + pad); ax.set_ylim(lo[1] - pad, hi[1] + pad)
            ax.set_aspect("equal"); ax.set_xticks([]); ax.set_yticks([])
            ax.set_title(f"{name}, step {f * every}", fontsize=8)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    save_figure(fig, path, title)


def _plot(path: Path, curves: dict, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4))
    for name, (steps, mse) in curves.items():
        ax.semilogy(steps, np.maximum(mse, 1e-16), label=name)
    ax.set_xlabel("step"); ax.set_ylabel("position MSE per coordinate [m²]"); ax.set_title(title, fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, path, title)
