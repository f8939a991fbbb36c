"""A study, not a feature: does a deformation map that holds the attachment *by construction* remove the
gravity study's transient error (benchmarks/rom.md, "What the gravity online error is made of")?

The paper's g is X + u~(X~, x_hat) * u_std + u_mean: nothing keeps the held points at rest, and in the
reduced model they leak (up to 0.46 mm). Here, for this study only, the map becomes

    x = X + phi(X) (u~ u_std + u_mean),   phi = 1 - exp(-s / L) for s > 0, else 0,

where s is the distance along the body's long axis past the plane between the scene's particle_velocity
(held) points and the next layer, and L one grid cell: the held points never move, for any latent. It is
done by wrapping ``mpmlab.rom.networks.g_mlp`` (every position, F and Jacobian of g goes through it, so
forward-mode derivatives stay exact), in this process only; the weight file does not record phi, so the weights it writes are only meaningful here. Training
(``mpmlab.rom.train.fit``, checkpointed: rerun to resume) and the evaluation (Lagrangian quadrature, all
points, linear projection, the test runs, E pooled as ``rom_eval``'s) run in this one process.

    python benchmarks/rom_held_map.py --tag gravity_held_lf100_p480_e85 --lambda-F 100 --seed 0
    python benchmarks/rom_held_map.py --tag gravity_held_lf100_p480_e85 --diagnose energy --runs g26

``--diagnose WHAT`` runs ``benchmarks/rom_diagnose.py``'s WHAT (swing, energy, equilibrium, consistency,
...) on the trained held map instead of evaluating it.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
import rom_diagnose as D  # noqa: E402

RES = ROOT / "benchmarks" / "results" / "rom"
DATA = ROOT / "benchmarks" / "out" / "rom" / "data" / "gravity_default_fp64"


def held_factor(X_min, X_max, u_mean, u_std, axis, end, length):
    """Wrap g's MLP so that g = X + phi(X) (u~ u_std + u_mean) (module doc): the wrapped MLP returns
    phi u~ + (phi - 1) u_mean / u_std, which the networks' standardiser turns into phi (u~ u_std + u_mean)."""
    import jax.numpy as jnp

    from mpmlab.rom import networks as N

    inner = N.g_mlp
    span = float(X_max[axis] - X_min[axis])

    def g_mlp(params, inp):
        d = len(u_std)
        s = inp[..., inp.shape[-1] - d + axis] * span + float(X_min[axis]) - end       # metres past the hold
        phi = jnp.where(s > 0, -jnp.expm1(-jnp.maximum(s, 0.0) / length), 0.0)[..., None]
        return phi * inner(params, inp) + (phi - 1.0) * (jnp.asarray(u_mean) / jnp.asarray(u_std))
    N.g_mlp = g_mlp


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tag", required=True)
    ap.add_argument("--lambda-F", dest="lambda_F", type=float, default=100.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--points", type=int, default=480)
    ap.add_argument("--schedule-scale", dest="schedule_scale", type=float, default=0.1)
    ap.add_argument("--data", default=str(DATA))
    ap.add_argument("--diagnose", default="", help="a benchmarks/rom_diagnose.py subcommand to run on the trained map")
    ap.add_argument("--runs", default="g26", help="--diagnose: comma-separated runs")
    a = ap.parse_args()

    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    from mpmlab.core.errors import SimulationDiverged
    from mpmlab.rom import networks as N
    from mpmlab.rom.evaluate import _sums, build_full_order, errors_of, run_config
    from mpmlab.rom.snapshots import load_snapshots, study
    from mpmlab.rom.train import TrainingSet, TrainOptions, fit

    s = study("gravity")
    train = load_snapshots(a.data, s, runs=tuple(s.train))
    data = TrainingSet.from_snapshots(train)
    _, fom0 = build_full_order(run_config(train, 0), "fp64")
    held = D.held_points(fom0)
    axis = int(np.argmax(np.ptp(data.X, 0)))
    end = 0.5 * (data.X[held, axis].max() + data.X[~held, axis].min())               # between the layers
    norm = N.fit_norm(data.X, data.x)
    held_factor(norm["X_min"], norm["X_max"], norm["u_mean"], norm["u_std"], axis, end, float(fom0.scene.dx))

    out = RES / a.tag
    out.mkdir(parents=True, exist_ok=True)
    opt = TrainOptions(latent=4, lambda_F=a.lambda_F, lambda_v=0.01, batch=8, schedule_scale=a.schedule_scale,
                       points=a.points, seed=a.seed)
    weights, history = fit(data, opt, out / "train_checkpoint.pkl")
    if len(history) < opt.total_epochs:
        raise SystemExit(f"stopped at epoch {len(history)} of {opt.total_epochs}; rerun to continue")
    params, nrm = N.to_jax(weights.params, jnp.float64), N.to_jax(weights.norm, jnp.float64)
    if a.diagnose:
        da = argparse.Namespace(runs=a.runs.split(","), projection="linear", frame=-1, hold=0.1, dt_scale=1.0,
                                start="eq19", rcond=0.0, boundary_weight=1.0, transfers=["pic"])
        getattr(D, a.diagnose.replace("-", "_"))(da, weights, params, nrm, load_snapshots(a.data, s, split=None))
        return

    test = load_snapshots(a.data, s, runs=tuple(s.test))
    rows, total = [], None
    for k, name in enumerate(test.names):
        X = test.x[k, 0]
        try:
            _, _, o = D.reduced_rollout(weights, test, k)
        except SimulationDiverged as err:
            rows.append({"run": name, "diverged_at_step": err.step})
            print(f"{name}: diverged at step {err.step}", flush=True)
            continue
        _, sums = _sums(params, nrm, X, o["z"], o["zdot"], test.x[k], test.v[k], test.F[k], X.mean(0))
        xr = np.asarray(N.g_apply(params, nrm, jnp.asarray(X)[None], jnp.asarray(o["z"])[:, None, :]))
        leak = 1e3 * float(np.sqrt(np.mean(np.sum((xr - X)[:, held] ** 2, -1), -1)).max())
        rows.append({"run": name, "E": errors_of(sums)["E"], "E_F": errors_of(sums)["E_F"], "held_leak_mm": leak})
        total = dict(sums) if total is None else {q: total[q] + sums[q] for q in total}
        print(f"{name}: E {rows[-1]['E']:.2%}, E_F {rows[-1]['E_F']:.1%}, held points' peak rms displacement "
              f"{leak:.2e} mm", flush=True)
    if total is None:
        raise SystemExit(f"{a.tag}: every test run diverged")
    e = errors_of(total)
    commit = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "HEAD"], capture_output=True, text=True).stdout.strip()
    summary = {"tag": a.tag, "commit": commit, "schedule": [list(st) for st in opt.epochs()], "lambda_F": a.lambda_F,
               "seed": a.seed, "points": a.points, "epochs": opt.total_epochs,
               "hold_end_m": end, "hold_length_m": float(fom0.scene.dx), "final_loss": history[-1]["loss"],
               "E": e["E"], "E_F": e["E_F"], "E_v": e["E_v"],
               "diverged": sum("diverged_at_step" in r for r in rows), "rows": rows}
    (out / "held_map.json").write_text(json.dumps(summary, indent=1))
    print(f"{a.tag}: pooled E {e['E']:.2%}, E_F {e['E_F']:.1%} (Lagrangian + linear, all points, 6 test runs)")


if __name__ == "__main__":
    main()
