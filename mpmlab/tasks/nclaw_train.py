"""``task=nclaw_train``: learn a neural constitutive law from one trajectory (NCLaw, Ma et al. 2023,
Sec. 3.4 and App. D.2), on either backend.

    mpmlab -m experiment=nclaw_datasets                       # the four ground-truth trajectories
    mpmlab task=nclaw_train scene=nclaw_jelly material=nclaw task.dataset=PATH/trajectory.h5

The scene is the training scene with the learned law (``material=nclaw``); the dataset is that
scene's ground-truth rollout with x, v, C and F at every step (``experiment=nclaw_datasets``). One
epoch is one teacher-forced pass over the trajectory (:mod:`mpmlab.inverse.teacher`) and one Adam
step per network: the release's schedule is the default (300 epochs, lr 1.0 elastic / 0.1 plastic,
cosine to 0, gradient norm clipped to 0.1 per network, period 25 -> 200 steps, whole-state reset).

Outputs in the run directory: ``nclaw_weights.safetensors`` (the trained law; both backends read it
through ``material.options.weights_file``), ``train_checkpoint.*`` (every ``checkpoint_every``
epochs: rerun the same command with the same ``hydra.run.dir`` to resume), ``recording.rrd`` (loss,
period, learning rates and gradient norms per epoch), ``train.png`` and ``summary.json``.
"""
from __future__ import annotations

import logging
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict

import numpy as np

from ..config import TaskConfig, register_task_schema
from ..config import build_scene, check_run_options, make_transfer_from_config, shape_options_from_config
from ..core.errors import ConfigError
from .common import RECORDING, SUMMARY, save_figure, write_config, write_json

log = logging.getLogger("mpmlab")
WEIGHTS = "nclaw_weights.safetensors"
PLOT = "train.png"
#: each network's weight names start with its prefix (mpmlab.laws.nclaw: e_W1 ... p_b3)
NETS = {"elastic": "e_", "plastic": "p_"}


@dataclass
class NclawTrainConfig(TaskConfig):
    """Train the ``nclaw`` law of the scene on a ground-truth trajectory by teacher forcing."""

    name: str = "nclaw_train"
    #: teacher (through the simulator, NCLaw's method) | labeled (the nets fitted to the dataset's
    #: (F, tau) and (F_n, C_n+1 -> F_n+1) pairs: NCLaw's "labeled" baseline, mpmlab.nclaw.baselines) |
    #: sysid (the scene's own law family, its parameters fitted by the same teacher forcing from E^0.8,
    #: 0.8 sigma_y, 0.8 phi: NCLaw's "sys-id"; run with the true material, not material=nclaw)
    method: str = "teacher"
    #: sysid: Adam on the log of the true law's parameters (mpmlab's choice; the paper gives none)
    sysid: Dict[str, Any] = field(default_factory=lambda: {"lr": 0.1, "clip": None})
    #: labeled: epochs, batch size, learning rate (the release's supervised.yaml: 30, 1000, 0.1) and frame stride
    labeled: Dict[str, Any] = field(default_factory=lambda: {"epochs": 30, "batch": 1000, "lr": 0.1, "stride": 1})
    #: the ground-truth trajectory.h5 (x, v, C, F at every step: experiment=nclaw_datasets)
    dataset: str = ""
    epochs: int = 300
    #: per network: Adam learning rate and gradient-norm clip (null: none)
    nets: Dict[str, Any] = field(default_factory=lambda: {"elastic": {"lr": 1.0, "clip": 0.1},
                                                          "plastic": {"lr": 0.1, "clip": 0.1}})
    #: cosine (to 0 over the epochs, NCLaw) | constant
    lr_schedule: str = "cosine"
    #: teacher forcing: the period from ``start`` (epoch 0) to ``end`` (last epoch) steps, and what a
    #: reset restores: [x, v, C, F] (the release) or [x, v] (kinematics only)
    teacher: Dict[str, Any] = field(default_factory=lambda: {"start": 25.0, "end": 200.0, "reset": ["x", "v", "C", "F"]})
    #: back-propagate this random fraction of the segments per epoch (rescaled: unbiased, cheaper)
    segment_fraction: float = 1.0
    #: weight of the velocity term (NCLaw Tab. 7; 0: the release's position-only loss)
    velocity_weight: float = 0.0
    #: seed of the segment draws (segment_fraction < 1)
    seed: int = 0
    #: steps per recomputed segment of a backward pass (memory; not the teacher-forcing segments)
    segment: int = 100
    checkpoint_every: int = 1
    #: a diverged epoch: stop (FitDiverged, exit 3) | backoff (step back one epoch and halve the learning
    #: rates, logged in the history, at most max_backoffs times; the release instead zeroes NaN gradients)
    on_divergence: str = "backoff"
    max_backoffs: int = 4
    #: continue from train_checkpoint.* in the run directory if present
    resume: bool = True
    #: stop this run (checkpointed; the same command continues) after this many epochs / seconds (0: no limit)
    stop_after_epochs: int = 0
    stop_after_s: float = 0.0
    #: keep XLA CPU's YNNPACK fusions (JAX; they make backward passes ~2x slower)
    jax_ynn_fusions: bool = False


