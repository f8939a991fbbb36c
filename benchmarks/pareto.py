"""Run time against error on the analytic-reference scenes (issue #5 items 1 and 2).

    python benchmarks/pareto.py                 # default sweep (~15-25 min on 2 busy CPU cores)
    python benchmarks/pareto.py --quick         # a few points per scene (smoke run)
    python benchmarks/pareto.py --full          # adds finer grids (much longer)
    python benchmarks/pareto.py --scenes mms,bar --backends jax
    python benchmarks/pareto.py --from-json benchmarks/results/pareto_multirun.json   # a Hydra multirun's points

Scenes (``mpmlab.tasks.bench``, which also serves ``mpmlab -m task=bench ...``): vibrating bar (1a),
Ritter dam break (3a), hydrostatic column (3c), the manufactured solution with body forces (2a; free-
floating variant ``mms`` and the note's slip-wall variant ``mms_slip``). Swept: grid spacing, time-step
factor (CFL), particles per cell, transfer, precision, backend. Each point records the steady-state wall
time of its steps (compiled stepper, best of ``--repeats``, compile measured separately) and its error
against the reference.

Writes ``benchmarks/results/pareto.json`` (all points + convergence orders), ``benchmarks/pareto.md``
(table), ``benchmarks/figures/pareto_<scene>.png`` (log-log error vs wall time, Pareto front marked)
and the ``pareto`` section of ``benchmarks/README.md``.
"""
from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _harness as H  # noqa: E402
from _harness import machine_info, write_readme_section  # noqa: E402

H.on_path(H.ROOT)
HERE = H.HERE
RESULTS = H.RESULTS / "pareto.json"
TABLE = HERE / "pareto.md"
FIGURES = H.FIGURES


def sweep(quick: bool, full: bool) -> list[dict]:
    """Points as dicts of run_point keyword arguments. One-factor-at-a-time around a base setting per
    scene, plus a grid-spacing x transfer block (the convergence orders come from it)."""
    P = []

    def add(scene, res, **kw):
        P.append({"scene": scene, "resolution": res, **kw})

    if quick:
        for tr in ("pic", "apic"):
            for n in (8, 16):
                add("mms", n, transfer=tr, precision="fp64")
        add("mms", 8, transfer="apic", precision="fp64", backend="warp")
        add("bar", 25, transfer="apic", precision="fp64")
        add("ritter", 0.02, transfer="apic", precision="fp32")
        add("hydrostatic", 0.02, transfer="pic", precision="fp64")
        return P
    mms_res = (8, 16, 32, 64) if full else (8, 16, 32)
    for prec in ("fp32", "fp64"):
        for tr in ("pic", "apic", "mls"):
            for n in mms_res:
                add("mms", n, transfer=tr, precision=prec)
    for cfl in (0.15, 0.5):
        add("mms", 16, transfer="apic", precision="fp64", cfl=cfl)
        add("mms", 32, transfer="apic", precision="fp64", cfl=cfl)
    add("mms", 16, transfer="apic", precision="fp64", particles_per_axis=3)
    add("mms", 32, transfer="apic", precision="fp64", particles_per_axis=3)
    for n in mms_res:
        add("mms", n, transfer="apic", precision="fp64", backend="warp")
        add("mms", n, transfer="apic", precision="fp32", backend="warp")
    for tr in ("apic", "mls"):
        for n in mms_res:
            add("mms_slip", n, transfer=tr, precision="fp64")
    for tr in ("apic", "mls"):
        for n in ((25, 50, 100, 200) if full else (25, 50, 100)):
            add("bar", n, transfer=tr, precision="fp64")
    add("bar", 50, transfer="apic", precision="fp32")
    add("bar", 50, transfer="apic", precision="fp64", cfl=0.3)
    add("bar", 50, transfer="apic", precision="fp64", particles_per_axis=1)
    add("bar", 50, transfer="apic", precision="fp64", backend="warp")
    for tr in ("apic", "flip"):
        for dx in ((0.02, 0.01, 0.005) if full else (0.02, 0.01)):
            add("ritter", dx, transfer=tr, precision="fp32")
    add("ritter", 0.02, transfer="apic", precision="fp32", particles_per_axis=3)
    add("ritter", 0.02, transfer="apic", precision="fp32", cfl=0.15)
    add("ritter", 0.02, transfer="apic", precision="fp32", backend="warp")
    for dx in ((0.02, 0.01, 0.005, 0.0025) if full else (0.02, 0.01, 0.005)):
        add("hydrostatic", dx, transfer="pic", precision="fp64")
    add("hydrostatic", 0.01, transfer="apic", precision="fp64")
    add("hydrostatic", 0.01, transfer="pic", precision="fp32")
    add("hydrostatic", 0.01, transfer="pic", precision="fp64", particles_per_axis=2)
    add("hydrostatic", 0.01, transfer="pic", precision="fp64", backend="warp")
    return P


