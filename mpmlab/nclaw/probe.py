"""Where a learned NCLaw law can be trusted: its constitutive errors on the training trajectory (NCLaw
Tab. 5), the reach of its learned return map, and how far a rollout's states lie from the training's.

* :func:`deviatoric_stretch` -- per particle, the largest isochoric log-stretch max_i |log(s_i / J^(1/D))|
  (s_i: the singular values of F) and J = det F. The truth of a J-only law (WATER, NCLaw App. B
  Eq. 21: F <- J^(1/3) I) keeps it at 0; a learned return map lets it grow with the shear rate.
* :func:`constitutive_errors` -- NCLaw Sec. F.3 / Tab. 5: the MSE of P = tau F^-T and of F^e,new on
  ``n`` pairs drawn from a ground-truth dataset (the pairs of :func:`mpmlab.nclaw.baselines.labeled_pairs`),
  beside the error of taking no return map at all (F^e,new = F_trial), which sets its scale, and the
  floor no nclaw return map can pass (:func:`best_in_rotation`: it keeps F_trial's rotation).
* :func:`state_range` -- what a rollout's states span; ``task=nclaw_train`` records it for its training
  rollout in the weight file (:func:`write_state_range`; :func:`record_state_range` for older files), and
  the law's divergence note compares a failed run's states with it.
* :func:`return_map_reach` -- the plastic network iterated with no velocity gradient from an isochoric
  stretch (uniaxial, or simple shear) of principal stretch ``a``: does it bring F back to J^(1/D) I,
  and does it keep J? A learned return map is a relaxation with a finite rate and a finite basin;
  beyond the basin it drives F away (benchmarks/nclaw.md, "WATER (c)").
* :func:`state_from_F`, :func:`F_of_state` -- a law's per-particle state from F and back, for the probes that
  drive a law by F (F-state laws, and J-only ones through J = det F).
* :func:`acoustic_minimum` -- the smallest eigenvalue of one explicit step's acoustic tensor at given states:
  below 0, a loss of strong ellipticity (waves grow at any dt). For learned and true laws alike; it does not
  tell NCLaw's (c) failures from its successes (benchmarks/nclaw.md, "The learned laws' ellipticity").
"""
from __future__ import annotations

from typing import Any, Mapping, Sequence

import numpy as np

from ..laws._linalg_np import deviatoric_stretch  # noqa: F401  (part of this module's API)


def _jax_law(law, dim: int, weights: Mapping[str, Any]):
    import jax.numpy as jnp

    from ..backends.jax import stepper as _x64  # noqa: F401  (float64 in JAX, as the backend enables it)
    from ..backends.jax.laws import law_functions

    return law_functions(law, dim), {k: jnp.asarray(np.asarray(a, np.float64)) for k, a in weights.items()}


