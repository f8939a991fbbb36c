"""NCLaw reproduced (Ma et al., ICML 2023, Tabs. 1-2): datasets, training and evaluation, resumable,
-> ``benchmarks/nclaw.md`` (section ``nclaw-train``) and ``benchmarks/results/nclaw/``.

    python benchmarks/nclaw.py --materials jelly,sand --backend jax --segment-fraction 0.25 --budget-min 80
    python benchmarks/nclaw.py --report               # only rewrite the tables from what is on disk

Per material: (1) the ground-truth trajectory (``experiment=nclaw_datasets``, Warp fp32, every step;
regenerated when missing: it is deterministic on the CPU and 96 MB, so it is not committed); (2)
``task=nclaw_train`` with the paper's schedule (300 epochs, lr 1.0 / 0.1, cosine, clip 0.1, period 25
-> 200), ``segment_fraction`` as given, stopped when the time budget is spent and resumed by the next
invocation (the run directory with its checkpoint is ``benchmarks/results/nclaw/train/<material>_<backend>``);
(3) when the training has finished, ``task=nclaw_eval`` of the trained weights and of the untrained
initialisation ("ours-init") on reconstruction, (a) time, (b) velocity seeds 1, 7, 8 and (c) geometry.

Every stage is a separate ``mpmlab`` process, so a killed invocation loses at most the current epoch.
The 96-MB datasets and the ground-truth rollouts live in ``benchmarks/out/nclaw`` (not committed).
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

from _harness import OUT, RESULTS, ROOT, add_backends, csv, log, machine_info, md_table, parser, write_readme_section

MD = Path(__file__).resolve().parent / "nclaw.md"
RES = RESULTS / "nclaw"
RAW = OUT / "nclaw"
MATERIALS = ("jelly", "sand", "plasticine", "water")
#: the networks' Xavier seed of the trainings and of the untrained "ours-init" row (--seed)
SEED = 0
VELOCITY_WEIGHT = 0.0     # --velocity-weight: task.velocity_weight of the teacher-forced trainings
RESET: tuple = ()         # --reset: task.teacher.reset of the teacher-forced trainings (empty: the task's default)
#: a training whose checkpoint has not changed for this long is killed and resumed (``watched``)
STALL_S = 900.0
#: Tab. 1 labeled and sys-id reconstruction
PAPER_BASELINES = {"jelly": (8.0e-9, 1.7e-8), "sand": (7.1e-2, 2.7e-7), "plasticine": (5.5e-6, 5.8e-10),
                   "water": (1.6e-7, 1.7e-8)}
PAPER_TAB1 = {"jelly": (2.4e-4, 1.1e-1), "sand": (2.6e-5, 4.8e-2), "plasticine": (6.5e-5, 4.6e-2),
              "water": (2.0e-5, 6.8e-2)}


def mpmlab(args: list[str], timeout: float | None = None) -> int:
    cmd = [sys.executable, "-m", "mpmlab", *args]
    log("$ mpmlab " + " ".join(args))
    try:
        return subprocess.run(cmd, cwd=ROOT, timeout=timeout).returncode
    except subprocess.TimeoutExpired:
        return 124


def dataset(material: str) -> Path:
    run = RAW / "data" / material
    path = run / "trajectory.h5"
    if not path.exists():
        rc = mpmlab(["experiment=nclaw_datasets", f"scene=nclaw_{material}", "output.recording=false",
                     "output.plots=false", "output.overwrite=true", f"hydra.run.dir={run}"])
        if rc != 0:
            raise SystemExit(f"dataset for {material} failed (exit {rc})")
    return path


def watched(args: list[str], progress: Path, budget_s: float, stall_s: float) -> int:
    """``mpmlab args`` with a watchdog: killed when ``progress`` (its checkpoint) has not changed for
    ``stall_s`` seconds (a JAX CPU computation was once seen never to return: every thread idle in a
    futex, 2026-12-02), then started again: it resumes from the checkpoint. Returns the last exit code."""
    deadline = time.time() + budget_s
    while True:
        left = deadline - time.time()
        run_args = [a for a in args if not a.startswith("task.stop_after_s=")] + [f"task.stop_after_s={max(left - 120, 60):.0f}"]
        log("$ mpmlab " + " ".join(run_args))
        proc = subprocess.Popen([sys.executable, "-m", "mpmlab", *run_args], cwd=ROOT)
        seen = time.time()
        last = progress.stat().st_mtime if progress.exists() else None
        while proc.poll() is None:
            time.sleep(15)
            now = progress.stat().st_mtime if progress.exists() else None
            if now != last:
                last, seen = now, time.time()
            if time.time() - seen > stall_s or time.time() > deadline + 300:
                log(f"no checkpoint for {time.time() - seen:.0f} s: killing the run (it resumes)")
                proc.kill()
                proc.wait()
                break
        else:
            return proc.returncode
        if time.time() > deadline - 120:
            return 124


def train(material: str, backend: str, fraction: float, epochs: int, budget_s: float, precision: str,
          method: str = "teacher") -> dict | None:
    tag = "" if method == "teacher" else f"_{method}"
    run = RES / "train" / f"{material}_{backend}{tag}"
    summary = run / "summary.json"
    if summary.exists():
        s = json.loads(summary.read_text())
        if s.get("status") == "ok" and (method == "labeled" or s.get("epochs_planned") == epochs):
            return s
    if budget_s <= 60:
        return json.loads(summary.read_text()) if summary.exists() else None
    data = dataset(material)
    args = ["task=nclaw_train", f"task.method={method}", f"scene=nclaw_{material}",
            f"material={material if method == 'sysid' else 'nclaw'}", f"backend={backend}",
            "transfer=mls", f"precision={precision}", f"task.dataset={data}", f"task.epochs={epochs}",
            *([f"material.options.seed={SEED}"] if method != "sysid" else []),
            *([f"task.velocity_weight={VELOCITY_WEIGHT!r}"] if VELOCITY_WEIGHT and method == "teacher" else []),
            *([f"task.teacher.reset=[{','.join(RESET)}]"] if RESET and method == "teacher" else []),
            f"task.segment_fraction={fraction}", "output.overwrite=true", f"hydra.run.dir={run}"]
    ckpt = run / ("train_checkpoint.pkl" if backend == "jax" else "train_checkpoint.pt")
    rc = mpmlab(args) if method == "labeled" else watched(args, ckpt, budget_s, STALL_S)
    if rc != 0:
        log(f"training {material}/{backend} ended with exit code {rc}")
    if summary.exists():
        return json.loads(summary.read_text())
    # no summary: the run failed (or was stopped) before writing one; say where its checkpoint stands
    return {"status": "failed" if rc != 0 else "stopped", "exit_code": rc, "epochs": checkpoint_epoch(ckpt)}


def checkpoint_epoch(path: Path) -> int:
    """The epochs done according to a training checkpoint (0 without one)."""
    if not path.exists():
        return 0
    if path.suffix == ".pkl":
        import pickle

        with open(path, "rb") as f:
            return int(pickle.load(f)["epoch"])
    import torch

    return int(torch.load(path, weights_only=False)["epoch"])


def evaluate(material: str, backend: str, weights: Path | None, label: str, cases: list[str], precision: str,
             law_params: dict | None = None, tag: str = "", partners: dict | None = None, init_seed: int = 0,
             learned_cfl_limit: float | None = None):
    run = RES / "eval" / f"{material}_{backend}_{label}{tag}"
    summary = run / "summary.json"
    if summary.exists():
        return json.loads(summary.read_text())
    args = ["task=nclaw_eval", f"task.material={material}", f"backend={backend}", "transfer=mls",
            f"precision={precision}", f"task.truth_dir={RAW / 'truth' / material}", f"task.label={label}",
            "task.cases=[" + ",".join(cases) + "]", f"hydra.run.dir={run}"]
    if weights is not None:
        args.append(f"task.weights={weights}")
    elif init_seed:
        args.append(f"task.init_seed={init_seed}")
    for k, v in (partners or {}).items():
        args.append(f"+task.partner_weights.{k}={v}")
    if learned_cfl_limit is not None:
        args.append(f"task.learned_cfl_limit={learned_cfl_limit}")
    for k, v in (law_params or {}).items():
        args.append(f"+task.law_params.{k}={v!r}")
    rc = mpmlab(args)
    return json.loads(summary.read_text()) if rc == 0 and summary.exists() else None


#: the qualitative cases of each material (NCLaw Figs. 3-4: no number in the paper), evaluated with --extras
EXTRAS = {"jelly": ("contact", "pool"), "plasticine": ("melting",), "water": ("incline",)}


def extras(material: str, backend: str, weights: Path, precision: str, learned_cfl_limit: float | None = None) -> None:
    """The material's qualitative cases (``EXTRAS``) once its training (and each partner's: SAND's for
    the melting) has finished; their metric and wall times go to the report's "Figs. 3-4" table."""
    from mpmlab.nclaw.scenes import eval_cases

    cases = [c for c in eval_cases(material) if c.name in EXTRAS.get(material, ())]
    partners = {}
    for c in cases:
        for p in c.partners:
            s = RES / "train" / f"{p}_{backend}" / "summary.json"
            if not (s.exists() and json.loads(s.read_text()).get("status") == "ok"):
                log(f"{material}/{backend}: case {c.name} waits for the {p} training (rerun when it has finished)")
                return
            partners[p] = RES / "train" / f"{p}_{backend}" / "nclaw_weights.safetensors"
    if cases:
        evaluate(material, backend, weights, "ours", [c.name for c in cases], precision, tag="_extras",
                 partners=partners, learned_cfl_limit=learned_cfl_limit)