def label(r: dict) -> str:
    return (f"{r['backend']}/{r['transfer']}/{r['precision']} res={r['resolution']:g} cfl={r['cfl']:g} "
            f"ppc={r['particles_per_cell']}")


def pareto_front(rows: list[dict]) -> list[dict]:
    """Points not dominated in (wall time, error): sorted by wall time, each with a smaller error than all faster ones."""
    front, best = [], math.inf
    for r in sorted(rows, key=lambda r: (r["wall_s"], r["error"])):
        if r["error"] < best:
            front.append(r)
            best = r["error"]
    return front


def convergence_orders(rows: list[dict]) -> list[dict]:
    """Observed orders p = log(e1 / e2) / log(dx1 / dx2) between successive refinements, for every group of
    points that differ only in grid spacing (same scene, backend, transfer, precision, CFL, particles per cell)."""
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        key = (r["scene"], r["backend"], r["transfer"], r["precision"], r["cfl"], r["particles_per_axis"])
        groups.setdefault(key, []).append(r)
    out = []
    for key, g in groups.items():
        g = sorted(g, key=lambda r: -r["dx"])
        if len(g) < 2:
            continue
        pairs = []
        for a, b in zip(g[:-1], g[1:]):
            if a["error"] > 0 and b["error"] > 0:
                pairs.append(math.log(a["error"] / b["error"]) / math.log(a["dx"] / b["dx"]))
        entry = {"scene": key[0], "backend": key[1], "transfer": key[2], "precision": key[3], "cfl": key[4],
                 "particles_per_axis": key[5], "dx": [r["dx"] for r in g], "error": [r["error"] for r in g],
                 "orders": pairs}
        if "F_error" in g[0]:
            entry["F_orders"] = [math.log(a["F_error"] / b["F_error"]) / math.log(a["dx"] / b["dx"])
                                 for a, b in zip(g[:-1], g[1:])]
        out.append(entry)
    return out