register_task_schema("nclaw_train", NclawTrainConfig)


def _plain(node):
    from omegaconf import DictConfig, ListConfig, OmegaConf

    return OmegaConf.to_container(node, resolve=True) if isinstance(node, (DictConfig, ListConfig)) else node


def nclaw_group(stepper):
    """(index, group) of the scene's one ``nclaw`` material group."""
    found = [(i, g) for i, g in enumerate(stepper.groups) if g.law.name == "nclaw"]
    if len(found) != 1:
        laws = sorted({g.law.name for g in stepper.groups})
        raise ConfigError(f"task=nclaw_train trains one nclaw body; scene '{stepper.scene.name}' has laws {laws}: "
                          f"add material=nclaw (one body).")
    return found[0]


def load_truth(path: str, stepper, steps: int) -> dict[str, np.ndarray]:
    """x, v, C, F [steps + 1, N, ...] of a ground-truth dataset (``mpmlab.nclaw.data.load_dataset``: every
    step, all four fields; J = det F too when a law of the scene carries J), checked against the scene:
    particle count, dt, length, first positions."""
    from ..nclaw.data import load_dataset

    ds = load_dataset(path)
    n, name = stepper.particles.count, stepper.scene.name
    if ds.n != n:
        raise ConfigError(f"dataset '{path}' has {ds.n} particles, scene '{name}' has {n}: it was made for another "
                          f"scene (its scene: '{ds.scene}'); rerun experiment=nclaw_datasets for this one.")
    ds.check_matches(dt=float(stepper.dt))
    if ds.steps < steps:
        raise ConfigError(f"dataset '{path}' has {ds.steps} steps; the training needs {steps} (scene.steps).")
    x0 = stepper.particles.x
    if not np.allclose(ds.x[0], x0, atol=1e-5 * max(1.0, float(np.abs(x0).max()))):
        raise ConfigError(f"dataset '{path}' (scene '{ds.scene}'): its first frame's positions are not the particles of "
                          f"scene '{name}' (another sampling or body); rerun experiment=nclaw_datasets with this scene.")
    out = {"x": ds.x, "v": ds.v, "C": ds.C, "F": ds.F}
    if any("J" in g.law.state_fields for g in stepper.groups):      # a J-state law (WATER's sys-id) resets J
        out["J"] = np.linalg.det(ds.F)
    return out