def constitutive_errors(law, weights: Mapping[str, Any], dataset, n: int = 1000, seed: int = 0,
                        pairs: Mapping[str, np.ndarray] | None = None) -> dict:
    """NCLaw Tab. 5 on ``dataset`` (a :func:`mpmlab.nclaw.data.load_dataset`): ``n`` elastic pairs
    (F, P_true) and ``n`` plastic pairs (F_n, C_n+1 -> F_n+1) drawn with ``numpy`` PCG64(``seed``);
    returns {"P": MSE of P [Pa^2], "F_new": MSE of F^e,new, "F_new_without_return_map": MSE of
    F_trial against F^e,new (no plastic step at all), "F_new_floor": the MSE of :func:`best_in_rotation`
    (the best any nclaw return map can do), "pairs": n, "P_true_rms": RMS of the true P}.
    ``pairs``: ``labeled_pairs(dataset)`` when already computed (it evaluates the true law on every frame)."""
    import jax
    import jax.numpy as jnp

    from .baselines import labeled_pairs

    dim = int(dataset.dim)
    fns, w = _jax_law(law, dim, weights)
    pairs = labeled_pairs(dataset) if pairs is None else pairs
    rng = np.random.Generator(np.random.PCG64(seed))
    ie = rng.choice(len(pairs["F"]), size=min(n, len(pairs["F"])), replace=False)
    ip = rng.choice(len(pairs["F0"]), size=min(n, len(pairs["F0"])), replace=False)
    row = jnp.zeros((0,))
    kir = jax.jit(jax.vmap(lambda F: fns.kirchhoff({"F": F}, row, w)))
    upd = jax.jit(jax.vmap(lambda F, C: fns.update({"F": F}, C, float(dataset.dt), row, w)["F"]))
    F = pairs["F"][ie]
    FinvT = np.linalg.inv(F).transpose(0, 2, 1)
    P_net = np.asarray(kir(jnp.asarray(F))) @ FinvT
    P_true = pairs["tau"][ie] @ FinvT
    F0, C1, F1 = pairs["F0"][ip], pairs["C1"][ip], pairs["F1"][ip]
    F_new = np.asarray(upd(jnp.asarray(F0), jnp.asarray(C1)))
    F_trial = (np.eye(dim) + float(dataset.dt) * C1) @ F0
    mse = lambda a, b: float(np.mean((a - b) ** 2))  # noqa: E731
    return {"P": mse(P_net, P_true), "F_new": mse(F_new, F1), "F_new_without_return_map": mse(F_trial, F1),
            "F_new_floor": mse(best_in_rotation(F_trial, F1), F1),
            "pairs": int(len(ie)), "P_true_rms": float(np.sqrt(np.mean(P_true ** 2)))}


def best_in_rotation(F_trial, F_target) -> np.ndarray:
    """The F^e,new closest to ``F_target`` (Frobenius) that an nclaw return map can give from ``F_trial``.

    F + alpha R T with T symmetric (Alg. 4) keeps F_trial's rotation R = U V^T: F_new = R (V S V^T +
    alpha T) = R S' with S' symmetric. The closest R S' to a target G is S' = sym(R^T G). WATER's truth
    (F <- J^(1/3) I, NCLaw Eq. 21) drops the rotation that (I + dt C) adds each step, so no weights can
    do better than this: the floor under Tab. 5's F^e,new column."""
    from ..laws._linalg_np import polar_rotation

    Ft = np.asarray(F_trial, np.float64)
    G = np.asarray(F_target, np.float64)
    out = np.empty_like(Ft)
    for i in range(len(Ft)):
        R = polar_rotation(Ft[i])
        M = R.T @ G[i]
        out[i] = R @ (0.5 * (M + M.T))
    return out


def state_range(F_frames) -> dict:
    """What a rollout's states span, from its F frames [T, N, D, D]: the largest deviatoric log-stretch
    (:func:`deviatoric_stretch`) of the sound particles, the largest per-frame 99th percentile of it, J's
    range, and ``inverted``: how many particle-frames had J <= 0 or a non-finite F. The
    training's range is recorded in a trained nclaw weight file (``state_range``); the law's divergence
    note compares a failed run's states with it."""
    F = np.asarray(F_frames, np.float64)
    devs, p99, jmin, jmax, inverted = [], [], np.inf, -np.inf, 0
    for frame in F:
        dev, J = deviatoric_stretch(frame)
        ok = np.isfinite(dev)                  # inverted (J <= 0) or non-finite F: counted, not a stretch
        inverted += int(np.sum(~ok))
        if ok.any():
            devs.append(float(np.max(dev[ok])))
            p99.append(float(np.percentile(dev[ok], 99)))
        if np.isfinite(J).any():
            jmin, jmax = min(jmin, float(np.nanmin(J))), max(jmax, float(np.nanmax(J)))
    return {"deviatoric_stretch_max": max(devs, default=float("nan")),
            "deviatoric_stretch_p99": max(p99, default=float("nan")), "J_min": jmin, "J_max": jmax,
            "inverted": inverted, "frames": int(len(F))}


