"""Offline training of the deformation-map ROM's networks (Chen et al. 2023, Sec. 4.2, Eq. 24, App. B):
the encoder e and the map g fitted to full-order snapshots, in JAX (optax's Adam), resumable.

Eq. 24, in the release's form (``/work/shared/notes/nclaw-rom.md`` Sec. 2.2), per batch of snapshots n
(with x_hat_n = e(x_n), x_hat_{n+1} = e(x_{n+1}) the next snapshot of the same run)::

    L = 1000 MSE(u~)  +  lambda_F MSE(F)  +  lambda_v 1000 MSE(dg/dx_hat (x_hat_{n+1} - x_hat_n) / dt - v_{n+1})

* u~: g's output, the standardised displacement, against the snapshot's (x - X - u_mean) / u_std (the
  network's own units; the paper's |g - x|^2 differs from it by the per-component scale u_std^2);
* F = dg/dX (exact, forward mode) against the snapshot's deformation gradient, dimensionless;
* the velocity term in m/s, against the *next* snapshot's velocity (the release's ``use_actual_v``);
  dt is the time between snapshots. A run's last snapshot has no next one: it enters the first two
  terms only.

Schedule (App. B, the release's README): Adam at 1e-3 / 1e-4 / 1e-5 / 1e-6 for 500 / 200 / 100 / 50
epochs, 8 snapshots per batch; ``schedule_scale`` scales the epoch counts (a reduced schedule), and
``points`` subsamples the points of each snapshot per batch (the loss is a mean over points; the
encoder always reads the whole snapshot). ``fit`` checkpoints every epoch (atomically) and resumes.
"""
from __future__ import annotations

import logging
import math
import pickle
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from ..core.errors import ConfigError
from ..io.files import write_pickle
from . import networks as N
from .options import TrainSettings

log = logging.getLogger("mpmlab")

#: App. B / the release's README: learning rates and their epochs
PAPER_SCHEDULE = ((1e-3, 500), (1e-4, 200), (1e-5, 100), (1e-6, 50))


@dataclass
class TrainingSet:
    """Training snapshots of one study: ``X`` ``[N, d]`` reference positions (every run starts there),
    ``x``, ``v`` ``[R, T, N, d]`` and ``F`` ``[R, T, N, d, d]`` for R runs of T snapshots each, ``dt``
    the time between snapshots [s]."""

    X: np.ndarray
    x: np.ndarray
    v: np.ndarray | None
    F: np.ndarray | None
    dt: float

    def __post_init__(self):
        self.X, self.x = np.asarray(self.X, float), np.asarray(self.x, float)
        R, T, n, d = self.x.shape if self.x.ndim == 4 else (None,) * 4
        if R is None or self.X.shape != (n, d):
            raise ConfigError(f"ROM snapshots: x has shape {self.x.shape} and X {self.X.shape}; give x [runs, frames, "
                              f"points, d] and X [points, d].")
        for k, want in (("v", (R, T, n, d)), ("F", (R, T, n, d, d))):
            a = getattr(self, k)
            if a is not None and np.shape(a) != want:
                raise ConfigError(f"ROM snapshots: {k} has shape {np.shape(a)}; it must be {want} like x.")
        if not (self.dt > 0 and math.isfinite(self.dt)):
            raise ConfigError(f"ROM snapshots: dt = {self.dt!r} (time between snapshots) must be a positive number.")

    @property
    def shape(self):
        return self.x.shape

    @classmethod
    def from_snapshots(cls, snap) -> "TrainingSet":
        """From ``mpmlab.rom.snapshots.load_snapshots``' result: every run must start from one reference
        configuration X (its first snapshot), and the snapshots be evenly spaced in time."""
        x0 = np.asarray(snap.x[:, 0], float)
        if not np.allclose(x0, x0[:1], rtol=0, atol=1e-9 * max(1.0, float(np.abs(x0).max()))):
            raise ConfigError("rom_train: the runs start from different configurations; g(X; x_hat) needs one "
                              "reference X for every snapshot (the same scene and sampling).")
        t = np.asarray(snap.time, float)
        if len(t) < 2 or not np.allclose(np.diff(t), t[1] - t[0], rtol=1e-6):
            raise ConfigError(f"rom_train: the snapshots' times {t[:4].tolist()}... are not evenly spaced (or fewer "
                              f"than two): the velocity term needs one interval.")
        return cls(x0[0], snap.x, snap.v, snap.F, float(t[1] - t[0]))