def run(cfg, ctx) -> dict:
    from .. import __version__
    from ..core.autodiff import adapter_for_backend
    from ..core.resume import array_digest, array_fingerprint
    from ..inverse.parameters import FitParameter
    from ..inverse.teacher import TeacherForcedFit, TeacherForcing
    from ..simulator import build_stepper

    t_task = time.perf_counter()
    out = Path(ctx.output_dir)
    check_run_options(cfg)
    tc = cfg.task
    if not tc.dataset:
        raise ConfigError("task=nclaw_train needs task.dataset=PATH/trajectory.h5 (the ground truth: "
                          "mpmlab -m experiment=nclaw_datasets).")
    scene = build_scene(cfg)
    transfer = make_transfer_from_config(cfg)
    shape_opts = shape_options_from_config(cfg, scene, transfer)
    backend, precision = cfg.backend.name, cfg.precision.name
    ad = adapter_for_backend(backend, precision)
    ad.before_build(tc)
    steps = int(cfg.steps)
    teacher = _plain(tc.teacher) or {}
    unknown = sorted(set(teacher) - {"start", "end", "reset"})
    if unknown:
        raise ConfigError(f"task.teacher: unknown option(s) {unknown}; use start, end, reset.")
    forcing = TeacherForcing(steps=steps, start=float(teacher.get("start", 25.0)), end=float(teacher.get("end", 200.0)),
                             reset=tuple(teacher.get("reset", ("x", "v", "C", "F"))))
    nets = _plain(tc.nets) or {}
    bad = sorted(set(nets) - set(NETS))
    if (bad or not nets) and str(tc.method) != "sysid":
        raise ConfigError(f"task.nets: {bad or 'none'}; give elastic and/or plastic, each {{lr, clip}}.")
    ckpt = out / f"train_checkpoint.{ad.checkpoint_suffix}"
    if (out / SUMMARY).exists() and not ctx.overwrite and not (tc.resume and ckpt.exists()):
        raise ConfigError(f"{out / SUMMARY} exists; choose another hydra.run.dir or set output.overwrite=true.")

    stepper = build_stepper(scene, backend, transfer, precision, **shape_opts)
    method = str(tc.method)
    if method not in ("teacher", "labeled", "sysid"):
        raise ConfigError(f"task.method = '{method}': use teacher (NCLaw's training), labeled or sysid (its baselines).")
    if method == "sysid":
        group = _one_group(stepper)
    else:
        gi, group = nclaw_group(stepper)
    if method == "labeled":
        return _run_labeled(cfg, ctx, out, tc, scene, stepper, group, steps, t_task)
    truth = load_truth(str(tc.dataset), stepper, steps)
    body = scene.bodies[int(stepper.particles.body_id[group.start])].name
    params, groups = [], {}
    if method == "sysid":
        params, nets = _sysid_parameters(group, body), {"law": _plain(tc.sysid) or {"lr": 0.1, "clip": None}}
        groups = {"law": [p.name for p in params]}
    for label, prefix in NETS.items():
        if label not in nets or method == "sysid":
            continue
        names = [k for k in group.weights if k.startswith(prefix)]
        groups[label] = names
        params += [FitParameter(name=k, target="law_weights", field=k, form="array", body=body) for k in names]
    for p in params:
        p.bind(scene, stepper, [])
    write_config(out, cfg, True)
    fit = TeacherForcedFit(stepper, scene, params, truth, forcing, epochs=int(tc.epochs),
                           segment_fraction=float(tc.segment_fraction), velocity_weight=float(tc.velocity_weight),
                           seed=int(tc.seed), groups=groups, segment=int(tc.segment))
    optimizer, sched = fit.optimizer({k: nets[k] for k in groups}, str(tc.lr_schedule))
    log.info("nclaw_train: %s on %s/%s/%s, %d particles, %d steps, %d epochs, nets %s, reset %s, segment_fraction %g",
             scene.name, backend, transfer.name, precision, stepper.particles.count, steps, int(tc.epochs),
             ", ".join(groups), list(forcing.reset), float(tc.segment_fraction))

    rec = _recorder(out, cfg, scene.name) if cfg.output.recording else None

    def record(h):
        scalars = {"period": h["period"], "segments": h["segments"]}
        scalars.update({f"lr/{k}": v for k, v in h["lr"].items()})
        scalars.update({f"grad_norm/{k}": v for k, v in h["grad_norms"].items()})
        rec.log(h["epoch"], h["loss"], scalars)

    def on_epoch(epoch, loss, values):
        if rec is None:
            return
        if not recorded[0]:              # a resumed run: the epochs before it, from the checkpoint, first
            for h in fit.history[:-1]:
                record(h)
            recorded[0] = True
        record(fit.history[-1])
    recorded = [False]

    t_run, first = time.perf_counter(), [None]

    def stop():
        if first[0] is None:
            first[0] = fit.epoch - 1          # the epoch this run started at (after a resume: later)
        ran = fit.epoch - first[0]
        return ((int(tc.stop_after_epochs) > 0 and ran >= int(tc.stop_after_epochs))
                or (float(tc.stop_after_s) > 0 and time.perf_counter() - t_run >= float(tc.stop_after_s)))
    # what a resume must share with the run that wrote the checkpoint (mpmlab.core.resume): the data, and
    # every option that shapes the curve (stop_after_*, checkpoint_every and progress do not)
    data = [truth[k] for k in sorted(truth)]
    identity = {"dataset": array_digest(*data), "dataset_fingerprint": array_fingerprint(*data), "method": method,
                "scene": scene.name, "steps": steps, "transfer": transfer.name, "precision": precision,
                "material": _plain(cfg.material), "epochs": int(tc.epochs), "nets": {k: nets[k] for k in groups},
                "lr_schedule": str(tc.lr_schedule),
                "teacher": {"start": forcing.start, "end": forcing.end, "reset": list(forcing.reset)},
                "segment_fraction": float(tc.segment_fraction), "velocity_weight": float(tc.velocity_weight),
                "seed": int(tc.seed), "segment": int(tc.segment)}
    try:
        raw = fit.run(int(tc.epochs), optimizer, sched, checkpoint=ckpt, checkpoint_every=int(tc.checkpoint_every),
                      resume=bool(tc.resume), progress=ctx.progress, on_epoch=on_epoch, identity=identity,
                      on_checkpoint=(None if method == "sysid" else lambda raw: _write_law_weights_as(out, fit, raw)),
                      stop=stop, on_divergence=str(tc.on_divergence), max_backoffs=int(tc.max_backoffs))
    finally:
        if rec is not None:
            rec.close()
    weights = None if method == "sysid" else _write_law_weights_as(out, fit, raw)
    state_range = (_record_state_range(out, fit.stepper, fit.adapter, fit.controls_of(raw), group, steps, backend)
                   if weights else None)
    hist = fit.history
    times = np.diff([0.0] + [h["time_s"] for h in hist]) if hist else np.array([])
    summary = {
        "task": "nclaw_train", "status": "partial" if fit.epoch < int(tc.epochs) else "ok", "scene": scene.name, "backend": backend, "transfer": transfer.name,
        "precision": precision, "particles": int(stepper.particles.count), "steps": steps, "dt": float(stepper.dt),
        "method": method, "dataset": str(tc.dataset), "weights": weights,
        "law": group.law.weights_metadata(stepper.dim) if method != "sysid" else {"law": group.law.name},
        "parameters": fit.report(raw) if method == "sysid" else None,
        "state_range": state_range,
        "epochs": int(fit.epoch), "epochs_planned": int(tc.epochs),
        "nets": {k: nets[k] for k in groups}, "lr_schedule": str(tc.lr_schedule),
        "teacher": {"start": forcing.start, "end": forcing.end, "reset": list(forcing.reset)},
        "segment_fraction": float(tc.segment_fraction), "velocity_weight": float(tc.velocity_weight),
        "resume_notes": list(fit.resume_notes),
        "initial_loss": float(hist[0]["loss"]) if hist else None,
        "backoffs": [dict(h["backoff"], resumed_at=h["epoch"], lr_scale=h["lr_scale"]) for h in hist if "backoff" in h],
        "final_loss": float(fit.final_loss),
        "final_loss_note": "the full teacher-forced loss (every segment) at the last epoch's period",
        "seconds_per_epoch": float(np.median(times[1:])) if len(times) > 1 else (float(times[0]) if len(times) else None),
        "history": hist,
        "wall_time_s": None,
        "mpmlab_version": __version__,
        "overrides": list(ctx.job.get("overrides", [])),
    }
    if cfg.output.plots and hist:
        plot_training(out / PLOT, hist, f"{scene.name}: nclaw on {backend}/{transfer.name}/{precision}")
    summary["wall_time_s"] = float(time.perf_counter() - t_task)
    write_json(out / SUMMARY, summary, True)
    more = (f" (stopped at epoch {fit.epoch} of {int(tc.epochs)}: rerun the same command to continue)"
            if fit.epoch < int(tc.epochs) else "")
    result = (f"weights {out / WEIGHTS}" if weights else "recovered " + ", ".join(
        f"{k} {v['recovered']:.4g} (truth {v['truth']:.4g})" for k, v in summary["parameters"].items()))
    print(f"mpmlab: nclaw_train {scene.name} {backend}: {fit.epoch} epochs{more} in {summary['wall_time_s']:.1f} s, loss "
          f"{summary['initial_loss']:.3e} -> {summary['final_loss']:.3e}; {result}", flush=True)
    return summary


