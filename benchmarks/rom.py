"""The deformation-map ROM (Chen et al. 2023) end to end, resumable: full-order snapshots, ``task=rom_train``
and ``task=rom_eval`` of one configuration per ``--tag`` -> ``benchmarks/rom.md`` (section ``rom-runs``) and
``benchmarks/results/rom/<tag>/`` (the training and evaluation summaries).

    python benchmarks/rom.py --study beam_2d --resolution tiny --latent 3 --batch 2 --schedule-scale 0.5 --tag beam_tiny_l3
    python benchmarks/rom.py --report                 # only rewrite the table from what is on disk

Stages, each a separate ``mpmlab`` process (a killed invocation loses at most the current epoch): (1) the
study's snapshots, one ``mpmlab experiment=rom_snapshots_<study> <run> scene.resolution=<res>`` per full-order
run (PIC, as the ROM; a run already made from the same scene and study is skipped, so this stage resumes too); (2) ``task=rom_train`` in ``benchmarks/results/rom/<tag>/train`` (committed:
checkpointed every epoch, ``--budget-min`` stops it, a rerun resumes, also from a fresh clone); (3)
``task=rom_eval`` on the test runs, every quadrature x projection and the sample counts given, once
the training is complete. Snapshots and evaluation runs live in ``benchmarks/out/rom`` (not committed). The paper's own studies (gravity, torsion, poke, tower)
run through the same stages; their tables (3-6) are not reproduced yet.
"""
from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

from _harness import OUT, RESULTS, ROOT, csv, log, machine_info, md_table, parser, write_readme_section

MD = Path(__file__).resolve().parent / "rom.md"
RES = RESULTS / "rom"
RAW = OUT / "rom"


def mpmlab(args: list[str]) -> int:
    log("$ mpmlab " + " ".join(args))
    return subprocess.run([sys.executable, "-m", "mpmlab", *args], cwd=ROOT).returncode


def snapshot_key(study: str) -> str:
    """A digest of what the study's snapshots are made from (the scene's YAML, its material and the
    study's runs): snapshots made from another version are made again, not silently reused."""
    import hashlib

    from mpmlab.rom import snapshots as S

    s = S.study(study)
    conf = ROOT / "mpmlab" / "conf"
    scene = (conf / "scene" / f"{s.scene}.yaml").read_text()
    text = scene + S.experiment_yaml(s) + repr(s.runs)
    for line in scene.splitlines():                       # the material the scene selects
        if "override /material:" in line:
            text += (conf / "material" / f"{line.split(':')[-1].strip()}.yaml").read_text()
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def snapshots(study: str, resolution: str, precision: str) -> Path:
    """The study's snapshots in ``benchmarks/out/rom/data/<study>_<resolution>_<precision>``, one full-order
    run per folder (``<run name>/``, as ``mpmlab.rom.snapshots.run_study`` lays them out), each its own
    ``mpmlab experiment=rom_snapshots_<study> <the run's overrides>`` process: a killed invocation loses
    at most the run in progress, and the next one makes only the runs without a summary (the tower's 20
    runs take over an hour on 2 cores). ``key`` records what they are made from (``snapshot_key``); a
    folder made from another version, or without a key (a Hydra sweep of an earlier version, unfinished),
    is made again from scratch."""
    from mpmlab.rom import snapshots as S

    data = RAW / "data" / f"{study}_{resolution}_{precision}"
    done = data / "complete"
    key = snapshot_key(study)
    if done.exists() and done.read_text().split() == ["ok", key]:
        return data
    stamp = data / "key"
    if data.exists() and not (stamp.exists() and stamp.read_text().strip() == key):
        log(f"{data}: made from another version of the {study} scene or study (or unfinished by an earlier "
            f"version of this script); making the snapshots again")
        shutil.rmtree(data)
    data.mkdir(parents=True, exist_ok=True)
    stamp.write_text(key + "\n")
    s = S.study(study)
    for i, r in enumerate(s.runs):
        out = data / r.name
        if (out / "summary.json").exists():
            continue
        log(f"{study}: full-order run {i + 1} of {len(s.runs)} ({r.name})")
        rc = mpmlab([f"experiment=rom_snapshots_{study}", *r.overrides, f"scene.resolution={resolution}", "backend=jax",
                     f"precision={precision}", "output.overwrite=true", f"hydra.run.dir={out}"])
        if rc != 0:
            raise SystemExit(f"snapshots of {study}, run {r.name}, failed (exit {rc})")
    done.write_text(f"ok {key}\n")
    return data