def fmt(v):
    return "–" if v is None else f"{v:.2e}"


def report() -> None:
    rows1, rows2, sched = [], [], []
    for run in sorted((RES / "train").glob("*")) if (RES / "train").exists() else []:
        s_path = run / "summary.json"
        if not s_path.exists():
            h_path = run / "history.json"    # a run that stopped on divergence (kept for the record)
            if h_path.exists():
                h = json.loads(h_path.read_text())
                material, backend, *rest = run.name.split("_")
                hist = h.get("history") or []
                times = [e["time_s"] for e in hist]
                spe = (times[-1] - times[0]) / max(len(times) - 1, 1) if len(times) > 1 else None
                sched.append([material, backend, f"teacher (on_divergence={h.get('on_divergence')})",
                              f"{h['diverged_at_epoch']} / {h['epochs_planned']}", h.get('fraction'),
                              fmt(hist[0]["loss"] if hist else None), "–",
                              f"{spe:.1f}" if spe else "–", f"{times[-1] / 3600:.2f}" if times else "–",
                              h.get("steps_back", 0),
                              f"{h['status']} at epoch {h['diverged_at_epoch']}"])
            continue
        s = json.loads(s_path.read_text())
        material, backend, *rest = run.name.split("_")
        method = rest[0] if rest else "teacher"
        if method == "labeled":             # no epochs of a rollout: its result is Tab. 1's labeled column
            continue
        hist = s.get("history") or []
        sched.append([material, backend, method, f"{s['epochs']} / {s['epochs_planned']}", s["segment_fraction"],
                      fmt(s.get("initial_loss")), fmt(s.get("final_loss")),
                      f"{s['seconds_per_epoch']:.1f}" if s.get("seconds_per_epoch") else "–",
                      f"{(hist[-1]['time_s'] / 3600):.2f}" if hist else "–",
                      "; ".join(f"epoch {b['diverged_at']} -> {b['resumed_at']} at x{b['lr_scale']:g}"
                                for b in s.get("backoffs") or []) or 0, s["status"]])
        if method != "teacher":            # a baseline's run: reported in the row of its material
            continue
        ev = {lab: RES / "eval" / f"{material}_{backend}_{lab}" / "summary.json"
              for lab in ("ours", "ours-init", "labeled", "sys-id")}
        ev = {k: json.loads(p.read_text()) for k, p in ev.items() if p.exists()}
        if "ours" in ev or "ours-init" in ev:
            tab = {k: v["table"] for k, v in ev.items()}
            pt = PAPER_TAB1.get(material, (None, None))
            r = tab.get("ours", {}).get("reconstruction", {}).get("mse")
            ri = tab.get("ours-init", {}).get("reconstruction", {}).get("mse")
            rl = tab.get("labeled", {}).get("reconstruction", {}).get("mse")
            rs = tab.get("sys-id", {}).get("reconstruction", {}).get("mse")
            pb = PAPER_BASELINES.get(material, (None, None))
            rows1.append([material, backend, fmt(r), fmt(pt[0]), fmt(ri), fmt(pt[1]),
                          "–" if r is None or ri is None else f"{ri / r:.0f}x", f"{fmt(rl)} ({fmt(pb[0])})",
                          f"{fmt(rs)} ({fmt(pb[1])})"])
            o = tab.get("ours", {})
            rows2.append([material, backend] + [f"{fmt(o.get(k, {}).get('mse'))} ({fmt(o.get(k, {}).get('paper'))})"
                                                for k in ("time", "velocity", "geometry")])
    rows3 = []
    for p in sorted((RES / "eval").glob("*_extras/summary.json")) if (RES / "eval").exists() else []:
        e = json.loads(p.read_text())
        for name, r in e["cases"].items():
            tt, tl = r.get("truth_wall_s"), r.get("learned_wall_s")
            rows3.append([e["material"], e["backend"], name, r.get("particles") or "–", r["steps"], fmt(r.get("mse")),
                          "–" if tt is None else f"{tt:.0f}", "–" if tl is None else f"{tl:.0f}", r["status"]])
    body = ["Schedule: the release's (300 epochs; Adam lr 1.0 elastic / 0.1 plastic, cosine to 0, grad-norm clip "
            "0.1 per net; teacher-forcing period 25 -> 200 steps, reset x, v, C, F), MLS, fp32, 1k particles "
            "(NCLaw App. D). `segment_fraction` < 1 back-propagates that random share of the segments per epoch "
            "(unbiased; the issue accepts it within 2x of the full schedule's loss). Regenerate: "
            "`python benchmarks/nclaw.py --materials ... --budget-min N` (resumes; `--report` rewrites this).", "",
            "### Training", "",
            *md_table(["material", "backend", "method", "epochs", "segment_fraction", "initial loss", "final loss",
                       "s / epoch", "hours", "steps back (on_divergence=backoff)", "status"], sched), "",
            "### Tab. 1: reconstruction [m²]", "",
            *md_table(["material", "backend", "ours", "paper", "ours-init", "paper init", "init / ours",
                       "labeled (paper)", "sys-id (paper)"], rows1), "",
            "### Tab. 2: generalisation, ours (paper) [m²]", "",
            *md_table(["material", "backend", "(a) time", "(b) velocity (3 seeds)", "(c) geometry"], rows2), "",
            "### Figs. 3-4: the qualitative cases (no number in the paper)", "",
            "The same metric on NCLaw's contact, pool, melting and incline scenes (stand-in meshes), with the "
            "wall times of the ground truth and of the learned law (seconds, this machine).", "",
            *md_table(["material", "backend", "case", "particles", "steps", "MSE [m²]", "truth s", "learned s",
                       "status"], rows3), "",
            f"Machine: {json.dumps(machine_info(load=True))}", ""]
    write_readme_section(MD, "nclaw-train", "Training and evaluation (Tabs. 1-2)", "\n".join(body))
    log(f"wrote {MD}")