#: NCLaw's sys-id start (the release's ``random: True``): log E scaled by 0.8 (E^0.8), the rest x 0.8
SYSID_START = {"E": "power", "bulk_modulus": "power", "yield_stress": "scale", "friction_angle": "scale"}


def _one_group(stepper):
    if len(stepper.groups) != 1:
        raise ConfigError(f"task.method=sysid fits one body's law; scene '{stepper.scene.name}' has "
                          f"{len(stepper.groups)} material groups.")
    g = stepper.groups[0]
    if g.law.name == "nclaw":
        raise ConfigError("task.method=sysid fits the true law family: use the dataset's material "
                          "(e.g. material=jelly), not material=nclaw.")
    return g


def _sysid_parameters(group, body):
    """FitParameters of the law's fitted parameters, started as NCLaw's sys-id (log-parametrised)."""
    from ..inverse.parameters import FitParameter

    names = group.law.param_names()
    truth = {n: float(np.asarray(group.params)[0, i]) for i, n in enumerate(names)}
    out = []
    for n, rule in SYSID_START.items():
        if n in truth:
            t = truth[n]
            start = math.exp(0.8 * math.log(t)) if rule == "power" else 0.8 * t
            out.append(FitParameter(name=n, target="law", param=n, form="scalar", transform="exp", init=start,
                                    truth=t, body=body))
    if not out:
        raise ConfigError(f"task.method=sysid: law '{group.law.name}' has none of the parameters NCLaw's sys-id "
                          f"fits ({', '.join(SYSID_START)}).")
    return out