def run(a) -> None:
    data = snapshots(a.study, a.resolution, a.precision)
    # the training run (checkpoint, weights, summary) is kept with the results, so that a training longer than
    # one session resumes from a fresh clone (the snapshots are regenerated: seconds per run)
    train = RES / a.tag / "train"
    opts = [f"task.study={a.study}", f"task.data={data}", f"task.latent={a.latent}", f"task.batch={a.batch}",
            f"task.schedule_scale={a.schedule_scale}", f"task.lambda_F={a.lambda_F}", f"task.lambda_v={a.lambda_v}",
            f"task.seed={a.seed}", f"precision={a.precision}"]
    if a.schedule:
        opts.append(f"task.schedule={a.schedule}")
    if a.points:
        opts.append(f"task.points={a.points}")
    if a.frame_stride > 1:
        opts.append(f"task.frame_stride={a.frame_stride}")
    if a.budget_min:
        opts.append(f"task.stop_after_s={60.0 * a.budget_min}")
    complete = (train / "summary.json").exists() and json.loads((train / "summary.json").read_text())["status"] == "ok"
    if a.eval_only and not complete:
        raise SystemExit(f"--eval-only: {a.tag} has no complete training in {train}")
    if not complete:
        rc = mpmlab(["task=rom_train", *opts, f"hydra.run.dir={train}", "output.overwrite=true"])
        if rc != 0:
            raise SystemExit(f"rom_train failed (exit {rc})")
        t = json.loads((train / "summary.json").read_text())
        if t["status"] != "ok":
            log(f"{a.tag}: training stopped at epoch {t['epochs']} of {t['epochs_planned']} (--budget-min); rerun the "
                f"same command to continue (the checkpoint is in {train})")
            return
    suffix = ("" if a.rom_backend == "jax" else f"_{a.rom_backend}") + (f"_{a.eval_tag}" if a.eval_tag else "")
    ev = RAW / "runs" / a.tag / f"eval{suffix}"
    rc = mpmlab(["task=rom_eval", f"task.study={a.study}", f"task.data={data}",
                 f"task.weights={train / 'rom_weights.safetensors'}", f"task.samples=[{a.samples}]",
                 f"task.quadratures=[{a.quadratures}]", f"task.projections=[{a.projections}]", f"precision={a.precision}",
                 *reduced_options(a), f"hydra.run.dir={ev}",
                 "output.overwrite=true", *([f"task.max_runs={a.max_runs}"] if a.max_runs else [])])
    if rc not in (0, 3):
        raise SystemExit(f"rom_eval failed (exit {rc})")
    dst = RES / a.tag
    dst.mkdir(parents=True, exist_ok=True)
    t = json.loads((train / "summary.json").read_text())
    t.pop("history", None)                      # the loss curve is in training.png and the run's recording
    (dst / "train.json").write_text(json.dumps(t, indent=1))
    keep_eval(ev, dst / f"eval{suffix}.json")
    for f, name in ((train / "training.png", "training.png"), (ev / "rom_eval.png", f"rom_eval{suffix}.png"),
                    (ev / "rom_latent.png", f"rom_latent{suffix}.png")):
        if f.exists():
            shutil.copy(f, dst / name)


def reduced_options(a) -> list[str]:
    """The reduced model's options of every ``task=rom_eval`` this script runs."""
    return [f"task.rom_backend={a.rom_backend}", f"task.tangent={a.tangent}", f"task.kinematic={a.kinematic}",
            f"task.hold_steps={a.hold_steps}"]


def keep_eval(ev: Path, dst: Path) -> None:
    """Keep an evaluation's summary with the results, without the per-run latent trajectories."""
    e = json.loads((ev / "summary.json").read_text())
    for row in e["rows"]:
        row.pop("z", None)
    tmp = dst.with_name(dst.name + ".tmp")          # whole or not at all: --report may read it meanwhile
    tmp.write_text(json.dumps(e, indent=1))
    tmp.replace(dst)


