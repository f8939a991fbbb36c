"""NCLaw (c), uncoupled: each learned law's update driven by the ground truth's own flow (issue 15).

    python benchmarks/nclaw_driven.py                      # PLASTICINE and SAND, 400 steps (~5 min)
    python benchmarks/nclaw_driven.py --materials water,jelly --steps 700
    python benchmarks/nclaw_driven.py --flow training --scale 2    # the training trajectory's flow, doubled
    python benchmarks/nclaw_driven.py --report

-> ``benchmarks/nclaw.md`` (section ``nclaw-driven``) and ``benchmarks/results/nclaw_driven.json``.

The (c) scene's ground truth is rolled out (JAX, MLS, fp32, its 30,000 particles) and every 6th particle's velocity
gradient C_n (MLS: the affine matrix) is kept for the first ``--steps`` steps. Each law's update alone then replays
that flow from F = I: F_n = update(F_(n-1), grad v = C_n), no grid, no coupling (fp64). The true law driven so
reproduces its own recorded F (the check, ``truth: replay error``); a learned law shows where its update takes F
under the flow the true material sees. If the laws that diverge on (c) left the true F under that flow and the
ones that run did not, the failure would be the update's; if not, it is born of the coupling (the learned stress
changing the flow).

``--flow training`` drives the laws instead with the training trajectory's own velocity gradients (its 1,000
particles, 1,000 steps), multiplied by ``--scale``: a probe that needs no test scene. At a scale other than 1 the
true F is that of the true law driven by the same scaled flow.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from _harness import OUT, RESULTS, log, md_table, parser, read_json, write_json, write_readme_section
from nclaw_draws import TRAININGS, weights
from nclaw_stability import outcome

MD = Path(__file__).resolve().parent / "nclaw.md"
JSON = RESULTS / "nclaw_driven.json"
FLOW = OUT / "nclaw" / "driven"
STRIDE = 6
REPORT_AT = (100, 200, 400, 700)


def truth_flow(material: str, steps: int) -> dict:
    """C_n and F_n (n = 1 ... steps) of every STRIDE-th particle of the (c) ground truth, cached."""
    path = FLOW / f"{material}_{steps}.npz"
    if path.exists():
        d = np.load(path)
        return {k: d[k] for k in d.files}
    from mpmlab.config import compose, stepper_from_config

    cfg = compose([f"scene=nclaw_geometry_{material}", "backend=jax", "transfer=mls", "precision=fp32",
                   "output.recording=false"])
    _, st = stepper_from_config(cfg)
    C, F = [], []

    def keep(i, s):
        if i > 0:
            C.append(np.asarray(s["C"])[::STRIDE].astype(np.float64))
            F.append(np.asarray(s["F"])[::STRIDE].astype(np.float64) if "F" in s else
                     np.cbrt(np.asarray(s["J"])[::STRIDE])[:, None, None] * np.eye(3))

    st.rollout(steps=steps, every=1, on_frame=keep)
    out = {"C": np.stack(C), "F": np.stack(F), "dt": np.float64(cfg.scene.dt)}
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, **out)
    return out


def training_flow(material: str, scale: float) -> dict:
    """The training trajectory's C_n (n = 1 ... T) times ``scale``, and its F_n (the truth's under scale 1)."""
    from mpmlab.nclaw.data import load_dataset

    ds = load_dataset(OUT / "nclaw" / "data" / material / "trajectory.h5")
    return {"C": scale * np.asarray(ds.C[1:], np.float64), "F": np.asarray(ds.F[1:], np.float64),
            "dt": np.float64(ds.dt)}


def _step(law, w, dt: float, row=None):
    """One particle-batched application of the law's update: F_n = update(F_(n-1), grad v = C_n)."""
    import jax
    import jax.numpy as jnp

    from mpmlab.nclaw.probe import F_of_state, _jax_law, state_from_F

    fns, wj = _jax_law(law, 3, w)
    rowj = jnp.zeros((0,)) if row is None else jnp.asarray(np.asarray(row, np.float64))
    state_of = state_from_F(law, "nclaw_driven")

    def one(F, C):
        return F_of_state(law, fns.update(state_of(F), C, dt, rowj, wj), 3)

    return jax.jit(jax.vmap(one))


def replay(law, w, flow: dict, row=None) -> np.ndarray:
    """F_n (n = 1 ... T) of the law driven by the flow from F = I."""
    import jax.numpy as jnp

    step = _step(law, w, float(flow["dt"]), row)
    F, out = jnp.asarray(np.tile(np.eye(3), (flow["C"].shape[1], 1, 1))), []
    for C in flow["C"]:
        F = step(F, jnp.asarray(C))
        out.append(np.asarray(F))
    return np.stack(out)


