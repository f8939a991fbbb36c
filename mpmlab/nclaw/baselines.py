"""NCLaw's "labeled" baseline (Ma et al. 2023, Tabs. 1-2; the release's ``train/supervised.yaml``): the
two networks fitted directly to ground-truth constitutive pairs instead of through the simulator.

* elastic: tau_net(F_n) against the true law's Kirchhoff stress tau(F_n), for every particle and
  frame of the dataset (F_n: the dataset's F; a J-only law's state is J = det F);
* plastic: the law's update from (F_n, C_{n+1}) -- F_trial = (I + dt C_{n+1}) F_n, then the return map
  -- against the dataset's F_{n+1} (MLS-MPM's velocity gradient is C, NCLaw App. D.1).

Adam (lr 0.1 for both, the release's), mini-batches of 1,000 pairs, 30 epochs, on JAX (a regression,
not a rollout: the resulting weight file runs on both backends); each net keeps its best epoch (the lowest
loss over all pairs, checked after every epoch). Each net's loss is the MSE scaled by
the variance of its targets, so one learning rate suits stresses in Pa and F near I.
"""
from __future__ import annotations

import math
import time
from typing import Any

import numpy as np

from ..core.errors import ConfigError


def true_law(dataset):
    """(law instance, parameter rows [N, P]) of the dataset's one material group."""
    from ..core import registry

    if len(dataset.laws) != 1:
        raise ConfigError(f"labeled baseline: dataset '{dataset.path}' has {len(dataset.laws)} material groups; it "
                          f"needs one (the training body).")
    m = dataset.laws[0]
    law = registry.laws.get(m["law"])()
    rows = np.asarray(dataset.params, float)[:, :len(law.param_names())]
    return law, rows


def labeled_pairs(dataset, stride: int = 1) -> dict[str, np.ndarray]:
    """``F`` [M, D, D] with ``tau`` [M, D, D] (elastic pairs) and ``F0``, ``C1``, ``F1`` (plastic pairs:
    F_n, C_{n+1}, F_{n+1}) from every ``stride``-th frame of a dataset, float64."""
    import jax
    import jax.numpy as jnp

    from ..backends.jax import stepper as _x64  # noqa: F401  (enables float64 in JAX, as the backend does)
    from ..backends.jax.laws import law_functions

    law, rows = true_law(dataset)
    D = dataset.dim
    fns = law_functions(law, D)
    w = {k: jnp.asarray(a) for k, a in law.initial_weights(D).items()}
    F = np.asarray(dataset.F[::stride], np.float64)                       # [T', N, D, D]
    T, N = F.shape[:2]
    Ff = F.reshape(-1, D, D)
    R = np.tile(rows, (T, 1))
    fields = law.state_fields
    # the plane-strain out-of-plane strain of the Hencky laws is 0 in 3D (issue 18): F alone is their state there
    zero = {"eps_zz"} if D == 3 else set()
    if set(fields) - zero == {"F"}:
        state = {"F": jnp.asarray(Ff), **{k: jnp.zeros(len(Ff)) for k in set(fields) & zero}}
    elif set(fields) == {"J"}:
        state = {"J": jnp.asarray(np.linalg.det(Ff))}
    else:
        raise ConfigError(f"labeled baseline: law '{law.name}' keeps {sorted(fields)}; only F- or J-state laws "
                          f"have their state in the dataset.")
    tau = np.asarray(jax.jit(jax.vmap(fns.kirchhoff, in_axes=(0, 0, None)))(state, jnp.asarray(R), w))
    full = np.asarray(dataset.F, np.float64)
    C = np.asarray(dataset.C, np.float64)
    idx = np.arange(0, full.shape[0] - 1, stride)
    return {"F": Ff, "tau": tau, "F0": full[idx].reshape(-1, D, D), "C1": C[idx + 1].reshape(-1, D, D),
            "F1": full[idx + 1].reshape(-1, D, D)}


