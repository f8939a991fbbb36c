"""``task=rom_train``: the deformation-map ROM's offline stage (Chen et al. 2023, Sec. 4.2, Eq. 24,
App. B) on a study's full-order snapshots (``mpmlab.rom.snapshots``):

    mpmlab -m experiment=rom_snapshots_torsion hydra.sweep.dir=data/torsion     # the FOM snapshots
    mpmlab task=rom_train task.study=torsion task.data=data/torsion task.latent=7

The encoder e and the map g (``mpmlab.rom.networks``) are fitted to the study's training runs by
``mpmlab.rom.train.fit`` (Adam at 1e-3 / 1e-4 / 1e-5 / 1e-6 for 500 / 200 / 100 / 50 epochs x
``task.schedule_scale``, 8 snapshots per batch, lambda_F = 100, lambda_v = 0.01). Outputs:
``rom_weights.safetensors`` (g and the encoder, read by JAX and torch alike), ``train_checkpoint.pkl``
(every epoch; rerun the same command with the same ``hydra.run.dir`` to resume), ``recording.rrd``
(loss and its three terms per epoch, the learning rate), ``training.png`` and ``summary.json`` (the
schedule, the curve, and the reconstruction error E of e and g on the training and test runs: the
error about the initial centroid, and relative to the displacement).
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional

import numpy as np

from ..config import TaskConfig, register_task_schema
from ..core.errors import ConfigError
from ..rom.options import TrainSettings
from .common import SUMMARY, save_figure, write_config, write_json

log = logging.getLogger("mpmlab")
WEIGHTS = "rom_weights.safetensors"
CHECKPOINT = "train_checkpoint.pkl"
RECORDING = "recording.rrd"
PLOT = "training.png"


@dataclass
class RomTrainConfig(TrainSettings, TaskConfig):
    """Train the ROM's encoder and deformation map on a study's snapshots. The training options
    (latent, lambda_F, lambda_v, batch, schedule, schedule_scale, points, frame_stride, seed) are
    ``mpmlab.rom.options.TrainSettings``' fields, shared with ``mpmlab.rom.train.TrainOptions``."""

    name: str = "rom_train"
    #: the study (mpmlab.rom.snapshots.STUDIES): gravity | torsion | poke | tower | ...
    study: str = ""
    #: the folder of the study's runs (a sweep directory of experiment=rom_snapshots_<study>)
    data: str = ""
    #: use only the first k training (and test) runs of the study: a reduced reproduction, or a test
    max_runs: Optional[int] = None
    #: end early on purpose (checkpointed; rerun to continue)
    stop_after_s: Optional[float] = None
    stop_after_epochs: Optional[int] = None


register_task_schema("rom_train", RomTrainConfig)