def merge_ranges(a: dict | None, b: dict) -> dict:
    """Two :func:`state_range` results as one (the union of their frames)."""
    if a is None:
        return dict(b)
    nanmax = lambda u, v: max((x for x in (u, v) if x == x), default=float("nan"))   # noqa: E731  (NaN: no sound particle)
    return {"deviatoric_stretch_max": nanmax(a["deviatoric_stretch_max"], b["deviatoric_stretch_max"]),
            "deviatoric_stretch_p99": nanmax(a["deviatoric_stretch_p99"], b["deviatoric_stretch_p99"]),
            "J_min": min(a["J_min"], b["J_min"]), "J_max": max(a["J_max"], b["J_max"]),
            "inverted": a["inverted"] + b["inverted"], "frames": a["frames"] + b["frames"]}


def beyond_training(rng: dict, trained: dict | None, rtol: float = 1e-6) -> list[str]:
    """Where a rollout's range ``rng`` left the range ``trained`` its law's training rollout visited (both
    :func:`state_range`) by more than ``rtol``, one clause each; empty when it stayed inside (or nothing
    was recorded)."""
    if not trained or "deviatoric_stretch_max" not in trained:
        return []
    out = []
    if rng["J_max"] > trained["J_max"] * (1 + rtol):
        out.append(f"J up to {rng['J_max']:.3g} (training: {trained['J_max']:.3g})")
    if rng["J_min"] < trained["J_min"] * (1 - rtol):
        out.append(f"J down to {rng['J_min']:.3g} (training: {trained['J_min']:.3g})")
    if rng["deviatoric_stretch_max"] > trained["deviatoric_stretch_max"] * (1 + rtol) + 1e-12:
        out.append(f"deviatoric log-stretch up to {rng['deviatoric_stretch_max']:.3g} "
                   f"(training: {trained['deviatoric_stretch_max']:.3g})")
    if rng["inverted"] > trained.get("inverted", 0):
        out.append(f"{rng['inverted']} inverted or non-finite particle-frames")
    return out


class RangeTracker:
    """:func:`state_range` accumulated over a rollout's frames without keeping them: ``update(F)`` with one
    frame's F [N, D, D] (``every``-th call only; rollout callbacks pass every frame)."""

    def __init__(self, every: int = 1):
        self.every, self.calls, self.range = max(1, int(every)), 0, None

    def update(self, F) -> None:
        if self.calls % self.every == 0:
            self.range = merge_ranges(self.range, state_range(np.asarray(F)[None]))
        self.calls += 1


def read_state_range(weights_file) -> dict | None:
    """The :func:`state_range` recorded in a weight file's metadata (:func:`write_state_range`), None when
    it records none."""
    import json

    from safetensors import safe_open

    with safe_open(str(weights_file), framework="numpy") as f:
        raw = (f.metadata() or {}).get("state_range")
    return json.loads(raw) if raw else None


def write_state_range(weights_file, rng: dict) -> None:
    """Record ``rng`` (a :func:`state_range`) in a weight file's metadata (``state_range``, JSON), keeping
    its arrays and its other metadata; atomic. The nclaw law's divergence note reads it."""
    import json

    from safetensors import safe_open
    from safetensors.numpy import load_file, save_file

    from ..io.files import write_atomically

    with safe_open(str(weights_file), framework="numpy") as f:
        meta = dict(f.metadata() or {})
    arrays = load_file(str(weights_file))
    meta["state_range"] = json.dumps(rng)
    write_atomically(weights_file, lambda tmp: save_file(arrays, str(tmp), metadata=meta), overwrite=True)


