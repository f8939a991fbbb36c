"""Why NCLaw WATER (c) diverges: the learned law probed where the rollout takes it (issue 15).

    python benchmarks/nclaw_probe.py                 # Tab. 5, the return map's reach, the rollouts (~15 min)
    python benchmarks/nclaw_probe.py --report        # tables and plot from benchmarks/results/nclaw_probe.json

-> ``benchmarks/nclaw.md`` (section ``nclaw-probe``), ``benchmarks/results/nclaw_probe.json`` and
``benchmarks/results/nclaw_probe.png``. Each part is kept in the JSON as it finishes and skipped when
present, so an interrupted run resumes.

1. **Tab. 5** (NCLaw Sec. F.3): the MSE of P = tau F^-T and of F^e,new on 1k pairs drawn from the WATER
   ground-truth trajectory (:func:`mpmlab.nclaw.probe.constitutive_errors`), for the weights of the
   full-schedule training, of the sampled one, and of the labeled baseline (fitted here when missing).
2. **The return map's reach** (:func:`mpmlab.nclaw.probe.return_map_reach`): the plastic network alone
   (zero velocity gradient, 400 steps of 5e-4 s) from isochoric stretches a = 1.1 ... 2.5.
3. **Rollouts** with the full-schedule weights (JAX, fp32, MLS, as ``nclaw_eval``): the largest and the
   99th-percentile deviatoric log-stretch (:func:`mpmlab.nclaw.probe.deviatoric_stretch`) and the smallest J
   every 10 steps, on the training scene (reconstruction) and on (c) geometry until it fails.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from _harness import RESULTS, ROOT, log, machine_info, md_table, parser, write_readme_section

MD = Path(__file__).resolve().parent / "nclaw.md"
JSON = RESULTS / "nclaw_probe.json"
PLOT = RESULTS / "nclaw_probe.png"
DATASET = ROOT / "benchmarks" / "out" / "nclaw" / "data" / "water" / "trajectory.h5"
TRUTH = ROOT / "benchmarks" / "out" / "nclaw" / "truth"
JELLY_DATASET = ROOT / "benchmarks" / "out" / "nclaw" / "data" / "jelly" / "trajectory.h5"
#: JELL-O's trained weights (the full-schedule seed-1 run is a second draw of the same training)
JELLY_WEIGHTS = {
    "full schedule, seed 0": RESULTS / "nclaw_full" / "train" / "jelly_jax" / "nclaw_weights.safetensors",
    "full schedule, seed 1": RESULTS / "nclaw_full_seed1" / "train" / "jelly_jax" / "nclaw_weights.safetensors",
    "sampled schedule (0.25), seed 0": RESULTS / "nclaw" / "train" / "jelly_jax" / "nclaw_weights.safetensors",
}
#: volumes J of the dilation starts F = J^(1/3) I for JELL-O's return map (its truth is elastic: the map is I)
JELLY_J = (0.2, 0.5, 0.8, 1.1, 1.2, 1.33, 1.5, 2.0)
WEIGHTS = {
    "ours, full schedule": RESULTS / "nclaw_full" / "train" / "water_jax" / "nclaw_weights.safetensors",
    "ours, sampled schedule (0.25)": RESULTS / "nclaw" / "train" / "water_jax" / "nclaw_weights.safetensors",
    "labeled": RESULTS / "nclaw_probe" / "water_labeled.safetensors",
}
#: NCLaw Tab. 5 (WATER): (ours, labeled)
PAPER_TAB5 = {"P": (6.1e-1, 2.6e-3), "F_new": (2.388e-6, 2.381e-6)}
STRETCHES = (1.1, 1.2, 1.35, 1.5, 1.65, 1.8, 1.9, 2.0, 2.1, 2.2, 2.35, 2.5)


def load(path: Path) -> dict:
    from safetensors.numpy import load_file

    return load_file(str(path))


def labeled_weights(ds, pairs) -> Path:
    """The labeled baseline on WATER (NCLaw's ``supervised.yaml``: 30 epochs, batch 1000, Adam 0.1)."""
    from mpmlab.laws.nclaw import Law, save_weights
    from mpmlab.nclaw.baselines import fit_labeled

    path = WEIGHTS["labeled"]
    if not path.exists():
        log("fitting the labeled baseline on WATER (about 4 min)")
        law = Law()
        w, rep = fit_labeled(law, 3, pairs, float(ds.dt))
        path.parent.mkdir(parents=True, exist_ok=True)
        save_weights(path, w, law, 3)
        log(f"labeled: {json.dumps(rep)}")
    return path


def rollout_stats(case_name: str, weights: Path, max_steps: int | None = None, material: str = "water",
                  through_inversion: bool = False) -> dict:
    """Every 10 steps of the learned rollout: the deviatoric stretch, J and (with nclaw_eval's ground truth
    on disk) the position MSE. It stops at the first inverted particle (``failed_by_step``), or with
    ``through_inversion`` only at non-finite positions, the statistics then over the particles not inverted
    (``first_inverted``)."""
    from mpmlab.config import compose, stepper_from_config
    from mpmlab.nclaw.probe import deviatoric_stretch
    from mpmlab.nclaw.scenes import eval_cases
    from omegaconf import open_dict

    case = next(c for c in eval_cases(material) if c.name == case_name)
    truth = TRUTH / material / f"{case_name}_jax_fp32.npz"        # nclaw_eval's ground truth, every 5 steps
    x_true = np.load(truth)["x"] if truth.exists() else None
    cfg = compose(case.learned(str(weights)) + ["backend=jax", "transfer=mls", "precision=fp32",
                                                "output.recording=false"])
    with open_dict(cfg):
        cfg.scene.cfl_limit = 1.0
    _, st = stepper_from_config(cfg)
    s = st.init()
    steps = min(case.steps, max_steps or case.steps)
    rows, failed, first_inverted, t0 = [], None, None, time.perf_counter()
    for k in range(10, steps + 1, 10):
        s = st._advance(s, 10)
        d = st.to_numpy(s)
        dev, J = deviatoric_stretch(d["F"])
        ok = np.isfinite(dev)                      # not inverted (J > 0) and finite
        if not np.all(np.isfinite(d["x"])) or not ok.any() or (not ok.all() and not through_inversion):
            failed = k
            rows.append({"step": k, "dev_max": None, "dev_p99": float(np.percentile(dev[ok], 99)) if ok.any()
                         else None, "J_min": None, "inverted": int(np.sum(~ok))})
            break
        if not ok.all():
            first_inverted = first_inverted or k
        rows.append({"step": k, "dev_max": float(dev[ok].max()), "dev_p99": float(np.percentile(dev[ok], 99)),
                     "J_min": float(J[ok].min()), "J_max": float(J[ok].max()), "inverted": int(np.sum(~ok)),
                     "mse": None if x_true is None else float(np.mean((d["x"] - x_true[k // 5]) ** 2))})
    return {"case": case_name, "particles": int(st.particles.count), "steps": steps, "failed_by_step": failed,
            "first_inverted": first_inverted, "rows": rows, "wall_s": time.perf_counter() - t0}


def measure(res: dict) -> dict:
    from mpmlab.laws.nclaw import Law
    from mpmlab.nclaw.baselines import labeled_pairs
    from mpmlab.nclaw.data import load_dataset
    from mpmlab.nclaw.probe import constitutive_errors, return_map_reach

    if not DATASET.exists():
        raise SystemExit(f"{DATASET} is missing: run `python benchmarks/nclaw.py --materials water` first "
                         f"(it writes the WATER dataset), then rerun this.")
    ds = load_dataset(DATASET)
    pairs = labeled_pairs(ds)                 # the true law on every frame: once, for the fit and Tab. 5
    labeled_weights(ds, pairs)
    law = Law()
    for label, path in WEIGHTS.items():
        if not path.exists():
            log(f"{label}: {path} is missing; skipped")
            continue
        w = load(path)
        tab5 = res.setdefault("tab5", {})
        if label not in tab5:
            tab5[label] = constitutive_errors(law, w, ds, n=1000, seed=0, pairs=pairs)
            save(res)
        reach = res.setdefault("reach", {})
        if label not in reach:
            reach[label] = return_map_reach(law, w, 3, STRETCHES, steps=400, dt=float(ds.dt))
            save(res)
    ro = res.setdefault("rollouts", {})
    for case in ("reconstruction", "geometry"):
        if case not in ro:
            log(f"rollout {case} (full-schedule weights)")
            ro[case] = rollout_stats(case, WEIGHTS["ours, full schedule"])
            save(res)
    res["machine"] = machine_info()
    save(res)
    return res


def measure_jelly(res: dict) -> dict:
    """JELL-O (c): the truth's range on the training scene, the return map from pure volume changes and
    the (c) rollout, per trained weight file present."""
    import h5py
    from mpmlab.laws.nclaw import Law
    from mpmlab.nclaw.probe import read_state_range, return_map_reach, state_range

    out = res.setdefault("jelly", {})
    if "truth_range" not in out and JELLY_DATASET.exists():
        with h5py.File(JELLY_DATASET) as f:
            out["truth_range"] = state_range(np.asarray(f["frames/F"][10::10]))
        save(res)
    law = Law()
    for label, path in JELLY_WEIGHTS.items():
        done = path.parent / "summary.json"        # a training in progress writes its weights every epoch
        if not (path.exists() and done.exists() and json.loads(done.read_text()).get("status") == "ok"):
            log(f"JELL-O {label}: no finished training in {path.parent}; skipped")
            continue
        row = out.setdefault(label, {})
        if "trained_range" not in row:
            row["trained_range"] = read_state_range(path)
        if "dilation" not in row:
            row["dilation"] = return_map_reach(law, load(path), 3, [j ** (1.0 / 3.0) for j in JELLY_J],
                                               kinds=("dilation",), steps=400, dt=1e-3, report=(10, 100, 400))
            save(res)
        if "geometry" not in row:
            log(f"JELL-O rollout (c) geometry, {label}")
            row["geometry"] = rollout_stats("geometry", path, material="jelly", through_inversion=True)
            save(res)
    return res


def save(res: dict) -> None:
    JSON.parent.mkdir(parents=True, exist_ok=True)
    tmp = JSON.with_suffix(".tmp")
    tmp.write_text(json.dumps(res, indent=1))
    tmp.replace(JSON)


def after(row: dict, step: int) -> dict:
    """``row["after"][step]``, whether the keys are ints (measured now) or strings (read from JSON)."""
    return row["after"][step] if step in row["after"] else row["after"][str(step)]


def fmt(v) -> str:
    return "–" if v is None else f"{v:.3g}"


def report(res: dict) -> str:
    L = ["Regenerate with `python benchmarks/nclaw_probe.py` (module `mpmlab.nclaw.probe`; raw numbers in "
         "`benchmarks/results/nclaw_probe.json`, plot `benchmarks/results/nclaw_probe.png`). WATER, JAX, fp64 "
         "for the probes, fp32 for the rollouts.", ""]
    t5 = res.get("tab5", {})
    if t5:
        L += ["**Tab. 5** (1k pairs drawn from the WATER ground truth, PCG64 seed 0; F^e,new without a return "
              "map, i.e. F_trial, is the scale of the return map's work):", ""]
        rows = [[k, fmt(v["P"]), fmt(v["F_new"]), fmt(v["F_new_without_return_map"]), fmt(v.get("F_new_floor"))]
                for k, v in t5.items()]
        rows.append(["paper: ours / labeled", f"{PAPER_TAB5['P'][0]:.3g} / {PAPER_TAB5['P'][1]:.3g}",
                     f"{PAPER_TAB5['F_new'][0]:.4g} / {PAPER_TAB5['F_new'][1]:.4g}", "–", "–"])
        L += md_table(["weights", "MSE of P [Pa²]", "MSE of F^e,new", "MSE of F_trial (no return map)",
                       "floor: the best F^e,new keeping F_trial's rotation"], rows)
        some = next(iter(t5.values()))
        L += ["", f"RMS of the true P over the pairs: {some['P_true_rms']:.4g} Pa.", ""]
    reach = res.get("reach", {})
    if reach:
        L += ["**The return map's reach** (the plastic net alone, zero velocity gradient, from an isochoric "
              "uniaxial stretch a; deviatoric log-stretch / J after 10 and 400 steps of 5e-4 s; the truth "
              "returns to 0 / 1 in one step):", ""]
        labels = list(reach)
        rows = []
        for i, a in enumerate(STRETCHES):
            row = [f"{a:g} ({np.log(a):.2f})"]
            for lab in labels:
                r = [x for x in reach[lab] if x["kind"] == "uniaxial"][i]
                a10, a400 = after(r, 10), after(r, 400)
                row.append(f"{fmt(a10['deviatoric_stretch'])} / {fmt(a10['J'])} → "
                           f"{fmt(a400['deviatoric_stretch'])} / {fmt(a400['J'])}")
            rows.append(row)
        L += md_table(["a (log a)"] + labels, rows) + [""]
    ro = res.get("rollouts", {})
    if ro:
        L += ["**Rollouts** with the full-schedule weights (JAX, fp32, MLS):", ""]
        rows = []
        for case, r in ro.items():
            ok = [x for x in r["rows"] if x["dev_max"] is not None]
            dmax = max(x["dev_max"] for x in ok)
            p99 = max(x["dev_p99"] for x in ok)
            jmin = min(x["J_min"] for x in ok)
            first = next((x["step"] for x in ok if x["dev_max"] > 0.5), None)
            rows.append([case, r["particles"], r["failed_by_step"] or f"no ({r['steps']} steps)", fmt(dmax),
                         fmt(p99), fmt(jmin), first or "never"])
        L += md_table(["case", "particles", "failed by step", "largest deviatoric log-stretch (until failure)",
                       "largest 99th percentile", "smallest J", "first step with a stretch > 0.5"], rows) + [""]
    return "\n".join(L) + "\n"


def report_jelly(res: dict) -> str:
    out = res.get("jelly", {})
    L = ["Regenerate with `python benchmarks/nclaw_probe.py --part jelly` (raw numbers in "
         "`benchmarks/results/nclaw_probe.json` under `jelly`). JAX; fp64 for the return map, fp32 for the rollouts.", ""]
    tr = out.get("truth_range")
    if tr:
        L += [f"The truth on the training scene (every 10th of its 1000 frames): J {tr['J_min']:.3g} to "
              f"{tr['J_max']:.3g}, largest deviatoric log-stretch {tr['deviatoric_stretch_max']:.3g}.", ""]
    rows, dil = [], []
    labels = [k for k in out if k != "truth_range"]
    for lab in labels:
        r = out[lab]
        t = r.get("trained_range") or {}
        g = r.get("geometry")
        ok = [x for x in (g or {}).get("rows", []) if x["dev_max"] is not None]
        first = next((x["step"] for x in ok if tr and x.get("J_max", 0) > 1.5 * tr["J_max"]), None)
        mse = [x["mse"] for x in ok if x.get("mse") is not None]
        rows.append([lab, f"{fmt(t.get('J_min'))} to {fmt(t.get('J_max'))}" if t else "–",
                     (f"{fmt(min(x['J_min'] for x in ok))} to {fmt(max(x['J_max'] for x in ok))}" if ok else "–"),
                     first or "never", (g or {}).get("first_inverted") or "none",
                     max((x["inverted"] for x in ok), default=0), fmt(float(np.mean(mse[::2]))) if mse else "–"])
        for d in r.get("dilation", []):
            J0 = d["stretch"] ** 3
            dil.append((J0, lab, [after(d, k)["J"] for k in (10, 100, 400)]))
    if rows:
        L += ["**(c) with each trained law** (the learned rollout every 10 steps; the MSE against the ground "
              "truth every 20 steps, near NCLaw's every-5-step metric):", ""]
        L += md_table(["weights", "J on its training scene (learned rollout)", "J on (c) (particles not inverted)",
                       "first step with J > 1.5x the truth's largest", "first inverted particle by step",
                       "most particles inverted at once", "(c) position MSE [m²]"], rows) + [""]
    if dil:
        L += ["**The return map alone from a pure volume change** F = J^(1/3) I (zero velocity gradient, so dt plays no part; "
              "the truth is elastic, so its return map leaves J where it is): J after 10 / 100 / 400 steps:", ""]
        Js = sorted({round(j, 6) for j, _, _ in dil})
        table = []
        for j in Js:
            cells = [f"{j:.3g}"]
            for lab in labels:
                v = next((x for jj, l2, x in dil if round(jj, 6) == j and l2 == lab), None)
                cells.append("–" if v is None else " / ".join(fmt(u) for u in v))
            table.append(cells)
        L += md_table(["J"] + labels, table) + [""]
    return "\n".join(L) + "\n"


def plot(res: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(11, 4))
    for lab, rows in res.get("reach", {}).items():
        u = [r for r in rows if r["kind"] == "uniaxial"]
        a = [r["log_stretch"] for r in u]
        fin = [after(r, 400)["deviatoric_stretch"] for r in u]
        one = [after(r, 10)["deviatoric_stretch"] for r in u]
        h = ax[0].plot(a, [min(f, 5) for f in fin], "o-", label=f"{lab}: 400 steps")[0]
        ax[0].plot(a, [min(f, 5) for f in one], "s--", color=h.get_color(), alpha=0.6, label=f"{lab}: 10 steps")
    ax[0].plot([0, 1], [0, 1], "k:", lw=0.8, label="no return map")
    ax[0].set(xlabel="initial deviatoric log-stretch (uniaxial)", ylabel="after the plastic net alone (inf → 5)",
              title="the learned return map's reach (WATER)")
    ax[0].legend(fontsize=7)
    for case, r in res.get("rollouts", {}).items():
        ok = [x for x in r["rows"] if x["dev_max"] is not None]
        s = [x["step"] for x in ok]
        h = ax[1].semilogy(s, [x["dev_max"] for x in ok], label=f"{case}: largest")[0]
        ax[1].semilogy(s, [x["dev_p99"] for x in ok], "--", color=h.get_color(), label=f"{case}: 99th percentile")
    ax[1].set(xlabel="step", ylabel="deviatoric log-stretch", title="learned WATER rollouts (full schedule)")
    ax[1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(PLOT, dpi=110)


def main():
    ap = parser(__doc__, raw=True)
    ap.add_argument("--report", action="store_true", help="tables and plot from the saved JSON only")
    ap.add_argument("--part", choices=("water", "jelly", "all"), default="all",
                    help="water: Tab. 5, the return map's reach and the rollouts; jelly: JELL-O (c)")
    a = ap.parse_args()
    res = json.loads(JSON.read_text()) if JSON.exists() else {}
    if not a.report and a.part in ("water", "all"):
        res = measure(res)
    if not a.report and a.part in ("jelly", "all"):
        res = measure_jelly(res)
    plot(res)
    write_readme_section(MD, "nclaw-probe", "WATER (c): the learned law where the rollout takes it", report(res))
    if res.get("jelly"):
        write_readme_section(MD, "nclaw-probe-jelly", "JELL-O (c): the learned law's volume", report_jelly(res))
    log(f"wrote {MD} and {PLOT}")


if __name__ == "__main__":
    main()
