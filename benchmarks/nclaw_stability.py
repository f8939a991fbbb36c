"""Do the learned laws that diverge on NCLaw (c) lose ellipticity where the ones that run do not? (issue 15)

    python benchmarks/nclaw_stability.py            # every full-schedule JAX training and the true laws (~10 min)
    python benchmarks/nclaw_stability.py --report   # only rewrite the section from the JSON

-> ``benchmarks/nclaw.md`` (section ``nclaw-stability``) and ``benchmarks/results/nclaw_stability.json``.

For each law, :func:`mpmlab.nclaw.probe.acoustic_minimum`: the smallest eigenvalue over 200 directions of the
acoustic tensor of one explicit step's stress response (the return map, then the elastic net) to a small
displacement gradient, on

* the training's own states: 1,000 deformation gradients of its ground-truth trajectory (every 10th frame,
  particles drawn with PCG64(0)), where the law was fitted;
* a ladder of states outside them: F = J^(1/3) diag(a, a^(-1/2), a^(-1/2)) (uniaxial) and J^(1/3) (I + gamma e1 e2^T)
  with gamma = a - 1/a (simple shear), log a in 0.1 ... 0.5, J in 0.8, 1, 1.2.

Two multi-step and stiffness measures beside it: the return map's reach (:func:`mpmlab.nclaw.probe.return_map_reach`,
400 steps at zero velocity gradient from isochoric uniaxial and shear stretches a = 1.1 ... 2.35: how many of the 16
come back), and the largest CFL number dt sqrt(q_max / rho) / dx of the (c) scene (dt 5e-4 s, dx 1/32 m, rho 1000)
over a wider ladder (log a up to 1, J 0.6 ... 1.5), q_max the acoustic tensor's largest eigenvalue: does the law
stiffen past the explicit step's bound where the training never went?

Values are divided by the same law's largest eigenvalue at F = I (its rest P-wave modulus), so the true law is the
reference:
a ratio below 0 is a loss of strong ellipticity (a wave grows whatever dt); the true elastoplastic laws reach 0
(perfect plasticity, cohesionless tension), not below. The (c) outcome is read from ``nclaw_draws``.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from _harness import OUT, RESULTS, log, md_table, parser, read_json, write_json, write_readme_section
from nclaw_draws import PAPER_C, TRAININGS, draw0, result, weights

MD = Path(__file__).resolve().parent / "nclaw.md"
JSON = RESULTS / "nclaw_stability.json"
DATA = OUT / "nclaw" / "data"
LOG_A = (0.1, 0.2, 0.3, 0.5)
JS = (0.8, 1.0, 1.2)
REACH = (1.1, 1.2, 1.35, 1.5, 1.65, 1.8, 2.0, 2.35)
#: the wider ladder of the stiffness measure, and the (c) scene's step, cell and density
WIDE_LOG_A, WIDE_JS = (0.0, 0.2, 0.4, 0.6, 0.8, 1.0), (0.6, 0.8, 1.0, 1.2, 1.5)
C_DT, C_DX, C_RHO = 5e-4, 1.0 / 32, 1000.0


def ladder(log_a=LOG_A, js=JS) -> tuple[np.ndarray, list[tuple[str, float, float]]]:
    Fs, tags = [], []
    for kind in ("uniaxial", "shear"):
        for la in log_a:
            a = float(np.exp(la))
            if kind == "uniaxial":
                F = np.diag([a, a ** -0.5, a ** -0.5])
            else:
                F = np.eye(3)
                F[0, 1] = a - 1.0 / a
            for J in js:
                Fs.append(J ** (1.0 / 3.0) * F)
                tags.append((kind, la, J))
    return np.stack(Fs), tags


def training_states(ds, n: int = 1000) -> np.ndarray:
    F = np.asarray(ds.F[::10], np.float64).reshape(-1, 3, 3)
    rng = np.random.Generator(np.random.PCG64(0))
    return F[rng.choice(len(F), size=min(n, len(F)), replace=False)]


def probe(law, w, F_train, F_ladder, tags, dt, row=None) -> dict:
    from mpmlab.nclaw.probe import acoustic_minimum, return_map_reach

    # one call (one compile) per eigenvalue kind: the smallest at F = I, the training states and the ladder;
    # the largest at F = I and over the wide ladder
    F_wide, _ = ladder(WIDE_LOG_A, WIDE_JS)
    q_min = acoustic_minimum(law, w, 3, np.concatenate([np.eye(3)[None], F_train, F_ladder]), dt=dt, row=row)
    q_max = acoustic_minimum(law, w, 3, np.concatenate([np.eye(3)[None], F_wide]), dt=dt, row=row, largest=True)
    q_min0, q0 = float(q_min[0]), float(q_max[0])
    qt, ql = q_min[1:1 + len(F_train)] / q0, q_min[1 + len(F_train):] / q0
    out = {"q_rest_Pa": q0, "q_min_rest_Pa": q_min0, "train_negative_share": float(np.mean(qt < -1e-6)),
           "train_p1": float(np.percentile(qt, 1)), "train_min": float(qt.min())}
    for lim in LOG_A:
        sel = [i for i, t in enumerate(tags) if t[1] <= lim + 1e-12]
        out[f"ladder_min_loga{lim}"] = float(ql[sel].min())
    out["ladder"] = [[*t, float(v)] for t, v in zip(tags, ql)]
    reach = return_map_reach(law, w, 3, REACH, steps=400, dt=dt, report=(400,)) if row is None else []
    out["returned"] = [sum(r["returned"] for r in reach), len(reach)]
    out["cfl_rest"] = C_DT * float(np.sqrt(max(q0, 0.0) / C_RHO)) / C_DX
    out["cfl_wide_max"] = C_DT * float(np.sqrt(max(float(q_max[1:].max()), 0.0) / C_RHO)) / C_DX
    return out


def outcome(material: str, run: str) -> str:
    rs = [draw0(run, material)] + [result(material, run, v) for v in ("draw1", "draw2", "lattice")]
    rs = [r for r in rs if r is not None]
    if not rs:
        return "–"
    bad = sum(r["status"] != "ok" for r in rs)
    ok = [r["mse"] / PAPER_C[material] for r in rs if r["status"] == "ok"]
    if bad == len(rs):
        return f"diverges ({bad} of {len(rs)} particle sets)"
    if bad:
        return f"diverges on {bad} of {len(rs)}; {min(ok):.2f}-{max(ok):.2f}x on the rest"
    return f"{min(ok):.2f}-{max(ok):.2f}x Tab. 2 ({len(rs)} particle sets)"


def measure(res: dict) -> None:
    from safetensors.numpy import load_file

    from mpmlab.laws.nclaw import Law
    from mpmlab.nclaw.baselines import true_law
    from mpmlab.nclaw.data import load_dataset

    F_ladder, tags = ladder()
    for material, runs in TRAININGS.items():
        if all(k in res for k in [f"{material}|truth"] + [f"{material}|{label}" for label, run in runs
                                                          if weights(run, material) is not None]):
            continue
        ds = load_dataset(DATA / material / "trajectory.h5")
        F_train = training_states(ds)
        dt = float(ds.dt)
        key = f"{material}|truth"
        if key not in res:
            law, rows = true_law(ds)
            res[key] = probe(law, {k: np.asarray(a) for k, a in law.initial_weights(3).items()}, F_train, F_ladder,
                             tags, dt, row=rows[0])
            write_json(JSON, res)
        for label, run in runs:
            key = f"{material}|{label}"
            if key in res or weights(run, material) is None:
                continue
            log(f"{material} {label}")
            res[key] = probe(Law(), load_file(str(weights(run, material))), F_train, F_ladder, tags, dt)
            write_json(JSON, res)


def report(res: dict) -> None:
    rows = []
    for material, runs in TRAININGS.items():
        for label, run in [("truth", None)] + list(runs):
            r = res.get(f"{material}|{label}")
            if r is None:
                continue
            rows.append([material, label, f"{r['q_rest_Pa'] / 1e3:.3g}", f"{r['q_min_rest_Pa'] / r['q_rest_Pa']:.3f}", f"{100 * r['train_negative_share']:.1f} %",
                         f"{r['train_p1']:.3f}", f"{r['train_min']:.3f}",
                         *(f"{r[f'ladder_min_loga{lim}']:.3f}" for lim in LOG_A),
                         ("– (elastic truth: F stays)" if material == "jelly" and run is not None else "–")
                         if not r.get("returned") or not r["returned"][1] or material == "jelly"
                         else "%d of %d" % tuple(r["returned"]),
                         "–" if "cfl_rest" not in r else f"{r['cfl_rest']:.2f} / {r['cfl_wide_max']:.2f}",
                         "(reference)" if run is None else outcome(material, run)])
    head = ["material", "law", "largest eigenvalue at F = I [kPa]", "smallest at F = I", "training states below 0", "1st percentile", "min",
            *(f"ladder, log a <= {lim}" for lim in LOG_A), "return map: stretches returned",
            "CFL at rest / largest on the wide ladder", "(c)"]
    body = ["Regenerate: `python benchmarks/nclaw_stability.py` (`--report` rewrites this; raw numbers in "
            "`benchmarks/results/nclaw_stability.json`). The smallest eigenvalue of one explicit step's acoustic "
            "tensor (`mpmlab.nclaw.probe.acoustic_minimum`: the return map, then the elastic stress, answering a "
            "small displacement gradient), divided by the same law's largest eigenvalue at F = I (its P-wave modulus); "
            "below 0 a wave grows whatever dt. "
            "Training states: 1,000 ground-truth F of the training trajectory; the ladder: isochoric uniaxial "
            f"stretch and simple shear of log-stretch up to the column's, times J in {list(JS)}. Return map: of "
            f"the 16 isochoric stretches a in {list(REACH)} (uniaxial and shear), how many the learned return map "
            "brings back within 400 steps (`return_map_reach`; the elastic true laws have none to test). CFL: "
            "dt sqrt(q_max / rho) / dx of the (c) scene at F = I and the largest over log a <= 1, J 0.6-1.5.", "",
            *md_table(head, rows), ""]
    write_readme_section(MD, "nclaw-stability", "The learned laws' ellipticity", "\n".join(body))
    log(f"wrote {MD}")


def main():
    ap = parser(__doc__.splitlines()[0])
    ap.add_argument("--report", action="store_true", help="only rewrite the nclaw.md section")
    a = ap.parse_args()
    res = read_json(JSON, {})
    if not a.report:
        measure(res)
    report(res)


if __name__ == "__main__":
    main()