@dataclass
class TrainOptions(TrainSettings):
    """Eq. 24's weights, the schedule and the sampling (module doc): ``TrainSettings``' fields (the
    ``task=rom_train`` options too; ``TrainOptions.from_config(cfg.task)``) and the schedule's arithmetic.
    ``schedule`` None is App. B's (``PAPER_SCHEDULE``)."""

    def __post_init__(self):
        stages = PAPER_SCHEDULE if self.schedule is None else self.schedule
        try:
            stages = tuple((float(lr), int(n)) for lr, n in stages)
            ok = len(stages) > 0 and all(lr > 0 and math.isfinite(lr) and n >= 1 for lr, n in stages)
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise ConfigError(f"rom_train: schedule = {self.schedule!r}; give [[learning rate, epochs], ...] with "
                              f"positive rates and epochs >= 1 (e.g. [[3e-3,150],[1e-3,100]]), or null (App. B's).")
        self.schedule = stages

    def epochs(self) -> list[tuple[float, int]]:
        """(lr, epochs) with the epoch counts scaled by ``schedule_scale`` (at least 1 each)."""
        return [(float(lr), max(1, int(round(n * self.schedule_scale)))) for lr, n in self.schedule]

    def lr_at(self, epoch: int) -> float:
        done = 0
        for lr, n in self.epochs():
            done += n
            if epoch < done:
                return lr
        return self.epochs()[-1][0]

    @property
    def total_epochs(self) -> int:
        return sum(n for _, n in self.epochs())


def check_options(opt: TrainOptions, data: TrainingSet) -> None:
    if opt.lambda_F > 0 and data.F is None:
        raise ConfigError(f"rom_train: lambda_F = {opt.lambda_F} needs F in the snapshots (store output.fields [F]); "
                          f"or set lambda_F 0.")
    if opt.lambda_v > 0 and data.v is None:
        raise ConfigError(f"rom_train: lambda_v = {opt.lambda_v} needs v in the snapshots; or set lambda_v 0.")
    if opt.points is not None and not 1 <= int(opt.points) <= data.X.shape[0]:
        raise ConfigError(f"rom_train: points = {opt.points} per snapshot; the snapshots have {data.X.shape[0]}.")
    if int(opt.frame_stride) < 1 or int(opt.batch) < 1 or not opt.schedule_scale > 0:
        raise ConfigError(f"rom_train: frame_stride = {opt.frame_stride}, batch = {opt.batch} and schedule_scale = "
                          f"{opt.schedule_scale} must be positive.")


def _pairs(R: int, T: int, stride: int) -> np.ndarray:
    """(run, frame, next frame or -1) of every training snapshot, frames every ``stride``."""
    frames = np.arange(0, T, stride)
    out = [(r, f, (frames[i + 1] if i + 1 < len(frames) else -1)) for r in range(R) for i, f in enumerate(frames)]
    return np.asarray(out, dtype=np.int64)


def make_loss(norm, lambda_F: float, lambda_v: float):
    """``loss(params, X_pts, x_n, x_next, x_pts, F_pts, v_pts, has_next, dt) -> (value, parts)``: Eq. 24
    on a batch (module doc). ``x_n``/``x_next`` ``[B, N, d]`` whole snapshots for the encoder; ``*_pts``
    the sampled points ``[B, P, ...]``; ``has_next`` ``[B]``."""
    import jax.numpy as jnp

    def loss(params, X_pts, x_n, x_next, x_pts, F_pts, v_pts, has_next, dt):
        z = N.encode(params, norm, jnp.swapaxes(x_n, 1, 2))              # [B, d_hat]
        z1 = N.encode(params, norm, jnp.swapaxes(x_next, 1, 2))
        if lambda_v > 0:   # x, F and the velocity dg/dx_hat (z1 - z) / dt in one forward pass (d + 1 tangents)
            x, F, vel = N.g_state(params, norm, X_pts, z[:, None, :], ((z1 - z) / dt)[:, None, :])   # [B, P, ...]
        else:
            x, F = N.g_F(params, norm, X_pts, z[:, None, :])
        std = norm["u_std"]
        mse_u = jnp.mean(((x - x_pts) / std) ** 2)
        mse_F = jnp.mean((F - F_pts) ** 2) if lambda_F > 0 else jnp.zeros(())
        if lambda_v > 0:
            per = jnp.mean((vel - v_pts) ** 2, axis=(1, 2))
            mse_v = jnp.sum(per * has_next) / jnp.maximum(jnp.sum(has_next), 1.0)
        else:
            mse_v = jnp.zeros(())
        value = 1000.0 * mse_u + lambda_F * mse_F + lambda_v * 1000.0 * mse_v
        return value, {"u": mse_u, "F": mse_F, "v": mse_v}
    return loss