def run(cfg, ctx) -> dict:
    from .. import __version__
    from ..rom import networks as N
    from ..rom.snapshots import load_snapshots, study
    from ..rom.train import TrainingSet, TrainOptions, fit, reconstruction_error

    t_task = time.perf_counter()
    out = Path(ctx.output_dir)
    tc = cfg.task
    if not tc.study or not tc.data:
        raise ConfigError("task=rom_train needs task.study=NAME and task.data=DIR (the study's runs: "
                          "mpmlab -m experiment=rom_snapshots_<study>).")
    s = study(str(tc.study))
    if not s.train:
        raise ConfigError(f"task.study = '{s.name}' has no training runs (it is a test set); train on its "
                          f"parent study and evaluate there.")
    k = None if tc.max_runs is None else int(tc.max_runs)
    if k is not None and k < 1:
        raise ConfigError(f"task.max_runs = {k} must be >= 1 (or null: every run).")
    train_runs, test_runs = tuple(s.train)[:k], tuple(s.test)[:k]
    snap = load_snapshots(str(tc.data), s, runs=train_runs)
    data = TrainingSet.from_snapshots(snap)
    opt = TrainOptions.from_config(tc)
    ckpt = out / CHECKPOINT
    if (out / SUMMARY).exists() and not ckpt.exists() and not ctx.overwrite:
        raise ConfigError(f"{out / SUMMARY} exists; choose another hydra.run.dir or set output.overwrite=true.")
    write_config(out, cfg, True)
    R, T, n, d = data.shape
    log.info("rom_train: study %s, %d training runs x %d snapshots of %d points (%dD), latent %d, %d epochs",
             s.name, R, T, n, d, opt.latent, opt.total_epochs)

    rec = None
    if cfg.output.recording:
        from ..io.rerun import EpochRecorder, unique_recording_id

        rec = EpochRecorder(out / RECORDING, unique_recording_id(f"rom_train-{s.name}-{out.name}"),
                            title="ROM training (Eq. 24)", overwrite=True)
    seen = [False]

    def record(h):
        rec.log(h["epoch"], h["loss"], {"mse/u": h["u"], "mse/F": h["F"], "mse/v": h["v"], "lr": h["lr"]})

    history_box: list = []

    def on_epoch(h):
        history_box.append(h)
        if rec is None:
            return
        if not seen[0]:
            seen[0] = True
            import pickle

            with open(ckpt, "rb") as f:                       # a resumed run: the epochs before it first
                for old in pickle.load(f)["history"][:-1]:
                    record(old)
        record(h)

    try:
        weights, history = fit(data, opt, ckpt, stop_after_s=tc.stop_after_s, stop_after_epochs=tc.stop_after_epochs,
                               on_epoch=on_epoch, progress=ctx.progress)
    finally:
        if rec is not None:
            rec.close()
    training = {"study": s.name, "runs": [s.runs[i].name for i in train_runs],
                "params": [s.runs[i].params for i in train_runs], "param_names": list(s.param_names)}
    N.save(out / WEIGHTS, weights.params, weights.norm, weights.spec, seed=int(tc.seed), training=training)
    errors = {"train": reconstruction_error(weights, data)}
    if test_runs:
        test = TrainingSet.from_snapshots(load_snapshots(str(tc.data), s, runs=test_runs))
        errors["test"] = reconstruction_error(weights, test)
    done = len(history) >= opt.total_epochs
    if cfg.output.plots and history:
        _plot(out / PLOT, history, f"rom_train {s.name}: latent {opt.latent}, {len(history)} epochs")
    summary = {"task": "rom_train", "status": "ok" if done else "stopped", "study": s.name, "data": str(tc.data),
               "runs": {"train": list(train_runs), "test": list(test_runs)}, "points": n, "dim": d,
               "snapshots_per_run": T, "snapshot_dt": data.dt, "latent": opt.latent,
               "lambda_F": opt.lambda_F, "lambda_v": opt.lambda_v, "batch": opt.batch,
               "schedule": opt.epochs(), "epochs": len(history), "epochs_planned": opt.total_epochs,
               "points_per_batch": opt.points, "frame_stride": opt.frame_stride,
               "initial_loss": history[0]["loss"] if history else None,
               "final_loss": history[-1]["loss"] if history else None,
               "reconstruction_error": errors, "history": history, "weights": str(out / WEIGHTS),
               "g_parameters": weights.spec.g_count(), "encoder_parameters": weights.spec.encoder_count(),
               "wall_time_s": float(time.perf_counter() - t_task), "mpmlab_version": __version__}
    write_json(out / SUMMARY, summary, True)
    more = "" if done else f" (stopped at epoch {len(history)} of {opt.total_epochs}: rerun the same command to continue)"
    test_e = errors.get("test", {}).get("E")
    print(f"mpmlab: rom_train {s.name}: {len(history)} epochs{more}, loss {summary['initial_loss']:.3e} -> "
          f"{summary['final_loss']:.3e}; E train {errors['train']['E']:.2%}"
          + ("" if test_e is None else f", test {test_e:.2%}") + f"; weights {out / WEIGHTS}", flush=True)
    return summary


def _plot(path: Path, history: list[dict[str, Any]], title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ep = np.array([h["epoch"] for h in history])
    fig, ax = plt.subplots(figsize=(6.5, 4))
    ax.semilogy(ep, [h["loss"] for h in history], label="loss (Eq. 24)", color="k")
    for k, lab in (("u", "MSE u~ (standardised)"), ("F", "MSE F"), ("v", "MSE v [m²/s²]")):
        vals = np.array([h[k] for h in history])
        if np.any(vals > 0):
            ax.semilogy(ep, np.maximum(vals, 1e-16), label=lab, lw=1)
    ax.set_xlabel("epoch"); ax.set_title(title, fontsize=9); ax.legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, path, title)