def superres(a) -> None:
    """Tab. 4 (Sec. 5.2.1), after the torsion training: the reduced model run at the 2x finer resolution
    (its grid and its points, weights from the coarse runs; no hyper-reduction), and the tracer baseline
    (the finer points advected through the coarse full-order runs), both against the finer full-order runs."""
    if a.study != "torsion":
        raise SystemExit("--superres is Tab. 4's study: give --study torsion")
    train = RES / a.tag / "train"
    if not (train / "summary.json").exists() or json.loads((train / "summary.json").read_text())["status"] != "ok":
        raise SystemExit(f"{a.tag}: the training is not complete; run without --superres first")
    coarse = snapshots(a.study, a.resolution, a.precision)
    fine = snapshots("torsion_fine", "fine", a.precision)
    weights = train / "rom_weights.safetensors"
    suffix = "" if a.rom_backend == "jax" else f"_{a.rom_backend}"
    jobs = {f"superres{suffix}": ["task.study=torsion_fine", f"task.data={fine}", "task.samples=[all]",
                                  f"task.quadratures=[{a.quadratures}]", f"task.projections=[{a.projections}]"],
            "tracers": ["task.study=torsion", f"task.data={coarse}", "task.truth_study=torsion_fine",
                        f"task.truth_data={fine}", "task.tracer_baseline=true", "task.samples=[all]",
                        "task.quadratures=[lagrangian]", "task.projections=[linear]"]}
    for name, opts in jobs.items():
        ev = RAW / "runs" / a.tag / name
        rc = mpmlab(["task=rom_eval", *opts, f"task.weights={weights}", f"precision={a.precision}",
                     *reduced_options(a), f"hydra.run.dir={ev}", "output.overwrite=true"])
        if rc not in (0, 3):
            raise SystemExit(f"rom_eval ({name}) failed (exit {rc})")
        keep_eval(ev, RES / a.tag / f"{name}.json")


def superres_report() -> list[str]:
    rows = []
    for d in sorted(RES.glob("*/superres*.json")) if RES.exists() else []:
        e = json.loads(d.read_text())
        tr = d.parent / "tracers.json"
        tracers = json.loads(tr.read_text()) if tr.exists() else {}
        tb = tracers.get("tracer_baseline")
        coarse_rom = tracers["schemes"][0] if tracers else None
        for s in e["schemes"]:
            rows.append([d.parent.name, e["fom"].get("rom_backend", "jax"), f"ROM at 2x, {s['scheme']}", pct(s["E"]),
                         pct(s["E_displacement"]), pct(s["E_F"]), f"{s['wall_s_per_simulated_s']:.3g}"])
        if coarse_rom:
            rows.append([d.parent.name, "jax", f"coarse ROM, g at the 2x points, {coarse_rom['scheme']}",
                         pct(coarse_rom["E"]), pct(coarse_rom["E_displacement"]), pct(coarse_rom["E_F"]),
                         f"{coarse_rom['wall_s_per_simulated_s']:.3g}"])
        if tb:
            rows.append([d.parent.name, "jax (FOM)", "tracer baseline", pct(tb["E"]), pct(tb["E_displacement"]),
                         pct(tb["E_F"]), f"{tb['wall_s_per_simulated_s']:.3g}"])
    if not rows:
        return []
    return ["Tab. 4 (super-resolution): errors in % against the 2x finer full-order runs of the torsion test set "
            "(`python benchmarks/rom.py --study torsion --resolution paper ... --tag TAG --superres`). The paper: "
            "0.46-0.49 % for the four schemes, 2.04 % for the tracer baseline.", "",
            *md_table(["tag", "backend", "model", "E", "E disp.", "E_F", "s / simulated s"], rows), ""]


#: Figs. 7-8 (Sec. 5.1.1-5.1.2): gravity, no hyper-reduction; (latent, lambda_F, lambda_v) per training, tag
#: ``fig78_l{latent}_lf{lambda_F:g}_lv{lambda_v:g}`` (the paper: Fig. 7 at latent 7, Fig. 8 at lambda 100 / 0.01)
FIG78 = [(7, 0.0, 0.0), (7, 0.0, 0.01), (7, 100.0, 0.0), (7, 100.0, 0.01), (1, 100.0, 0.01), (2, 100.0, 0.01),
         (4, 100.0, 0.01)]


def fig78_tag(latent, lf, lv) -> str:
    return f"fig78_l{latent}_lf{lf:g}_lv{lv:g}"