def fit(data: TrainingSet, opt: TrainOptions, checkpoint: str | Path | None = None, *, stop_after_s: float | None = None,
        stop_after_epochs: int | None = None, on_epoch: Callable | None = None, progress: bool | None = None):
    """Train e and g on ``data`` (module doc); returns ``(weights: RomWeights, history: list of dicts)``.

    With ``checkpoint`` (a file path) the state is saved after every epoch and a later call with the
    same path resumes (the same curve as an uninterrupted run: the batch order is drawn per epoch from
    ``seed`` and the epoch number). ``stop_after_s`` / ``stop_after_epochs`` end the call early
    (checkpointed). ``on_epoch(record)`` sees each epoch's record (loss, its parts, lr, seconds)."""
    import jax
    import jax.numpy as jnp
    import optax
    from tqdm.auto import tqdm

    check_options(opt, data)
    R, T, n, d = data.shape
    spec = N.RomSpec(dim=d, latent=int(opt.latent), n_points=n)
    norm_np = N.fit_norm(data.X, data.x)
    norm = N.to_jax(norm_np, jnp.float64 if jax.config.jax_enable_x64 else jnp.float32)
    dtype = norm["u_std"].dtype
    pairs = _pairs(R, T, int(opt.frame_stride))
    loss = make_loss(norm, float(opt.lambda_F), float(opt.lambda_v))
    tx = optax.inject_hyperparams(optax.adam)(learning_rate=opt.lr_at(0))
    value_and_grad = jax.value_and_grad(loss, has_aux=True)

    @jax.jit
    def train_step(params, state, lr, X, xs, Fs, vs, r, f, f1, has_next, pts, dt):
        """One batch: gather its snapshots, Eq. 24's value and gradient, Adam's update, in one program
        (one dispatch per batch: the eager gathers and updates cost more than the networks on small sets)."""
        x_n, x_next = xs[r, f], xs[r, f1]
        x_pts = x_n[:, pts]
        F_pts = Fs[r, f][:, pts] if Fs is not None else jnp.zeros(x_pts.shape + (d,), dtype)
        v_pts = vs[r, f1][:, pts] if vs is not None else jnp.zeros_like(x_pts)
        X_pts = jnp.broadcast_to(X[pts], x_pts.shape)
        (val, parts), g = value_and_grad(params, X_pts, x_n, x_next, x_pts, F_pts, v_pts, has_next.astype(dtype), dt)
        state.hyperparams["learning_rate"] = lr
        upd, state = tx.update(g, state, params)
        return optax.apply_updates(params, upd), state, jnp.stack([val, parts["u"], parts["F"], parts["v"]])

    @jax.jit
    def train_epoch(params, state, lr, X, xs, Fs, vs, batches, dt):
        """The epoch's full batches in order, as one scanned program (one dispatch per epoch)."""
        def body(carry, b):
            p, st = carry
            p, st, m = train_step(p, st, lr, X, xs, Fs, vs, *b, dt)
            return (p, st), m
        (params, state), m = jax.lax.scan(body, (params, state), batches)
        return params, state, m

    ckpt = Path(checkpoint) if checkpoint else None
    # what shapes the training curve: a resume must not change it silently (an older checkpoint records none)
    curve = {"lambda_F": float(opt.lambda_F), "lambda_v": float(opt.lambda_v), "batch": int(opt.batch),
             "schedule": [[float(lr), int(k)] for lr, k in opt.epochs()], "points": opt.points,
             "frame_stride": int(opt.frame_stride), "seed": int(opt.seed)}
    digest = data_digest(data) if ckpt is not None else None
    fingerprint = data_fingerprint(data) if ckpt is not None else None
    if ckpt is not None and ckpt.exists():
        with open(ckpt, "rb") as f:
            saved = pickle.load(f)
        from ..core.resume import FINGERPRINT_RTOL, fingerprint_distance

        # snapshots made again on another machine differ in their last bits (mpmlab.core.resume): resumed when
        # their fingerprints agree
        other = saved.get("data", digest) != digest
        near = fingerprint_distance(saved.get("data_fingerprint"), fingerprint) if other else 0.0
        if other and near <= FINGERPRINT_RTOL:
            log.warning("rom_train: the snapshots differ from those the checkpoint %s was trained on at round-off "
                        "only (fingerprints agree to %.1e of each array's RMS): resuming", ckpt, near)
        elif other:
            raise ConfigError(f"rom_train: the checkpoint {ckpt} was trained on other snapshots (data digest "
                              f"{saved['data'][:12]}, these are {digest[:12]}); use another run directory, or the "
                              f"snapshots it was trained on.")
        if saved.get("spec") != (d, int(opt.latent), n):
            raise ConfigError(f"rom_train: the checkpoint {ckpt} is for (dim, latent, points) = {saved.get('spec')}, "
                              f"this run is {(d, int(opt.latent), n)}; use another run directory.")
        changed = [k for k, v in saved.get("options", curve).items() if curve.get(k) != v]
        if changed:
            k = changed[0]
            raise ConfigError(f"rom_train: the checkpoint {ckpt} was trained with {k} = {saved['options'][k]!r}, this run "
                              f"asks for {curve[k]!r}; resume with the same options, or use another run directory.")
        params = jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype), saved["params"])
        state = jax.tree_util.tree_map(lambda a: jnp.asarray(a) if isinstance(a, np.ndarray) else a, saved["opt_state"])
        epoch0, history = int(saved["epoch"]), list(saved["history"])
    else:
        params = N.to_jax(N.init_params(spec, opt.seed), dtype)
        state = tx.init(params)
        epoch0, history = 0, []
    X = jnp.asarray(data.X, dtype)
    xs = jnp.asarray(data.x, dtype)
    Fs = jnp.asarray(data.F, dtype) if data.F is not None else None
    vs = jnp.asarray(data.v, dtype) if data.v is not None else None
    dt = float(data.dt) * int(opt.frame_stride)
    total = opt.total_epochs
    t0 = time.perf_counter()
    bar = tqdm(range(epoch0, total), initial=epoch0, total=total, unit="epoch", disable=None if progress is None
               else not progress, leave=False, desc="rom_train")
    for epoch in bar:
        rng = np.random.default_rng([int(opt.seed), epoch])
        order = rng.permutation(len(pairs))
        lr = opt.lr_at(epoch)
        state.hyperparams["learning_rate"] = jnp.asarray(lr, dtype)
        t_ep = time.perf_counter()
        lr_dev, dt_dev = jnp.asarray(lr, dtype), jnp.asarray(dt, dtype)
        batches = []
        for b0 in range(0, len(order), int(opt.batch)):
            rows = pairs[order[b0:b0 + int(opt.batch)]]
            r, f, f1 = rows[:, 0], rows[:, 1], rows[:, 2]
            has_next = f1 >= 0
            f1 = np.where(has_next, f1, f)
            pts = (rng.choice(n, size=int(opt.points), replace=False) if opt.points is not None else np.arange(n))
            batches.append((r, f, f1, has_next, pts))
        full = [b for b in batches if len(b[0]) == int(opt.batch)]       # same draws as batch by batch
        rows_of, measured = [], []
        if full:
            stacked = tuple(np.stack(col) for col in zip(*full))
            params, state, m = train_epoch(params, state, lr_dev, X, xs, Fs, vs, stacked, dt_dev)
            rows_of += [int(opt.batch)] * len(full)
            measured.append(m)
        for b in batches[len(full):]:                                    # the last, shorter batch
            params, state, m = train_step(params, state, lr_dev, X, xs, Fs, vs, *b, dt_dev)
            rows_of.append(len(b[0]))
            measured.append(m[None])
        m = np.asarray(jnp.concatenate(measured), np.float64)            # [batches, 4]: one sync per epoch
        if not np.all(np.isfinite(m[:, 0])):
            raise ConfigError(f"rom_train: the loss became {m[~np.isfinite(m[:, 0]), 0][0]} at epoch {epoch} (lr {lr:g}); "
                              f"lower the learning rate or check the snapshots for non-finite values.")
        k = np.asarray(rows_of, np.float64)
        count = float(k.sum())
        sums = {key: float(np.sum(m[:, j] * k)) for j, key in enumerate(("loss", "u", "F", "v"))}
        rec = {"epoch": epoch + 1, "lr": lr, **{k: v / count for k, v in sums.items()},
               "seconds": time.perf_counter() - t_ep}
        history.append(rec)
        bar.set_postfix(loss=f"{rec['loss']:.3e}")
        if ckpt is not None:
            write_pickle(ckpt, {"epoch": epoch + 1, "spec": (d, int(opt.latent), n), "options": curve, "data": digest,
                                  "data_fingerprint": fingerprint,
                                  "params": jax.tree_util.tree_map(np.asarray, params),
                                  "opt_state": jax.tree_util.tree_map(
                                      lambda a: np.asarray(a) if hasattr(a, "shape") else a, state),
                                  "history": history})
        if on_epoch is not None:
            on_epoch(rec)
        if (stop_after_epochs is not None and epoch + 1 - epoch0 >= stop_after_epochs) or \
                (stop_after_s is not None and time.perf_counter() - t0 >= stop_after_s):
            break
    bar.close()
    weights = N.RomWeights({k: np.asarray(a, np.float64) for k, a in params.items()}, norm_np, spec, int(opt.seed))
    return weights, history


