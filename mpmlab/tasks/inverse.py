"""``task=inverse``: fit rollout controls to observations (JAX-MPM Sec. 3.2 and 5).

Reads ``task.parameters`` (what to fit, see :mod:`mpmlab.inverse.parameters`), ``task.observation``
(an observation operator: ``{kind: lagrangian|eulerian, ...}``), the observation schedule, and either
generates reference observations from the parameters' ``truth`` or reads them from an HDF5 trajectory
(top-level ``input``). Optimiser and learning-rate schedule come from ``task.optimizer.<backend>`` /
``task.lr_schedule.<backend>`` (``_target_``: optax on JAX, torch.optim on Warp); the backend's autodiff
adapter (:mod:`mpmlab.core.autodiff`) instantiates them, so this task names no backend.

Outputs in the run directory: ``summary.json`` (truth, recovered, relative_error per parameter, epochs,
wall_time_s, loss history), ``fit.png`` (loss and parameter convergence), ``recording.rrd`` (loss and
parameters per epoch as rerun scalars), ``config.yaml`` and ``fit_checkpoint.*`` (resume: run the same
command with the same ``hydra.run.dir``).
"""
from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional

import numpy as np
from omegaconf import MISSING

from ..config import TaskConfig, register_task_schema
from ..config import build_scene, check_run_options, make_transfer_from_config, shape_options_from_config
from ..core.errors import ConfigError
from .common import RECORDING, SUMMARY, save_figure, write_config, write_json

log = logging.getLogger("mpmlab")
FIT_PLOT = "fit.png"


@dataclass
class FitParameterConfig:
    """One fitted quantity of ``task=inverse`` (see ``mpmlab.inverse.parameters``)."""

    #: initial_velocity | law | boundary | gravity | law_weights
    target: str = MISSING
    #: scalar | array | mlp
    form: str = "scalar"
    body: Optional[str] = None
    #: initial_velocity: x | y | z
    component: Optional[str] = None
    #: law: the parameter name
    param: Optional[str] = None
    #: boundary: its name under scene.boundaries, and its data (mu, friction); law_weights: the array name
    boundary: Optional[str] = None
    field: Optional[str] = None
    #: initial_velocity, form scalar: v = value * basis(x, y, z)
    basis: Optional[str] = None
    #: form mlp: input coordinates, hidden widths, activation (relu | tanh | softplus), weight seed
    inputs: List[str] = dataclasses.field(default_factory=lambda: ["y"])
    hidden: List[int] = dataclasses.field(default_factory=lambda: [30, 30, 30])
    activation: str = "relu"
    seed: int = 0
    #: starting value (physical units; a list for arrays)
    init: Optional[Any] = None
    #: the truth (value, list, or an expression of x, y, z and task.constants) for generated data
    truth: Optional[Any] = None
    #: identity | softplus | exp
    transform: str = "identity"


@dataclass
class InverseTaskConfig(TaskConfig):
    """Fit parameters to observations of a reference rollout (JAX-MPM Sec. 3.2, Eq. 28)."""

    name: str = "inverse"
    parameters: Dict[str, FitParameterConfig] = field(default_factory=dict)
    #: the observation operator: {kind: lagrangian, quantity: x, particles: 100} or {kind: eulerian, ...}
    observation: Dict[str, Any] = field(default_factory=lambda: {"kind": "lagrangian", "quantity": "x"})
    #: named observation presets of an experiment; ``observation: ${task.observations.${task.supervision}}``
    observations: Dict[str, Any] = field(default_factory=dict)
    supervision: Optional[str] = None
    #: observation steps: {steps: [...]}, {frames: F, every: K} (the last F frames, K steps apart) or
    #: {frames: F, spread: true} (evenly over the rollout)
    schedule: Dict[str, Any] = field(default_factory=lambda: {"frames": 10, "every": 10})
    #: Gaussian noise (std) added to the reference observations, and its seed
    noise: float = 0.0
    noise_seed: int = 0
    #: names usable in field expressions (e.g. H0)
    constants: Dict[str, float] = field(default_factory=dict)
    epochs: int = 100
    #: per backend: an optax transform (jax) / a torch.optim class (warp), by _target_
    optimizer: Dict[str, Any] = field(default_factory=dict)
    lr_schedule: Dict[str, Any] = field(default_factory=dict)
    #: used when the optimiser config sets no learning rate and no schedule is given
    learning_rate: float = 0.1
    #: steps per recomputed segment of the backward pass (memory O(steps / segment + segment))
    segment: int = 100
    checkpoint_every: int = 10
    #: a diverged epoch (gradient optimisers): stop (FitDiverged, exit 3) | backoff (step back one epoch and
    #: halve the updates, logged in the history, at most max_backoffs times)
    on_divergence: str = "stop"
    max_backoffs: int = 4
    #: continue from fit_checkpoint.* in the run directory if present
    resume: bool = True
    #: stop early once the loss is at or below this
    loss_tolerance: float = 0.0
    #: keep XLA CPU's YNNPACK fusions (JAX backend); off by default here because they make the
    #: backward pass ~2x slower (mpmlab/backends/jax/xla_options.py); XLA_FLAGS set by you wins
    jax_ynn_fusions: bool = False