def plot(rows: list[dict], scene: str, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.6))
    markers = {"pic": "s", "flip": "v", "apic": "o", "mls": "^", "tpic": "D"}
    colors = {("jax", "fp32"): "tab:blue", ("jax", "fp64"): "tab:cyan", ("warp", "fp32"): "tab:red",
              ("warp", "fp64"): "tab:orange"}
    seen = set()
    for r in rows:
        key = (r["backend"], r["precision"], r["transfer"])
        lab = "/".join(key) if key not in seen else None
        seen.add(key)
        ax.scatter(r["wall_s"], r["error"], marker=markers.get(r["transfer"], "o"),
                   color=colors.get((r["backend"], r["precision"]), "k"), s=30, label=lab, alpha=0.8)
    front = pareto_front(rows)
    ax.plot([r["wall_s"] for r in front], [r["error"] for r in front], "k--", lw=1, label="Pareto front")
    ax.scatter([r["wall_s"] for r in front], [r["error"] for r in front], facecolors="none", edgecolors="k", s=90)
    for r in front:
        ax.annotate(f"{r['resolution']:g}", (r["wall_s"], r["error"]), textcoords="offset points", xytext=(5, 4), fontsize=7)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("steady-state wall time [s] (compile excluded)")
    ax.set_ylabel(f"error: {rows[0]['metric']}")
    ax.set_title(f"{scene}: error vs run time ({len(rows)} points; front labelled with resolution)", fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, loc="best")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def report(rows: list[dict], machine: dict, args_text: str, wall_total: float) -> None:
    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    orders = convergence_orders(rows)
    H.write_json(RESULTS, {"machine": machine, "command": args_text, "sweep_wall_s": wall_total, "points": rows,
                           "convergence": orders})
    FIGURES.mkdir(parents=True, exist_ok=True)
    lines = [f"# Run time against error (`{args_text}`)", "",
             f"Machine: {machine.get('cpu')}, {machine.get('cores')} cores (shared with other jobs), "
             f"jax {machine.get('jax')}, warp {machine.get('warp')}. Sweep took {wall_total / 60:.1f} min.",
             "`wall_s`: steady-state time of the point's steps (compiled stepper, compile excluded); `compile_s`: "
             "first call minus steady state (compilation and frame output). * = on the Pareto front.", ""]
    readme = []
    for sc in scenes:
        R = [r for r in rows if r["scene"] == sc]
        front = pareto_front(R)
        ids = {id(r) for r in front}
        plot(R, sc, FIGURES / f"pareto_{sc}.png")
        lines += [f"## {sc}: {R[0]['metric']} (resolution = {R[0]['resolution_meaning']})", "",
                  *H.md_table(["front", "backend", "transfer", "prec", "resolution", "dx", "cfl", "ppc", "particles",
                               "steps", "error", "wall_s", "compile_s"],
                              (["*" if id(r) in ids else "", r["backend"], r["transfer"], r["precision"],
                                f"{r['resolution']:g}", f"{r['dx']:.4g}", f"{r['cfl']:g}", r["particles_per_cell"],
                                r["particles"], r["steps"], f"{r['error']:.3e}", f"{r['wall_s']:.3f}",
                                f"{r['compile_s']:.2f}"] for r in sorted(R, key=lambda r: r["wall_s"])))]
        lines.append("")
        readme.append(f"**{sc}** ({R[0]['metric']}): front = " + "; ".join(
            f"{r['backend']}/{r['transfer']}/{r['precision']} res {r['resolution']:g}, cfl {r['cfl']:g}, ppc "
            f"{r['particles_per_cell']} ({r['error']:.2e} in {r['wall_s']:.2f} s)" for r in front) + "\n\n"
            f"![{sc}](figures/pareto_{sc}.png)\n\n")
    lines += ["## Convergence orders (successive refinements, same other settings)", "",
              *H.md_table(["scene", "backend", "transfer", "prec", "cfl", "ppc/axis", "dx", "error", "observed orders",
                           "F orders"],
                          ([o["scene"], o["backend"], o["transfer"], o["precision"], f"{o['cfl']:g}",
                            o["particles_per_axis"], ", ".join(f"{d:.3g}" for d in o["dx"]),
                            ", ".join(f"{e:.2e}" for e in o["error"]), ", ".join(f"{p:.2f}" for p in o["orders"]),
                            ", ".join(f"{p:.2f}" for p in o.get("F_orders", []))] for o in orders))]
    TABLE.write_text("\n".join(lines) + "\n")
    mms = [o for o in orders if o["scene"].startswith("mms") and o["backend"] == "jax" and o["precision"] == "fp64"
           and o["cfl"] == 0.3 and o["particles_per_axis"] == 2]
    conv = "".join(f"- {o['scene']} {o['transfer']}: orders {', '.join(f'{p:.2f}' for p in o['orders'])} "
                   f"(dx {', '.join(f'{d:.3g}' for d in o['dx'])})\n" for o in mms)
    body = (f"`python benchmarks/pareto.py` ({args_text}); all points in `results/pareto.json`, the table in "
            f"[pareto.md](pareto.md). Hydra: `mpmlab -m task=bench task.scene=mms task.resolution=8,16,32 "
            f"transfer=pic,apic,mls task.out=$PWD/benchmarks/results/pareto_multirun.json` (or "
            f"`mpmlab -m experiment=pareto_mms task.out=...`), then `python benchmarks/pareto.py --from-json "
            f"benchmarks/results/pareto_multirun.json`.\n\n"
            f"Machine: {machine.get('cpu')}, {machine.get('cores')} cores shared with other jobs: wall times are "
            f"comparable within one sweep only.\n\n" + "".join(readme) +
            "**Convergence orders** of the MMS displacement error (JAX fp64, CFL 0.3, 2x2 particles per cell; "
            "A = 0.05 as in verification note #2a):\n\n" + conv + "\n"
            "With A = 0.05 a particle crosses 1-3 cells; APIC's error then stalls at ~0.4 % of A from 32 cells "
            "on (grid-crossing / particle-quadrature error, Steffen et al. 2008; unchanged for CFL 0.15-0.5, so "
            "not a time-step error). At A = 0.005 APIC converges at order 2.2 and MLS at 2.4 (16 -> 32 cells, tests/test_convergence.py). "
            "PIC is first order (its per-step projection error, O(dx^2 / dt)). The slip-wall variant is "
            "limited to about first order by the wall: quadratic B-splines put 1/8 of the face traction on the "
            "first free node and hold the ghost node at v_n = 0 instead of the mirror value.\n")
    write_readme_section(HERE / "README.md", "pareto", "Run time against error (Pareto fronts, convergence orders)", body)


def main(argv=None) -> None:
    ap = H.parser(__doc__, raw=True)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--full", action="store_true")
    ap.add_argument("--scenes", default="bar,ritter,hydrostatic,mms,mms_slip")
    H.add_backends(ap)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--from-json", default=None, help="make the report from a JSON list of points (task=bench out)")
    args = ap.parse_args(argv)
    args_text = " ".join(["pareto.py"] + (argv if argv is not None else sys.argv[1:]))
    machine = machine_info()
    if args.from_json:
        rows = json.loads(Path(args.from_json).read_text())
        report(rows, machine, args_text, 0.0)
        return
    from mpmlab.tasks.bench import run_point

    scenes, backends = args.scenes.split(","), args.backends.split(",")
    pts = [p for p in sweep(args.quick, args.full) if p["scene"] in scenes and p.get("backend", "jax") in backends]
    rows, t0 = [], time.perf_counter()
    for i, p in enumerate(pts):
        r = run_point(repeats=args.repeats, **p)
        rows.append(r)
        print(f"[{i + 1}/{len(pts)}] {r['scene']:11s} {label(r):50s} error={r['error']:.3e} wall={r['wall_s']:.3f}s "
              f"compile={r['compile_s']:.2f}s  ({(time.perf_counter() - t0) / 60:.1f} min)", flush=True)
    report(rows, machine, args_text, time.perf_counter() - t0)


if __name__ == "__main__":
    main()