def _run_labeled(cfg, ctx, out, tc, scene, stepper, group, steps, t_task) -> dict:
    """NCLaw's "labeled" baseline: fit the nets to the dataset's constitutive pairs (no rollout)."""
    from .. import __version__
    from ..laws.nclaw import save_weights
    from ..nclaw.baselines import fit_labeled, labeled_pairs
    from ..nclaw.data import load_dataset

    load_truth(str(tc.dataset), stepper, steps)                 # the same checks as a teacher-forced run
    ds = load_dataset(str(tc.dataset))
    opts = {"epochs": 30, "batch": 1000, "lr": 0.1, "stride": 1, **(_plain(tc.labeled) or {})}
    unknown = sorted(set(opts) - {"epochs", "batch", "lr", "stride"})
    if unknown:
        raise ConfigError(f"task.labeled: unknown option(s) {unknown}; use epochs, batch, lr, stride.")
    write_config(out, cfg, True)
    pairs = labeled_pairs(ds, stride=int(opts["stride"]))
    weights, report = fit_labeled(group.law, stepper.dim, pairs, ds.dt, epochs=int(opts["epochs"]),
                                  batch=int(opts["batch"]), lr=float(opts["lr"]), seed=int(tc.seed),
                                  progress=ctx.progress)
    from ..io.files import write_atomically

    write_atomically(out / WEIGHTS, lambda tmp: save_weights(str(tmp), weights, group.law, dim=stepper.dim),
                     overwrite=True)
    # the fitted law rolled out on the training scene: its range, for the divergence note, as a teacher run's
    from ..core.autodiff import adapter

    ad = adapter(stepper)
    controls = stepper.controls()
    gi = next(i for i, g in enumerate(stepper.groups) if g is group)
    controls["law_weights"] = list(controls["law_weights"])
    controls["law_weights"][gi] = {k: ad.asarray(np.asarray(a)) for k, a in weights.items()}
    state_range = _record_state_range(out, stepper, ad, controls, group, steps, cfg.backend.name)
    summary = {"task": "nclaw_train", "method": "labeled", "status": "ok", "scene": scene.name, "state_range": state_range,
               "particles": int(stepper.particles.count), "dataset": str(tc.dataset), "weights": WEIGHTS,
               "law": group.law.weights_metadata(stepper.dim), "labeled": report, "true_law": ds.laws[0]["law"],
               "wall_time_s": float(time.perf_counter() - t_task), "mpmlab_version": __version__,
               "overrides": list(ctx.job.get("overrides", []))}
    write_json(out / SUMMARY, summary, True)
    print(f"mpmlab: nclaw_train (labeled) {scene.name}: elastic loss {report['e']['loss_initial']:.3e} -> "
          f"{report['e']['loss_final']:.3e}, plastic {report['p']['loss_initial']:.3e} -> {report['p']['loss_final']:.3e} "
          f"(relative MSE) in {summary['wall_time_s']:.1f} s; weights {out / WEIGHTS}", flush=True)
    return summary