register_task_schema("inverse", InverseTaskConfig)


def _plain(node):
    from omegaconf import DictConfig, ListConfig, OmegaConf

    return OmegaConf.to_container(node, resolve=True) if isinstance(node, (DictConfig, ListConfig)) else node


def schedule_from_config(tc, total_steps: int):
    from ..observations import ObservationSchedule

    s = _plain(tc.schedule) or {}
    noise, seed = float(tc.noise), int(tc.noise_seed)
    if s.get("steps") is not None:
        return ObservationSchedule(steps=tuple(int(a) for a in s["steps"]), noise=noise, seed=seed)
    frames, every = s.get("frames"), s.get("every")
    if frames is None:
        raise ConfigError("task.schedule needs 'steps' (a list) or 'frames' (+ 'every', or 'spread: true').")
    frames = int(frames)
    if s.get("spread"):
        if total_steps % frames:
            raise ConfigError(f"task.schedule: {frames} evenly spread frames need steps ({total_steps}) divisible by {frames}.")
        every = total_steps // frames
    if every is None:
        raise ConfigError("task.schedule: give 'every' (steps between frames) or 'spread: true'.")
    sch = ObservationSchedule.last_frames(total_steps, frames, int(every))
    return ObservationSchedule(steps=sch.steps, noise=noise, seed=seed)


def parameters_from_config(tc):
    from ..inverse.parameters import FitParameter

    consts = _plain(tc.constants) or {}
    out = []
    for name, p in (_plain(tc.parameters) or {}).items():
        p = {k: v for k, v in p.items() if v is not None}
        try:
            out.append(FitParameter(name=name, constants=consts, **p))
        except TypeError as exc:
            raise ConfigError(f"task.parameters.{name}: {exc}; check the option names.") from None
    if not out:
        raise ConfigError("task=inverse needs at least one entry under task.parameters.")
    return out


def reference_from_h5(path: str, observation, schedule, steps_total: int):
    """Observations of a stored trajectory at the schedule's steps (frames must exist there)."""
    from ..io.h5 import read_trajectory
    from ..observations import apply_numpy

    traj = read_trajectory(path)
    want = schedule.steps_array(steps_total)
    where = {int(s): k for k, s in enumerate(traj.step)}
    missing = [int(s) for s in want if int(s) not in where]
    if missing:
        raise ConfigError(f"input '{path}' has no frames at steps {missing[:5]}{'...' if len(missing) > 5 else ''}; "
                          f"store frames at the observation steps (frame_every) or change task.schedule.")
    ref = np.stack([apply_numpy(observation, {"x": traj.x[where[int(s)]], "v": traj.v[where[int(s)]]}) for s in want])
    return schedule.add_noise(ref)