def drive(law, w, flow: dict, row=None) -> dict:
    """Replay the flow through the law's update from F = I; per report step: the largest deviatoric
    log-stretch, J's range, the count of inverted or non-finite F, and the median / 99th percentile of
    |F_driven - F_truth| / |F_truth|."""
    from mpmlab.nclaw.probe import deviatoric_stretch

    F_all, F_true = replay(law, w, flow, row), flow["F"]
    out = {}
    for n in sorted({r for r in REPORT_AT if r <= len(F_all)} | {len(F_all)}):
        Fn = F_all[n - 1]
        dev, J = deviatoric_stretch(Fn)
        ok = np.isfinite(dev)
        err = np.linalg.norm((Fn - F_true[n - 1]).reshape(len(Fn), -1), axis=1) / \
            np.linalg.norm(F_true[n - 1].reshape(len(Fn), -1), axis=1)
        err = err[np.isfinite(err)]
        out[str(n)] = {"deviatoric_stretch_max": float(dev[ok].max()) if ok.any() else None,
                       "J_min": float(np.nanmin(J)), "J_max": float(np.nanmax(J)), "bad": int((~ok).sum()),
                       "err_median": float(np.median(err)) if len(err) else None,
                       "err_p99": float(np.percentile(err, 99)) if len(err) else None}
    return out


def measure(res: dict, materials: list[str], steps: int, source: str = "c", scale: float = 1.0) -> None:
    from safetensors.numpy import load_file

    from mpmlab.laws.nclaw import Law
    from mpmlab.nclaw.baselines import true_law
    from mpmlab.nclaw.data import load_dataset

    tag = f"{steps}" if source == "c" else f"training x{scale:g}"
    for material in materials:
        missing = [f"{material}|truth|{tag}"] + [f"{material}|{label}|{tag}" for label, run in TRAININGS[material]
                                                 if weights(run, material) is not None]
        if all(k in res for k in missing):
            continue
        flow = truth_flow(material, steps) if source == "c" else training_flow(material, scale)
        law, rows = true_law(load_dataset(OUT / "nclaw" / "data" / material / "trajectory.h5"))
        w_true = {k: np.asarray(a) for k, a in law.initial_weights(3).items()}
        if scale != 1.0:           # under a scaled flow the reference F is the true law's own replay of it
            flow["F"] = replay(law, w_true, flow, row=rows[0])
        key = f"{material}|truth|{tag}"
        if key not in res:
            res[key] = drive(law, w_true, flow, row=rows[0])
            write_json(JSON, res)
        for label, run in TRAININGS[material]:
            key = f"{material}|{label}|{tag}"
            if key in res or weights(run, material) is None:
                continue
            log(f"{material} {label}")
            res[key] = drive(Law(), load_file(str(weights(run, material))), flow)
            write_json(JSON, res)


def _order(key: str) -> tuple:
    """Report order: the (c) flows by length, then the training flows by scale; materials and laws as listed
    in TRAININGS, the truth first."""
    material, label, flow = key.split("|")
    labels = ["truth"] + [lab for lab, _ in TRAININGS[material]]
    by_flow = (0, int(flow), 0.0) if flow.isdigit() else (1, 0, float(flow.split("x")[-1]))
    return (*by_flow, list(TRAININGS).index(material), labels.index(label) if label in labels else len(labels))


def report(res: dict) -> None:
    rows = []
    for key in sorted(res, key=_order):
        r = res[key]
        material, label, flow = key.split("|")
        run = dict(TRAININGS[material]).get(label)
        for n, v in r.items():
            rows.append([material, label, "(c)" if flow.isdigit() else flow, n, "–" if v["deviatoric_stretch_max"] is None else
                         f"{v['deviatoric_stretch_max']:.3g}", f"{v['J_min']:.3g} to {v['J_max']:.3g}", v["bad"],
                         "–" if v["err_median"] is None else f"{v['err_median']:.2e} / {v['err_p99']:.2e}",
                         "(reference)" if run is None else outcome(material, run)])
    body = ["Regenerate: `python benchmarks/nclaw_driven.py` (`--report` rewrites this; raw numbers in "
            "`benchmarks/results/nclaw_driven.json`). Each law's update alone, driven from F = I by the (c) ground "
            f"truth's recorded velocity gradients (every {STRIDE}th of its 30,000 particles, fp64): the largest "
            "deviatoric log-stretch, J's range, inverted or non-finite F, and |F - F_truth| / |F_truth| (median / 99th "
            "percentile) at the step given. The truth's own row is the replay check (its error is fp32 round-off).",
            "", *md_table(["material", "law", "flow", "step", "largest deviatoric stretch", "J", "inverted or non-finite",
                           "error of F: median / 99th pct", "(c)"], rows), ""]
    write_readme_section(MD, "nclaw-driven", "(c) uncoupled: the laws driven by the truth's flow", "\n".join(body))
    log(f"wrote {MD}")


def main():
    ap = parser(__doc__.splitlines()[0])
    ap.add_argument("--materials", default="plasticine,sand")
    ap.add_argument("--steps", type=int, default=400)
    ap.add_argument("--flow", default="c", choices=("c", "training"),
                    help="the (c) ground truth's flow (default) or the training trajectory's")
    ap.add_argument("--scale", type=float, default=1.0, help="--flow training: multiply its velocity gradients")
    ap.add_argument("--report", action="store_true")
    a = ap.parse_args()
    if a.scale != 1.0 and a.flow != "training":
        raise SystemExit("--scale multiplies the training trajectory's flow; give --flow training with it")
    res = read_json(JSON, {})
    if not a.report:
        measure(res, [m for m in a.materials.split(",") if m], a.steps, a.flow, a.scale)
    report(res)


if __name__ == "__main__":
    main()