def record_state_range(weights_file, material: str, backend: str = "jax", precision: str = "fp32") -> dict:
    """For a weight file trained before ``task=nclaw_train`` recorded it: roll the learned law out freely
    on ``material``'s training scene (NCLaw's reconstruction case: 1000 steps, no teacher forcing), take
    :func:`state_range` of every 10th frame and write it into the file (:func:`write_state_range`)."""
    from ..config import compose, stepper_from_config
    from ..core.errors import SimulationDiverged
    from .scenes import eval_cases

    case = next(c for c in eval_cases(material) if c.name == "reconstruction")
    _, st = stepper_from_config(compose(case.learned(str(weights_file)) + [
        f"backend={backend}", f"precision={precision}", "output.recording=false"]))
    try:
        traj = st.rollout(steps=case.steps, every=10, fields=("F",))
        rng = state_range(np.asarray(traj.fields["F"])[1:])
    except SimulationDiverged as e:
        rng = {"diverged": True, "step": int(e.step)}
    rng["rollout"] = f"the training scene, {case.steps} steps, no teacher forcing, every 10th frame"
    write_state_range(weights_file, rng)
    return rng


def _start(kind: str, a: float, dim: int) -> np.ndarray:
    """An isochoric F of principal stretch ``a``: uniaxial diag(a, a^(-1/(D-1)), ...) or simple shear
    (gamma = a - 1/a, whose larger singular value is a); or ``dilation``, a I (J = a^D, no deviatoric part)."""
    if kind == "uniaxial":
        return np.diag([a] + [a ** (-1.0 / (dim - 1))] * (dim - 1))
    if kind == "shear":
        F = np.eye(dim)
        F[0, 1] = a - 1.0 / a
        return F
    if kind == "dilation":      # a volume change alone: F = a I, J = a^D (a < 1 compresses)
        return a * np.eye(dim)
    raise ValueError(f"return_map_reach: kind '{kind}' is not uniaxial, shear or dilation")


def return_map_reach(law, weights: Mapping[str, Any], dim: int, stretches: Sequence[float],
                     kinds: Sequence[str] = ("uniaxial", "shear"), steps: int = 400, dt: float = 5e-4,
                     report: Sequence[int] = (1, 10, 50, 400)) -> list[dict]:
    """The law's update iterated ``steps`` times with zero velocity gradient (only the return map acts)
    from each start (:func:`_start`); per (kind, a): the deviatoric stretch and J after the steps in ``report``,
    and ``returned`` (the final deviatoric stretch below a tenth of the initial log a, J finite and
    positive; for ``dilation``, whose start has no deviatoric part, only the latter: read J)."""
    import jax
    import jax.numpy as jnp

    fns, w = _jax_law(law, dim, weights)
    row = jnp.zeros((0,))
    zero = jnp.zeros((dim, dim))
    starts = [(k, float(a), _start(k, float(a), dim)) for k in kinds for a in stretches]
    F = jnp.asarray(np.stack([s for _, _, s in starts]))
    step = jax.jit(jax.vmap(lambda F: fns.update({"F": F}, zero, dt, row, w)["F"]))
    want = sorted({int(r) for r in report if 0 < int(r) <= steps} | {int(steps)})
    seen = {}
    for k in range(1, steps + 1):
        F = step(F)
        if k in want:
            seen[k] = deviatoric_stretch(np.asarray(F))
    out = []
    for i, (kind, a, _) in enumerate(starts):
        rows = {k: {"deviatoric_stretch": float(seen[k][0][i]), "J": float(seen[k][1][i])} for k in want}
        last = rows[want[-1]]
        ok = np.isfinite(last["J"]) and last["J"] > 0 and last["deviatoric_stretch"] <= 0.1 * abs(np.log(a))
        out.append({"kind": kind, "stretch": a, "log_stretch": float(np.log(a)), "after": rows,
                    "returned": bool(ok)})
    return out


