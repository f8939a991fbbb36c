"""Online evaluation of the deformation-map ROM (Chen et al. 2023, Sec. 5): the reduced model of each test
run, stepped from its initial state (Eq. 19) by ``ReducedStepper`` and compared with the run's full-order
snapshots, for any quadrature x projection x sample-count scheme.

Errors, pooled over test runs, snapshots (the initial one included) and points:

* ``E`` (the paper's, below Eq. 24): sqrt(sum |x_ROM - x_FOM|^2 / sum |x_FOM - c|^2), c the initial
  centroid of the body. The paper states no origin (its release uses 5 m per axis); the value depends
  on it, so it is fixed here and the displacement-relative error is given beside it;
* ``E_corner``: the same about the scene domain's lower corner instead of the centroid. The paper's
  numbers are consistent with an origin of that kind (a few body sizes away), not with the centroid
  (``benchmarks/rom.md``, "The error's origin"); on the paper's scenes here (gravity, torsion, poke) it is 0.22-0.32 x ``E``;
* ``E_displacement``: sqrt(sum |x_ROM - x_FOM|^2 / sum |x_FOM - X|^2);
* ``E_v``: sqrt(sum |v_ROM - v_FOM|^2 / sum |v_FOM|^2);
* ``E_F``: sqrt(sum |F_ROM - F_FOM|_F^2 / sum |F_FOM - I|_F^2) (relative to the deformation, not to |F|,
  which would hide it behind the identity).

x_ROM, v_ROM, F_ROM are g(X; x_hat), dg/dx_hat v_hat and dg/dX at the truth's reference points X, so the
truth may be a finer full-order run of the same parameters (super-resolution, Sec. 5.2.1): ``truth``.

Each run's scene is rebuilt from the config its ``trajectory.h5`` records (the same scene, resolution
and dt as the snapshots), with the PIC transfer (Alg. 5), on the reduced model's backend (JAX or Warp).
The ROM's time step defaults to the FOM's; another ``dt`` must divide the snapshot interval, and is not held to the FOM's CFL limit (an unstable
one ends in ``SimulationDiverged``). Wall times: the reduced rollout (after one compiled warm-up step)
and ``fom_timing_steps`` steps of the full-order model of the same scene in the same process, both per
simulated second.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from ..core.errors import ConfigError
from . import networks as N

#: the sums an error is made of (numerator key, denominator key)
_SUMS = {"E": ("x", "x_c"), "E_corner": ("x", "x_o"), "E_displacement": ("x", "u"), "E_v": ("v", "v_ref"),
         "E_F": ("F", "F_I")}


@dataclass(frozen=True)
class Scheme:
    """One online configuration: quadrature (lagrangian | eulerian), projection (linear | nonlinear) and
    the number of sample points |M| (an int, or ``"all"``)."""

    quadrature: str
    projection: str
    samples: object

    @property
    def label(self) -> str:
        return f"{self.quadrature}+{self.projection}, M={self.samples}"


def schemes(quadratures, projections, samples) -> list[Scheme]:
    """Every combination, in the order given."""
    out = []
    for q in quadratures:
        for p in projections:
            for m in samples:
                out.append(Scheme(str(q), str(p), m if m == "all" else int(m)))
    return out


def run_config(snap, k: int):
    """The composed config (an OmegaConf DictConfig) run ``k`` of ``snap`` recorded in its trajectory.h5."""
    from ..config import recorded_config

    text = snap.attrs[k].get("config_yaml") or ""
    if not text:
        raise ConfigError(f"'{snap.paths[k]}' records no config; the ROM cannot rebuild its scene.")
    return recorded_config(text)


def build_full_order(cfg, precision: str, dt: float | None = None, backend: str = "jax"):
    """(scene, stepper) of a recorded run's config with the PIC transfer; ``dt`` replaces the scene's
    (and lifts its CFL limit: the reduced model's stability is measured, not assumed)."""
    from ..build import build_scene
    from ..simulator import build_stepper

    if dt is not None:
        cfg = cfg.copy()
        cfg.scene.dt = float(dt)
        cfg.scene.cfl_limit = float("inf")
    scene = build_scene(cfg)
    return scene, build_stepper(scene, backend, "pic", precision)


#: points (snapshots x material points) per evaluation of g and its Jacobians in ``_sums``: forward mode over
#: g's inputs keeps ~10 tangents of every hidden layer, ~2 kB per point; the 30 s continual poke (4,321
#: snapshots x 1,600 points) in one call needed 17.7 GB and was killed
SUM_CHUNK_POINTS = 200_000


def _sums(params, norm, X, z, zdot, x, v, F, c, corner=None):
    """The error sums of one run, (per snapshot, in all): x, v, F of g at (X, z, zdot) against the truth's
    ``[T, N, ...]``, in chunks of snapshots (``SUM_CHUNK_POINTS``)."""
    import jax.numpy as jnp

    z, zdot, Xj = np.asarray(z), np.asarray(zdot), jnp.asarray(X)[None]
    step = max(1, SUM_CHUNK_POINTS // max(1, len(X)))
    per_frame, total = {}, {}
    for a in range(0, len(z), step):
        b = slice(a, a + step)
        xr, Fr, vr = N.g_state(params, norm, Xj, jnp.asarray(z[b])[:, None, :],
                               jnp.asarray(zdot[b])[:, None, :])
        pf, tot = error_sums(np.asarray(xr), np.asarray(vr), np.asarray(Fr), x[b], v[b], F[b], X, c, corner)
        for key, val in pf.items():
            per_frame.setdefault(key, []).extend(val)
        for key, val in tot.items():
            total[key] = total.get(key, 0.0) + val
    return per_frame, total


def domain_corner(cfg) -> np.ndarray:
    """The lower corner of a run's scene domain (``scene.domain.lo``), the origin of ``E_corner``."""
    return np.asarray(list(cfg.scene.domain.lo), dtype=float)


def error_sums(xr, vr, Fr, x, v, F, X, c, corner=None):
    """The error sums of one run, (per snapshot, in all): predicted x, v, F ``[T, N, ...]`` against the
    truth's, with the truth's reference positions X, initial centroid c and the domain's lower corner
    (None: no ``E_corner``)."""
    eye = np.eye(X.shape[1])
    per_frame = {"x": np.sum((xr - x) ** 2, axis=(1, 2)).tolist(), "x_c": np.sum((x - c) ** 2, axis=(1, 2)).tolist()}
    total = {"x": float(np.sum((xr - x) ** 2)), "x_c": float(np.sum((x - c) ** 2)),
             "u": float(np.sum((x - X) ** 2)), "v": float(np.sum((vr - v) ** 2)), "v_ref": float(np.sum(v ** 2)),
             "F": float(np.sum((Fr - F) ** 2)), "F_I": float(np.sum((F - eye) ** 2))}
    if corner is not None:
        total["x_o"] = float(np.sum((x - np.asarray(corner)) ** 2))
    return per_frame, total


def latent_return(z) -> float | None:
    """How far x_hat ends from where it started, relative to its largest excursion: |x_hat(T) - x_hat(0)| /
    max_t |x_hat(t) - x_hat(0)| (Fig. 14's "return property": 0 when a poked body's latent comes back to
    its start; None when x_hat never moved)."""
    z = np.asarray(z, float)
    far = float(np.max(np.linalg.norm(z - z[0], axis=1)))
    return float(np.linalg.norm(z[-1] - z[0]) / far) if far > 0 else None


def latent_pca(z) -> tuple[np.ndarray, np.ndarray]:
    """(the trajectory x_hat(t) [T, d_hat] on its first two principal components [T, 2], their share of
    the variance [2]): Fig. 14's view of a reduced rollout."""
    z = np.asarray(z, float)
    c = z - z.mean(axis=0)
    _, sv, vt = np.linalg.svd(c, full_matrices=False)
    k = min(2, vt.shape[0])
    share = sv[:k] ** 2 / max(float(np.sum(sv ** 2)), np.finfo(float).tiny)
    proj = c @ vt[:k].T
    if k < 2:
        proj, share = np.pad(proj, ((0, 0), (0, 2 - k))), np.pad(share, (0, 2 - k))
    return proj, share


def errors_of(sums: dict) -> dict:
    """The ``_SUMS`` errors of pooled sums (None where a denominator is 0 or, in sums of an older version,
    missing)."""
    return {k: (math.sqrt(sums[a] / sums[b]) if sums.get(b, 0) > 0 else None) for k, (a, b) in _SUMS.items()}


def evaluate(weights: N.RomWeights, snap, scheme_list, *, precision: str = "fp64", dt: float | None = None,
             seed: int = 0, truth=None, fom_timing_steps: int = 100, fom_backend: str = "jax",
             backend: str = "jax", progress: bool | None = False, log=None, eulerian_capacity: float | None = None,
             tangent: str = "next", kinematic: str = "position", hold_steps: float = 1.0) -> dict:
    """Every scheme on every run of ``snap`` (``mpmlab.rom.snapshots.load_snapshots``' result: the test
    runs). ``truth``: snapshots of the same runs to compare against (default ``snap``; e.g. a 2x finer
    FOM). ``backend``: the reduced model's (jax: ``ReducedStepper``; warp: ``WarpReducedStepper``; both
    have every scheme). ``eulerian_capacity``: the Eulerian quadrature's point budget (None: the stepper's
    default, ``mpmlab.rom.stepper.EULER_CAPACITY``). ``tangent``: where the velocity least squares takes
    dg/dx_hat (``mpmlab.rom.stepper.TANGENTS``: "next", or the paper's "current"). ``kinematic``: how the
    particle_velocity boundaries are held (``mpmlab.rom.kinematic``: "position", or "velocity"), and over how
    many steps the position-level hold closes an error (``hold_steps``). ``progress``: a bar
    over the rollouts (None: when stderr is a terminal). Returns
    ``{"schemes": [...], "runs": [...], "fom": {...}}`` (module doc)."""
    import jax.numpy as jnp

    from tqdm.auto import tqdm

    from ..core.errors import SimulationDiverged
    from ..simulator import build_stepper
    from .stepper import reduced_stepper

    if backend not in ("jax", "warp"):
        raise ConfigError(f"rom_eval: backend '{backend}'; choose jax or warp.")
    truth = snap if truth is None else truth
    if tuple(truth.names) != tuple(snap.names):
        raise ConfigError(f"rom_eval: the truth's runs {list(truth.names)} are not the test runs {list(snap.names)}.")
    R, T = snap.x.shape[:2]
    if truth.x.shape[1] != T or not np.allclose(truth.time, snap.time, rtol=1e-6, atol=1e-9):
        raise ConfigError(f"rom_eval: the truth keeps {truth.x.shape[1]} snapshots up to t = {truth.time[-1]:.6g} s, "
                          f"the test runs {T} up to {snap.time[-1]:.6g} s; they must share the snapshot times.")
    interval = float(snap.time[1] - snap.time[0]) if T > 1 else 0.0
    rows, runs, fom_rows = [], [], []
    if precision == "fp64":       # before any array is made: without it the error sums' networks ran in float32
        import jax

        jax.config.update("jax_enable_x64", True)
    dtype = jnp.float64 if precision == "fp64" else jnp.float32
    params, norm = N.to_jax(weights.params, dtype), N.to_jax(weights.norm, dtype)
    bar = tqdm(total=R * len(scheme_list), unit="rollout", desc="rom_eval", leave=False,
               disable=None if progress is None else not progress)
    for k in range(R):
        cfg = run_config(snap, k)
        scene, fom = build_full_order(cfg, precision, dt, backend)
        X0 = np.asarray(fom.particles.x)
        tol = (1e-9 if snap.x.dtype == np.float64 else 1e-5) * max(1.0, float(np.abs(X0).max(initial=0.0)))
        if X0.shape != snap.x[k, 0].shape or not np.allclose(X0, snap.x[k, 0], rtol=0, atol=tol):
            raise ConfigError(f"rom_eval: run {snap.names[k]}'s rebuilt scene has {len(X0)} points that are not its "
                              f"snapshots' first frame ({snap.x.shape[2]} points): the scene changed since it was run.")
        step_dt = float(fom.dt)
        every = interval / step_dt if interval else 1.0
        if abs(every - round(every)) > 1e-6 * every:
            raise ConfigError(f"rom_eval: dt = {step_dt:g} s does not divide the snapshot interval {interval:g} s; "
                              f"choose dt = {interval:g} / n.")
        every = max(1, int(round(every)))
        steps = every * (T - 1)
        Xt = truth.x[k, 0]
        c = truth.x[k, 0].mean(axis=0)
        timed = fom if fom_backend == backend else build_stepper(scene, fom_backend, "pic", precision)
        fom_rows.append(_time_full_order(timed, min(int(fom_timing_steps), steps), every))
        for sch in scheme_list:
            m = len(X0) if sch.samples == "all" else int(sch.samples)
            more = {} if eulerian_capacity is None else {"eulerian_capacity": float(eulerian_capacity)}
            rom = reduced_stepper(fom, weights, samples=m, quadrature=sch.quadrature, projection=sch.projection,
                                  seed=seed, tangent=tangent, kinematic=kinematic,
                                  hold_steps=hold_steps, **more)
            s0 = rom.init()
            t0 = time.perf_counter()
            rom._np(rom.step(s0).z)                              # compile the reduced step
            compile_s = time.perf_counter() - t0
            t0 = time.perf_counter()
            status, why, at, partial = "ok", "", None, None
            try:
                out = rom.rollout(s0, steps=steps, every=every)
            except SimulationDiverged as e:
                status, why, at, partial = "diverged", str(e), e.step, getattr(e, "partial", None)
            wall = time.perf_counter() - t0
            row = {"run": snap.names[k], "params": dict(zip(snap.param_names, map(float, snap.params[k]))),
                   "scheme": sch.label, "quadrature": sch.quadrature, "projection": sch.projection,
                   "samples": m, "dt": step_dt, "steps": steps, "status": status,
                   "compile_s": compile_s, "wall_s": wall,
                   "wall_s_per_simulated_s": wall / (steps * step_dt) if steps else None}
            if status == "ok":
                per_frame, sums = _sums(params, norm, Xt, out["z"], out["zdot"], truth.x[k], truth.v[k],
                                        truth.F[k], c, domain_corner(cfg))
                row.update(sums=sums, per_frame=per_frame, **errors_of(sums), outside=int(out["state"].outside),
                           unconverged=int(out["state"].unconverged), z=out["z"].tolist(),
                           latent_return=latent_return(out["z"]))
            else:
                row.update(message=why, diverged_at_step=at)
                if partial is not None and len(partial["z"]) > 1:    # the errors over the frames before it
                    n = len(partial["z"])
                    per_frame, sums = _sums(params, norm, Xt, partial["z"], partial["zdot"], truth.x[k, :n],
                                            truth.v[k, :n], truth.F[k, :n], c, domain_corner(cfg))
                    row["before_divergence"] = {"frames": n, "until_s": float(partial["time"][-1]), **errors_of(sums),
                                                "per_frame": per_frame}
            rows.append(row)
            bar.update()
            if log is not None:
                e = row.get("E")
                log.info("rom_eval %s %s: %s%s, %.3g s per simulated s", snap.names[k], sch.label, status,
                         "" if e is None else f" E = {e:.3%}", row["wall_s_per_simulated_s"] or float("nan"))
        runs.append(snap.names[k])
    bar.close()
    table = []
    for sch in scheme_list:
        mine = [r for r in rows if r["scheme"] == sch.label]
        ok = [r for r in mine if r["status"] == "ok"]
        pooled = {key: sum(r["sums"][key] for r in ok) for key in ok[0]["sums"]} if ok else None
        wall = sum(r["wall_s"] for r in mine)
        sim = sum(r["steps"] * r["dt"] for r in mine)
        table.append({"scheme": sch.label, "quadrature": sch.quadrature, "projection": sch.projection,
                      "samples": sch.samples, "runs": len(mine), "diverged": len(mine) - len(ok),
                      **(errors_of(pooled) if pooled and len(ok) == len(mine) else {k: None for k in _SUMS}),
                      "wall_s_per_simulated_s": wall / sim if sim else None,
                      "latent_return": max((r["latent_return"] for r in ok if r["latent_return"] is not None),
                                           default=None)})
    fom_wall = sum(f["wall_s"] for f in fom_rows)
    fom_sim = sum(f["simulated_s"] for f in fom_rows)
    fom = {"backend": fom_backend, "rom_backend": backend, "transfer": "pic", "precision": precision, "timed_steps": [f["steps"] for f in fom_rows],
           "wall_s_per_simulated_s": fom_wall / fom_sim if fom_sim else None}
    for row in table:
        a, b = row["wall_s_per_simulated_s"], fom["wall_s_per_simulated_s"]
        row["speedup_vs_fom"] = b / a if a and b else None
    return {"schemes": table, "rows": rows, "runs": runs, "fom": fom, "tangent": tangent, "kinematic": kinematic, "hold_steps": hold_steps, "snapshot_interval": interval,
            "snapshots": T}


def tracer_baseline(snap, truth, *, precision: str = "fp64", backend: str = "jax", progress: bool | None = False,
                    log=None) -> dict:
    """Tab. 4's baseline (Sec. 5.2.1, the "tracer particle technique"): the truth's finer points advected
    as massless tracers (``Body(tracer=True)``) through each coarse full-order run of ``snap``, scored
    against the finer truth with the ROM's error sums. The tracers are each coarse body refined by the
    ratio of the two scenes' cell widths per axis (regular sampling: the finer run's own points); when
    they are not the truth's points (another sampling), a ConfigError says so. Returns ``{"E", ...,
    "sums", "runs", "wall_s_per_simulated_s"}``."""
    import dataclasses

    from tqdm.auto import tqdm

    from ..build import build_scene
    from ..simulator import build_stepper

    if tuple(truth.names) != tuple(snap.names):
        raise ConfigError(f"tracer baseline: the truth's runs {list(truth.names)} are not the test runs {list(snap.names)}.")
    R, T = snap.x.shape[:2]
    interval = float(snap.time[1] - snap.time[0]) if T > 1 else 0.0
    total, rows = None, []
    for k in tqdm(range(R), unit="run", desc="tracers", leave=False, disable=None if progress is None else not progress):
        cfg = run_config(snap, k)
        coarse = build_scene(cfg)
        fine_dx = float(run_config(truth, k).scene.dx)
        r = coarse.dx / fine_dx
        if abs(r - round(r)) > 1e-9 * r or round(r) < 1:
            raise ConfigError(f"tracer baseline: the truth's cell width {fine_dx:g} m is not the coarse {coarse.dx:g} m "
                              f"divided by an integer.")
        r = int(round(r))
        tracers = [dataclasses.replace(b, particles_per_cell=b.particles_per_cell * r ** coarse.dim, tracer=True,
                                       name=f"{b.name or i}_tracers")
                   for i, b in enumerate(coarse.bodies) if not b.tracer]
        scene = dataclasses.replace(coarse, bodies=list(coarse.bodies) + tracers)
        stepper = build_stepper(scene, backend, "pic", precision)
        every = max(1, int(round(interval / float(stepper.dt)))) if interval else 1
        t0 = time.perf_counter()
        traj = stepper.rollout(steps=every * (T - 1), every=every, fields=("F",))
        wall = time.perf_counter() - t0
        mine = np.nonzero(traj.body_id >= len(coarse.bodies))[0]
        X, Xt = traj.x[0][mine], truth.x[k, 0]
        if len(X) != len(Xt):
            raise ConfigError(f"tracer baseline: {len(X)} tracers, but the truth has {len(Xt)} points; its points are "
                              f"not the coarse bodies refined {r}x per axis.")
        from scipy.spatial import cKDTree

        dist, order = cKDTree(X).query(Xt)
        if dist.max() > 1e-9 * max(1.0, float(np.abs(Xt).max())) or len(set(order)) != len(order):
            raise ConfigError(f"tracer baseline: the truth's points are not the coarse bodies refined {r}x per axis "
                              f"(largest distance {dist.max():.3g} m); only regularly sampled truths are supported.")
        idx = mine[order]
        c = Xt.mean(axis=0)
        _, sums = error_sums(traj.x[:, idx], traj.v[:, idx], traj.fields["F"][:, idx], truth.x[k], truth.v[k],
                             truth.F[k], Xt, c, domain_corner(cfg))
        total = sums if total is None else {key: total[key] + sums[key] for key in sums}
        rows.append({"run": snap.names[k], "tracers": len(idx), "wall_s": wall, **errors_of(sums)})
        if log is not None:
            log.info("tracer baseline %s: %d tracers, E = %.3f%%", snap.names[k], len(idx), 100 * rows[-1]["E"])
    sim = R * (T - 1) * interval
    return {**errors_of(total), "sums": total, "runs": rows,
            "wall_s_per_simulated_s": sum(r["wall_s"] for r in rows) / sim if sim else None}


def _time_full_order(fom, steps, chunk):
    """Wall time of about ``steps`` steps of the full-order stepper ``fom`` (PIC), advanced ``chunk`` steps
    (one snapshot interval) per call as a rollout does, after a compiled warm-up chunk."""
    chunk = max(1, min(int(chunk), int(steps) or 1))
    n = max(1, int(math.ceil(int(steps) / chunk))) if steps else 0
    s = fom._advance(fom.init(), chunk)
    fom._block(s)
    t0 = time.perf_counter()
    for _ in range(n):
        s = fom._advance(s, chunk)
    fom._block(s)
    wall = time.perf_counter() - t0
    return {"steps": n * chunk, "wall_s": wall, "simulated_s": n * chunk * float(fom.dt)}