def data_digest(data: TrainingSet) -> str:
    """SHA-256 of the training snapshots (X, x, v, F, dt as float64): a resumed training must see the data
    it started on (regenerated snapshots of a changed scene would otherwise continue it silently)."""
    from ..core.resume import array_digest

    return array_digest(data.X, data.x, data.v, data.F, np.asarray(data.dt))


def data_fingerprint(data: TrainingSet) -> list:
    """``mpmlab.core.resume.array_fingerprint`` of the snapshots, each run's snapshots as frames."""
    from ..core.resume import array_fingerprint

    R, T, n, d = data.shape
    frames = lambda a: None if a is None else np.asarray(a).reshape((R * T, n) + np.asarray(a).shape[3:])
    return array_fingerprint(np.asarray(data.X)[None], frames(data.x), frames(data.v), frames(data.F),
                             np.asarray([data.dt], float))


def reconstruction_error(weights: N.RomWeights, data: TrainingSet, origin: str = "centroid") -> dict:
    """How well e and g reproduce snapshots (no time stepping): E = sqrt(sum |g(X; e(x)) - x|^2 /
    sum |x - c|^2) with c the initial centroid (``origin="centroid"``; the paper states no origin, the
    release uses 5 m per axis: the value depends on it), and the displacement-relative error
    sqrt(sum |g - x|^2 / sum |x - X|^2), over every run, snapshot and point."""
    import jax
    import jax.numpy as jnp

    dtype = jnp.float64 if jax.config.jax_enable_x64 else jnp.float32
    params, norm = N.to_jax(weights.params, dtype), N.to_jax(weights.norm, dtype)
    R, T, n, d = data.shape
    c = data.X.mean(axis=0)
    num = den_c = den_u = 0.0
    for r in range(R):
        z = N.encode(params, norm, jnp.swapaxes(jnp.asarray(data.x[r]), 1, 2))
        x = np.asarray(N.g_apply(params, norm, jnp.asarray(data.X)[None], z[:, None, :]))
        num += float(np.sum((x - data.x[r]) ** 2))
        den_c += float(np.sum((data.x[r] - c) ** 2))
        den_u += float(np.sum((data.x[r] - data.X) ** 2))
    return {"E": math.sqrt(num / den_c), "E_displacement": math.sqrt(num / den_u) if den_u > 0 else None,
            "origin": origin}