def sphere_directions(n: int, dim: int = 3) -> np.ndarray:
    """``n`` unit vectors spread over the sphere (Fibonacci lattice; in 2D: angles k pi / n, half a circle
    suffices since the acoustic tensor is even in n)."""
    if dim == 2:
        t = np.pi * np.arange(n) / n
        return np.stack([np.cos(t), np.sin(t)], axis=1)
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    r = np.sqrt(1.0 - z * z)
    phi = np.pi * (1.0 + 5.0 ** 0.5) * k
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def state_from_F(law, who: str = "probe"):
    """(state of one particle from its F, F from such a state), JAX functions for the F-driven probes: an F-state
    law keeps F (the 3D Hencky laws' plane-strain eps_zz is 0, as in ``baselines.labeled_pairs``), a J-only law
    (WATER's truth) J = det F, whose F is J^(1/D) I; any other law is refused (``who`` names the caller)."""
    import jax.numpy as jnp

    fields = set(law.state_fields)
    if fields == {"J"}:
        return lambda F: {"J": jnp.linalg.det(F)}
    if fields - {"eps_zz"} == {"F"}:
        return lambda F: {"F": F, **({"eps_zz": jnp.zeros(())} if "eps_zz" in fields else {})}
    raise ValueError(f"{who}: law '{law.name}' keeps {sorted(fields)}; it takes F- or J-state laws")


def F_of_state(law, state, dim: int):
    """F of one particle's state (the inverse of :func:`state_from_F`): F, or J^(1/D) I for a J-only law (in 3D
    the real cube root, so an inverted J < 0 stays an inverted F)."""
    import jax.numpy as jnp

    if "F" in state:
        return state["F"]
    root = jnp.cbrt(state["J"]) if dim == 3 else jnp.power(state["J"], 1.0 / dim)
    return root * jnp.eye(dim)


def acoustic_minimum(law, weights: Mapping[str, Any], dim: int, F, dt: float = 5e-4, row=None,
                     directions: int = 200, chunk: int = 512, largest: bool = False) -> np.ndarray:
    """Per state F [M, D, D]: the smallest eigenvalue [Pa] over ``directions`` unit vectors n of the acoustic
    tensor Q_ik(n) = K_ijkl n_j n_l of one explicit step's response, K = d tau(Z((I + L) F)) / dL at L = 0, with
    Z the law's update at zero velocity gradient (its return map) and tau its Kirchhoff stress: how the stress
    the next P2G spreads answers a small displacement gradient L of the current configuration. A negative
    value is a loss of strong ellipticity: a wave of normal n grows, whatever dt (material instability, not
    CFL). The initial-stress (geometric) term is left out: it is of the order of tau, small beside the moduli
    at the strains here. ``row``: the law's parameters in declared order (a learned nclaw law has none); a
    J-only law (WATER's truth) gets J = det F, and the 3D Hencky laws' plane-strain eps_zz is 0. ``largest``:
    the largest eigenvalue over the directions instead (at F = I: the P-wave modulus, a scale for the rest)."""
    import jax
    import jax.numpy as jnp

    fns, w = _jax_law(law, dim, weights)
    row = jnp.zeros((0,)) if row is None else jnp.asarray(np.asarray(row, np.float64))
    zero = jnp.zeros((dim, dim))
    n = jnp.asarray(sphere_directions(directions, dim))
    state_of = state_from_F(law, "acoustic_minimum")

    def stress_after_step(L, F0):
        Ft = (jnp.eye(dim) + L) @ F0
        return fns.kirchhoff(fns.update(state_of(Ft), zero, dt, row, w), row, w)

    def qmin(F0):
        K = jax.jacfwd(stress_after_step)(zero, F0)             # [i, j, k, l]: d tau_ij / d L_kl
        Q = jnp.einsum("ijkl,nj,nl->nik", K, n, n)              # per direction: Q_ik
        Q = 0.5 * (Q + jnp.swapaxes(Q, 1, 2))                   # its symmetric part decides the growth
        ev = jnp.linalg.eigvalsh(Q)
        return jnp.max(ev) if largest else jnp.min(ev)

    f = jax.jit(jax.vmap(qmin))
    F = np.asarray(F, np.float64)
    return np.concatenate([np.asarray(f(jnp.asarray(F[i:i + chunk]))) for i in range(0, len(F), chunk)])