def run(cfg, ctx) -> dict:
    from .. import __version__
    from ..core.autodiff import adapter_for_backend
    from ..inverse.fit import Fit
    from ..observations import make_observation
    from ..simulator import build_stepper

    t_task = time.perf_counter()
    out = Path(ctx.output_dir)
    check_run_options(cfg)
    tc = cfg.task
    scene = build_scene(cfg)
    transfer = make_transfer_from_config(cfg)
    shape_opts = shape_options_from_config(cfg, scene, transfer)
    backend, precision = cfg.backend.name, cfg.precision.name
    ad = adapter_for_backend(backend, precision)
    ad.before_build(tc)                     # JAX: XLA options that must precede the first computation
    steps = int(cfg.steps)
    observation = make_observation(_plain(tc.observation))
    schedule = schedule_from_config(tc, steps)
    schedule.steps_array(steps)
    params = parameters_from_config(tc)
    opt_node = tc.optimizer.get(backend) if tc.optimizer is not None else None
    if opt_node is None:
        raise ConfigError(f"task.optimizer has no entry for backend '{backend}'; add task.optimizer.{backend}._target_.")
    sched_node = tc.lr_schedule.get(backend) if tc.lr_schedule is not None else None
    lm_class = _levenberg_marquardt_class(opt_node)
    if lm_class is not None:                # no learning rate: the schedule does not apply
        options = {k: v for k, v in _plain(opt_node).items() if k != "_target_"}
        try:
            optimizer, sched = lm_class(**options), None
        except TypeError as exc:
            raise ConfigError(f"task.optimizer.{backend}: {exc}; the options are those of "
                              f"mpmlab.inverse.lm.LevenbergMarquardt.") from None
    else:                   # optax (the schedule is the learning rate) or torch.optim (a scheduler wraps it)
        optimizer, sched = ad.optimizer_from_config(opt_node, sched_node, tc.learning_rate)
    ckpt = out / f"fit_checkpoint.{ad.checkpoint_suffix}"
    if (out / SUMMARY).exists() and not ctx.overwrite and not (tc.resume and ckpt.exists()):
        raise ConfigError(f"{out / SUMMARY} exists; choose another hydra.run.dir or set output.overwrite=true.")
    write_config(out, cfg, True)

    stepper = build_stepper(scene, backend, transfer, precision, **shape_opts)
    for p in params:
        p.bind(scene, stepper, list(scene_boundary_names(cfg)))
    fit = Fit(stepper, scene, params, observation, schedule, segment=int(tc.segment))
    if cfg.input:
        fit.reference = reference_from_h5(str(cfg.input), observation, schedule, steps)
    t0 = time.perf_counter()
    ref = fit.reference if fit.reference is not None else fit.make_reference()
    ref_time = time.perf_counter() - t0
    log.info("inverse: %s on %s/%s/%s, %d particles, %d steps, %d observation frames x %d indices, fitting %s",
             scene.name, backend, transfer.name, precision, stepper.particles.count, steps, ref.shape[0], ref.shape[1],
             ", ".join(p.name for p in params))

    rec = _Recorder(out / RECORDING, f"inverse-{scene.name}-{out.name}") if cfg.output.recording else None
    try:
        raw = fit.run(int(tc.epochs), optimizer, sched, checkpoint=ckpt, checkpoint_every=int(tc.checkpoint_every),
                      resume=bool(tc.resume), progress=ctx.progress,
                      on_epoch=rec.log if rec is not None else None, tolerance=float(tc.loss_tolerance),
                      on_divergence=str(tc.on_divergence), max_backoffs=int(tc.max_backoffs))
    finally:
        if rec is not None:
            rec.close()
    report = fit.report(raw)
    summary = {
        "task": "inverse", "status": "ok", "scene": scene.name, "resolution": str(cfg.scene.resolution),
        "backend": backend, "transfer": transfer.name, "precision": precision,
        "particles": int(stepper.particles.count), "steps": steps, "dt": float(stepper.dt),
        "observation": {"kind": observation.name, **{k: v for k, v in _plain(tc.observation).items() if k != "kind"}},
        "observation_frames": int(ref.shape[0]), "observed_indices": int(ref.shape[1]),
        "truth": {k: v.get("truth", v.get("truth_field_rms")) for k, v in report.items()},
        "recovered": {k: v.get("recovered", v.get("recovered_field_rms")) for k, v in report.items()},
        "relative_error": {k: v.get("relative_error") for k, v in report.items()},
        "parameters": report,
        "profiles": fit.profiles(raw),
        "optimizer": str(opt_node.get("_target_")),
        "stopped": fit.lm_stop,
        "epochs": int(fit.epoch),
        "final_loss": float(fit.final_loss),
        "initial_loss": float(fit.history[0]["loss"]) if fit.history else None,
        "reference_time_s": float(ref_time),
        "history": fit.history,
        "wall_time_s": None,
        "mpmlab_version": __version__,
        "overrides": list(ctx.job.get("overrides", [])),
    }
    summary["weight_files"] = _write_law_weights(out, fit, raw)
    if cfg.output.plots:
        plot_fit(out / FIT_PLOT, fit.history, report, summary["profiles"], f"{scene.name}: {backend}/{transfer.name}")
    summary["wall_time_s"] = float(time.perf_counter() - t_task)
    write_json(out / SUMMARY, summary, True)
    errs = ", ".join(f"{k} {_fmt(v)}" for k, v in summary["relative_error"].items())
    print(f"mpmlab: inverse {scene.name} {backend}: {fit.epoch} epochs in {summary['wall_time_s']:.1f} s, "
          f"loss {summary['initial_loss']:.3e} -> {summary['final_loss']:.3e}; relative error: {errs} -> {out}", flush=True)
    return summary