def _write_law_weights_as(out: Path, fit, raw) -> str:
    """The trained law as ``nclaw_weights.safetensors`` (atomic; replaced at every checkpoint)."""
    from .inverse import _write_law_weights

    files = _write_law_weights(out, fit, raw)
    os.replace(out / files["nclaw"], out / WEIGHTS)
    return WEIGHTS


def _record_state_range(out: Path, stepper, ad, controls, group, steps: int, backend: str) -> dict:
    """The states the trained law visits on its own training scene, rolled out freely (no teacher
    forcing; ``mpmlab.nclaw.probe.state_range`` of every 10th frame of its particles' F), written into
    the weight file's metadata (``state_range``), where the law's divergence note reads it: a run that
    fails outside this range says so (benchmarks/nclaw.md, "WATER (c)"). A rollout that diverges
    records where."""
    import contextlib

    from ..core.errors import SimulationDiverged
    from ..nclaw.probe import state_range, write_state_range
    from ..observations import ParticleState

    D = stepper.dim
    frames = list(range(10, steps + 1, 10)) or [steps]
    quiet = contextlib.nullcontext()
    if backend == "warp":
        import torch

        quiet = torch.no_grad()
    try:
        with quiet:
            y, invalid = ad.observe(stepper, controls, ParticleState(quantity="F"), frames)
        F = ad.numpy(y).reshape(len(frames), -1, D, D)[:, group.start:group.stop]
        rng = state_range(F) if not bool(np.asarray(invalid).any()) else {"diverged": True}
    except SimulationDiverged as e:
        rng = {"diverged": True, "step": int(e.step)}
    rng["rollout"] = f"the training scene, {steps} steps, no teacher forcing, every 10th frame"
    write_state_range(out / WEIGHTS, rng)
    return rng


def _recorder(out: Path, cfg, scene_name: str):
    from ..io.rerun import EpochRecorder, unique_recording_id

    return EpochRecorder(out / RECORDING, unique_recording_id(f"nclaw_train-{scene_name}-{out.name}"),
                         title="NCLaw training", overwrite=True, units={"period": "steps"})


def plot_training(path: Path, history, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    e = [h["epoch"] for h in history]
    fig, axs = plt.subplots(1, 3, figsize=(14, 3.8))
    axs[0].semilogy(e, [h["loss"] for h in history])
    axs[0].set_xlabel("epoch"); axs[0].set_title("teacher-forced loss")
    ax2 = axs[1]
    for k in history[0]["lr"]:
        ax2.plot(e, [h["lr"][k] for h in history], label=f"lr {k}")
    ax2.set_xlabel("epoch"); ax2.set_title("learning rate"); ax2.legend(fontsize=7)
    tw = ax2.twinx()
    tw.plot(e, [h["period"] for h in history], "k--", lw=0.8)
    tw.set_ylabel("period [steps] (dashed)")
    for k in history[0]["grad_norms"]:
        axs[2].semilogy(e, [max(h["grad_norms"][k], 1e-30) for h in history], label=k)
    axs[2].set_xlabel("epoch"); axs[2].set_title("gradient norm (before clipping)"); axs[2].legend(fontsize=7)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    save_figure(fig, path, title)