def fit_labeled(law, dim: int, pairs: dict[str, np.ndarray], dt: float, epochs: int = 30, batch: int = 1000,
                lr: float = 0.1, seed: int = 0, progress: bool | None = None) -> tuple[dict, dict]:
    """Fit ``law``'s (an nclaw instance) two networks to ``pairs``; returns (weights, report)."""
    import jax
    import jax.numpy as jnp
    import optax
    from tqdm.auto import tqdm

    from ..backends.jax.laws import law_functions

    fns = law_functions(law, dim)
    w0 = {k: jnp.asarray(a) for k, a in law.initial_weights(dim).items()}
    row = jnp.zeros((0,))
    kir = jax.vmap(lambda F, w: fns.kirchhoff({"F": F}, row, w), in_axes=(0, None))
    upd = jax.vmap(lambda F, C, w: fns.update({"F": F}, C, dt, row, w)["F"], in_axes=(0, 0, None))
    scale_e = float(np.var(pairs["tau"])) or 1.0
    scale_p = float(np.var(pairs["F1"] - pairs["F0"])) or 1.0

    def loss_e(w, F, tau):
        r = kir(F, w) - tau
        return jnp.mean(r * r) / scale_e

    def loss_p(w, F0, C1, F1):
        r = upd(F0, C1, w) - F1
        return jnp.mean(r * r) / scale_p

    report: dict[str, Any] = {"epochs": int(epochs), "batch": int(batch), "lr": float(lr)}
    weights = dict(w0)
    rng = np.random.default_rng(seed)
    for net, lossf, keys in (("e", loss_e, ("F", "tau")), ("p", loss_p, ("F0", "C1", "F1"))):
        names = [k for k in weights if k.startswith(net + "_")]
        data = [jnp.asarray(pairs[k]) for k in keys]
        M = int(data[0].shape[0])
        opt = optax.adam(lr)
        train = {k: weights[k] for k in names}
        frozen = {k: v for k, v in weights.items() if k not in names}
        state = opt.init(train)

        @jax.jit
        def step(train, state, *batch_data):
            val, g = jax.value_and_grad(lambda t: lossf({**frozen, **t}, *batch_data))(train)
            up, state = opt.update(g, state, train)
            return optax.apply_updates(train, up), state, val

        # the data as arguments, not closed over: a closed-over array is a constant that XLA folds
        # (minutes for the 1M pairs of an NCLaw trajectory)
        full = jax.jit(lambda t, *d: lossf({**frozen, **t}, *d))
        first = float(full(train, *data))
        t0 = time.perf_counter()
        nb = max(1, math.ceil(M / batch))
        bar = tqdm(total=epochs * nb, disable=None if progress is None else not progress, leave=False,
                   desc=f"labeled {net}")
        # the weights of the epoch with the lowest loss over every pair are kept: at the release's lr 0.1 the
        # plastic net, which starts near its target (F_new ~ F_trial), can climb away from it again, and
        # whether it does varies with the float round-off of the machine (a 14x rise on one CPU, a 3e5x fall
        # on another, same data and seed)
        best, best_epoch, last = first, 0, first
        keep = dict(train)
        for epoch in range(1, int(epochs) + 1):
            perm = rng.permutation(M)
            for b in range(nb):
                sel = jnp.asarray(perm[b * batch:(b + 1) * batch])
                train, state, _ = step(train, state, *(a[sel] for a in data))
                bar.update(1)
            last = float(full(train, *data))
            if math.isfinite(last) and last < best:
                best, best_epoch, keep = last, epoch, dict(train)
        bar.close()
        if not math.isfinite(last) and best_epoch == 0:
            from ..core.errors import FitDiverged
            raise FitDiverged(f"labeled baseline: the {net} network's loss became {last}; lower the learning rate.")
        weights.update(keep)
        report[net] = {"pairs": M, "loss_initial": first, "loss_final": best, "loss_last_epoch": last,
                       "best_epoch": best_epoch, "seconds": time.perf_counter() - t0,
                       "target_variance": scale_e if net == "e" else scale_p}
    return {k: np.asarray(v, np.float64) for k, v in weights.items()}, report