def fig78_report() -> list[str]:
    """Figs. 7-8 from the ``fig78_*`` tags' evaluations: a table and ``results/rom/fig7_8.png``."""
    rows, pts = [], {}
    for latent, lf, lv in FIG78:
        d = RES / fig78_tag(latent, lf, lv)
        if not (d / "eval.json").exists():
            continue
        e, t = json.loads((d / "eval.json").read_text()), json.loads((d / "train.json").read_text())
        E = {s["scheme"].split(",")[0]: s["E"] for s in e["schemes"]}
        pts[(latent, lf, lv)] = E
        rows.append([latent, f"{lf:g}", f"{lv:g}", t["epochs"], pct(t.get("reconstruction_error", {}).get("test", {}).get("E"))]
                    + [pct(E.get(k)) for k in SCHEMES])
    if not rows:
        return []
    plot_fig78(pts)
    return ["Figs. 7-8 (Sec. 5.1.1-5.1.2): the gravity study, no hyper-reduction (every point a sample), E in % on the 6 "
            "test runs, tangent `next`. Each training: 480 points per snapshot, 85 epochs (the paper's schedule x 0.1), "
            "batch 8, seed 0 (`python benchmarks/rom.py --study gravity --resolution default --latent L --lambda-F LF "
            "--lambda-v LV --points 480 --schedule \"[[1e-3,50],[1e-4,20],[1e-5,10],[1e-6,5]]\" --tag "
            "fig78_lL_lfLF_lvLV --samples all --quadratures lagrangian --projections linear`). Lagrangian + linear only: "
            "with every point a sample the nonlinear projection took 1,620 s per simulated second on the shared 2 cores "
            "(about 50 min per training for the 6 test runs) and the Eulerian quadrature more; a dash is a scheme not "
            "run. The paper (Fig. 7, latent 7): errors within 0-0.3 %, λ_v helping the "
            "linear projection, λ_F all four schemes; (Fig. 8) the error falling with the latent size, latent 1 worst "
            "(up to 1 %). Plot: `results/rom/fig7_8.png`.", "",
            *md_table(["latent", "λ_F", "λ_v", "epochs", "recon. E"] + list(SCHEMES), rows), ""]


SCHEMES = ("lagrangian+nonlinear", "eulerian+nonlinear", "lagrangian+linear", "eulerian+linear")


def plot_fig78(pts: dict) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4))
    fig7 = [k for k in pts if k[0] == 7]
    for i, sch in enumerate(SCHEMES):
        ys = [100 * pts[k].get(sch, float("nan")) for k in fig7]
        a.bar([j + 0.2 * i for j in range(len(fig7))], ys, 0.2, label=sch)
    a.set_xticks([j + 0.3 for j in range(len(fig7))], [f"λ_F {k[1]:g}\nλ_v {k[2]:g}" for k in fig7])
    a.set_ylabel("position error E (%)")
    a.set_title("Fig. 7: penalties (latent 7)")
    a.legend(fontsize=7)
    fig8 = sorted(k for k in pts if k[1:] == (100.0, 0.01))
    for sch in SCHEMES:
        b.plot([k[0] for k in fig8], [100 * pts[k].get(sch, float("nan")) for k in fig8], "o-", label=sch)
    b.set_xlabel("latent size")
    b.set_ylabel("position error E (%)")
    b.set_title("Fig. 8: latent size (λ_F 100, λ_v 0.01)")
    fig.tight_layout()
    fig.savefig(RES / "fig7_8.png", dpi=110)
    plt.close(fig)


def pct(x) -> str:
    return "–" if x is None else f"{100 * x:.2f}"


def report() -> None:
    rows = []
    for d in sorted(RES.glob("*/eval*.json")) if RES.exists() else []:
        e, t = json.loads(d.read_text()), json.loads((d.parent / "train.json").read_text())
        rec = t.get("reconstruction_error", {})
        for s in e["schemes"]:
            rows.append([d.parent.name, e["study"], e["fom"].get("rom_backend", "jax"), t["latent"], t["batch"],
                         t["epochs"], t["lambda_F"],
                         pct(rec.get("test", {}).get("E")),
                         f"{s['scheme']}, {e.get('tangent', 'current')}, {e.get('kinematic', 'velocity')} hold"
                         + (f" over {e['hold_steps']:g} steps" if e.get("hold_steps", 1.0) != 1.0 else ""),
                         pct(s["E"]), pct(s.get("E_corner")), pct(s["E_displacement"]),
                         pct(s["E_v"]), pct(s["E_F"]), f"{s['wall_s_per_simulated_s']:.3g}",
                         f"{e['fom']['wall_s_per_simulated_s']:.3g}", f"{s['diverged']}/{s['runs']}"])
    body = ["Errors in % on the study's test runs, pooled over runs, snapshots and points (`mpmlab.rom.evaluate`): "
            "E about the initial centroid (the paper's measure; its origin is not stated in the paper), E about the scene "
            "domain's lower corner (`E corner`, evaluations from session 34 on; section \"The error's origin\"), and "
            "relative to the displacement, the velocity and F - I. The scheme ends with the velocity fit's tangent (`next`: "
            "dg/dx_hat at the new latent, the default since session 23; `current`: the paper's explicit one, every "
            "evaluation before it), then how particle_velocity points are held (`position`: at their prescribed positions, "
            "the default since session 38, `mpmlab.rom.kinematic`; `velocity`: their velocities only, every evaluation "
            "before it). `recon.` is the encoder + g reconstruction of the test "
            "snapshots (no time stepping). Wall times per simulated second, ROM (its backend) and full-order model "
            "(JAX, PIC) in the same process. Regenerate: `python benchmarks/rom.py --study ... --tag ...` (resumes), "
            "`--report` rewrites this table.", "",
            *md_table(["tag", "study", "ROM backend", "latent", "batch", "epochs", "λ_F", "recon. E", "scheme", "E",
                       "E corner", "E disp.", "E_v",
                       "E_F", "ROM s/s", "FOM s/s", "diverged"], rows), "",
            *superres_report(), *fig78_report(), f"Machine: {json.dumps(machine_info(load=True))}", ""]
    write_readme_section(MD, "rom-runs", "Runs (train + evaluate)", "\n".join(body))
    log(f"wrote {MD}")