def _write_law_weights(out: Path, fit, raw) -> dict[str, str]:
    """Fitted shared law weights, one safetensors file per material group whose weights were fitted
    (``law_weights_<law>.safetensors``, all of the group's arrays): the file both backends read, e.g.
    through the law's ``weights_file`` option. Returns ``{law: file name}``."""
    groups = sorted({p._index for p in fit.parameters if p.target == "law_weights"})
    if not groups:
        return {}
    from safetensors.numpy import save_file

    from ..io.files import write_atomically

    controls = fit.controls_of(raw)
    files = {}
    for g in groups:
        law = fit.stepper.groups[g].law
        arrays = {k: np.ascontiguousarray(fit.adapter.numpy(a), dtype=np.float64)
                  for k, a in controls["law_weights"][g].items()}
        name = f"law_weights_{law.name}.safetensors"
        # the run directory was checked before the fit (summary.json guard), so a resumed run replaces it
        meta = law.weights_metadata(fit.stepper.dim) or None     # e.g. nclaw's dim, variant, alpha
        write_atomically(out / name, lambda tmp, arrays=arrays, meta=meta: save_file(arrays, str(tmp), metadata=meta),
                         overwrite=True)
        files[law.name] = name
    return files


def _levenberg_marquardt_class(opt_node):
    """The optimiser's class when it is mpmlab's LevenbergMarquardt (or a subclass), else None."""
    from ..inverse.lm import LevenbergMarquardt

    target = opt_node.get("_target_") if hasattr(opt_node, "get") else None
    # hydra.utils.get_class logs "[hydra.utils][ERROR] Error getting class" for a function such as
    # optax.adam before raising; look the target up quietly (as instantiate() does) and test its type
    try:
        from hydra._internal.utils import _locate
    except ImportError:     # pragma: no cover - a Hydra without it: the same lookup by import
        from ..core.registry import load_object as _locate
    try:
        cls = _locate(str(target)) if target else None
    except Exception:       # a misspelled target: instantiate() reports it with Hydra's message
        return None
    return cls if isinstance(cls, type) and issubclass(cls, LevenbergMarquardt) else None


def scene_boundary_names(cfg):
    """Config names of the enabled boundaries, in the scene's order."""
    return [name for name, b in cfg.scene.boundaries.items() if b.enabled] if not cfg.scene.builder else []


def _fmt(v):
    if v is None:
        return "n/a"
    if isinstance(v, list):
        return "[" + ", ".join(f"{a:.2%}" for a in v) + "]"
    return f"{v:.2%}"


class _Recorder:
    """Loss and parameter values per epoch as rerun scalars (timeline ``epoch``: ``metrics/loss``,
    ``metrics/<parameter>[/k]``), written atomically, in a blueprint made for a fit: log10 and linear
    loss, one plot per parameter (``mpmlab.io.rerun.EpochRecorder``). The recording id gets a unique
    suffix, so two fits opened at once stay apart in the viewer."""

    def __init__(self, path: Path, recording_id: str):
        from ..io.rerun import EpochRecorder, unique_recording_id

        self.path = path
        self.rec = EpochRecorder(path, unique_recording_id(recording_id), title="inverse fit", overwrite=True)

    def log(self, epoch, loss, values):
        self.rec.log(epoch, loss, values)

    def close(self):
        self.rec.close()


def plot_fit(path: Path, history, report, profiles, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scalars = {k: v for k, v in report.items() if "truth" in v or "recovered" in v}
    n = 1 + (1 if history and history[0]["values"] else 0) + len(profiles)
    fig, axs = plt.subplots(1, n, figsize=(5 * n, 3.8), squeeze=False)
    ax = axs[0, 0]
    ax.semilogy([h["epoch"] for h in history], [h["loss"] for h in history])
    ax.set_xlabel("epoch"); ax.set_ylabel("loss (mean squared residual)"); ax.set_title("loss")
    k = 1
    if history and history[0]["values"]:
        ax = axs[0, k]; k += 1
        for name in history[0]["values"]:
            vals = np.array([np.asarray(h["values"][name], float).reshape(-1) for h in history])
            truth = np.asarray(scalars.get(name, {}).get("truth", np.nan), float).reshape(-1)
            for j in range(vals.shape[1]):
                lab = name if vals.shape[1] == 1 else f"{name}[{j}]"
                line, = ax.plot([h["epoch"] for h in history], vals[:, j], label=lab)
                if j < truth.size and np.isfinite(truth[j]):
                    ax.axhline(truth[j], color=line.get_color(), ls="--", lw=0.8)
        ax.set_xlabel("epoch"); ax.set_title("parameters (dashed: truth)"); ax.legend(fontsize=7)
    for name, pr in profiles.items():
        ax = axs[0, k]; k += 1
        ax.plot(pr["recovered"], pr["at"], label="recovered")
        if "truth" in pr:
            ax.plot(pr["truth"], pr["at"], "k--", label="truth")
        ax.set_ylabel(pr["coordinate"]); ax.set_xlabel(name); ax.legend(fontsize=7); ax.set_title(f"{name} profile")
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    save_figure(fig, path, title)