def main():
    ap = parser(__doc__.splitlines()[0])
    ap.add_argument("--materials", default="jelly,sand", help="comma-separated: jelly, sand, plasticine, water")
    add_backends(ap, default="jax")
    ap.add_argument("--segment-fraction", type=float, default=0.25)
    ap.add_argument("--epochs", type=int, default=300)
    ap.add_argument("--precision", default="fp32")
    ap.add_argument("--budget-min", type=float, default=85.0, help="wall-clock budget of this invocation [min]")
    ap.add_argument("--cases", default="reconstruction,time,velocity_seed1,velocity_seed7,velocity_seed8,geometry")
    ap.add_argument("--baselines", action="store_true", help="also the labeled and sys-id baselines (NCLaw Tab. 1)")
    ap.add_argument("--no-extras", dest="extras", action="store_false",
                    help="skip the qualitative cases (contact, pool, melting, incline: NCLaw Figs. 3-4)")
    ap.add_argument("--learned-cfl-limit", type=float, default=None,
                    help="the qualitative cases' cfl_limit for the learned law (task.learned_cfl_limit): NCLaw runs "
                         "them at its dt whatever the learned tangent's wave speed (nclaw.md, 'Figs. 3-4')")
    ap.add_argument("--seed", type=int, default=0, help="the networks' initial-weight seed (material.options.seed); "
                                                        "give another seed its own --results folder")
    ap.add_argument("--velocity-weight", type=float, default=0.0,
                    help="weight [s^2] of the velocity term of the training loss (task.velocity_weight; NCLaw Tab. 7, "
                         "whose weight the paper does not give; 0: the release's position-only loss); give it its own "
                         "--results folder")
    ap.add_argument("--reset", default="", help="what teacher forcing resets at each segment: 'x,v' (kinematics only, "
                                                "the paper's text; C and the law state carry over) or 'x,v,C,F' (the "
                                                "release, the task's default); give it its own --results folder")
    ap.add_argument("--report", action="store_true", help="only rewrite benchmarks/nclaw.md from the results")
    ap.add_argument("--results", default=None, help="results folder (default benchmarks/results/nclaw); with it "
                                                    "the Markdown goes to <results>/nclaw.md")
    a = ap.parse_args()
    global RES, MD, SEED, VELOCITY_WEIGHT, RESET
    SEED, VELOCITY_WEIGHT, RESET = a.seed, a.velocity_weight, tuple(csv(a.reset))
    if a.results:
        RES = Path(a.results).resolve()
        MD = RES / "nclaw.md"
    if a.report:
        return report()
    deadline = time.time() + 60 * a.budget_min
    mats = csv(a.materials)
    for m in mats:
        if m not in MATERIALS:
            raise SystemExit(f"--materials: unknown '{m}' (choose from {', '.join(MATERIALS)})")
    for backend in csv(a.backends):
        for i, m in enumerate(mats):
            left = deadline - time.time()
            share = left / max(len(mats) - i, 1)           # split what is left among the materials to go
            s = train(m, backend, a.segment_fraction, a.epochs, share, a.precision)
            if s is None or s.get("status") != "ok":
                if s and s.get("status") == "failed":
                    log(f"{m}/{backend}: training failed at epoch {s['epochs']} of {a.epochs} (exit code "
                        f"{s['exit_code']}; its log is in {RES / 'train' / f'{m}_{backend}'})")
                else:
                    log(f"{m}/{backend}: training at epoch {s['epochs'] if s else 0} of {a.epochs}; rerun to continue")
                continue
            weights = RES / "train" / f"{m}_{backend}" / "nclaw_weights.safetensors"
            cases = csv(a.cases)
            evaluate(m, backend, weights, "ours", cases, a.precision)
            evaluate(m, backend, None, "ours-init", ["reconstruction"], a.precision, init_seed=SEED)
            if a.extras:
                extras(m, backend, weights, a.precision, a.learned_cfl_limit)
            if a.baselines:
                lab = train(m, backend, 1.0, a.epochs, deadline - time.time(), a.precision, "labeled")
                if lab is not None and lab.get("status") == "ok":
                    evaluate(m, backend, RES / "train" / f"{m}_{backend}_labeled" / "nclaw_weights.safetensors",
                             "labeled", ["reconstruction"], a.precision)
                sid = train(m, backend, a.segment_fraction, a.epochs, deadline - time.time(), a.precision, "sysid")
                if sid is not None and sid.get("status") == "ok":
                    evaluate(m, backend, None, "sys-id", ["reconstruction"], a.precision,
                             {k: v["recovered"] for k, v in sid["parameters"].items()})
    report()


if __name__ == "__main__":
    os.environ.setdefault("WARP_QUIET", "1")
    main()