def main():
    ap = parser(__doc__.splitlines()[0])
    ap.add_argument("--study", default="beam_2d")
    ap.add_argument("--resolution", default="tiny")
    ap.add_argument("--precision", default="fp64")
    ap.add_argument("--latent", type=int, default=3)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--schedule-scale", type=float, default=1.0)
    ap.add_argument("--schedule", default="", help="Adam stages as [[lr,epochs],...] (default: App. B's)")
    ap.add_argument("--lambda-F", dest="lambda_F", type=float, default=100.0)
    ap.add_argument("--lambda-v", dest="lambda_v", type=float, default=0.01)
    ap.add_argument("--points", type=int, default=0,
                    help="points per snapshot per batch in training (0: all; the loss is a mean over points)")
    ap.add_argument("--frame-stride", dest="frame_stride", type=int, default=1,
                    help="train on every k-th snapshot of each run")
    ap.add_argument("--max-runs", dest="max_runs", type=int, default=0,
                    help="evaluate only the study's first k test runs (0: all)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--samples", default="50,all", help="comma-separated |M| values (integers or all)")
    ap.add_argument("--quadratures", default="lagrangian,eulerian")
    ap.add_argument("--projections", default="linear,nonlinear")
    ap.add_argument("--tag", default="")
    ap.add_argument("--rom-backend", dest="rom_backend", default="jax", choices=("jax", "warp"),
                    help="the reduced model's backend (its evaluation is kept as eval_<backend>.json beside JAX's)")
    ap.add_argument("--budget-min", dest="budget_min", type=float, default=0.0,
                    help="stop training after this many minutes (checkpointed: rerun to continue); 0: no limit")
    ap.add_argument("--tangent", default="next", choices=("next", "current"),
                    help="where the velocity least squares takes dg/dx_hat: x_hat_(n+1), or x_hat_n as the paper "
                         "(mpmlab.rom.stepper)")
    ap.add_argument("--kinematic", default="position", choices=("position", "velocity"),
                    help="how the reduced model holds particle_velocity points: at their prescribed positions (Eq. 3) "
                         "or velocities only (before session 38): mpmlab.rom.kinematic")
    ap.add_argument("--hold-steps", dest="hold_steps", type=float, default=1.0,
                    help="the position-level hold closes a held point's error over this many steps (1: at once)")
    ap.add_argument("--eval-tag", dest="eval_tag", default="",
                    help="keep this evaluation as eval_<tag>.json beside the others (e.g. another quadrature)")
    ap.add_argument("--eval-only", dest="eval_only", action="store_true",
                    help="evaluate the tag's complete training again (its training options need not be given)")
    ap.add_argument("--superres", action="store_true",
                    help="Tab. 4 after a complete torsion training: the ROM at 2x resolution and the tracer baseline")
    ap.add_argument("--report", action="store_true", help="only rewrite benchmarks/rom.md")
    a = ap.parse_args()
    if not a.report:
        if not a.tag:
            raise SystemExit("give --tag NAME (the results folder benchmarks/results/rom/NAME)")
        csv(a.samples)
        superres(a) if a.superres else run(a)
    report()


if __name__ == "__main__":
    main()
