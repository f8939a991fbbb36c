"""Large-shear manufactured solutions (issue 19, item 4): which shape function x transfer pairs survive
the twisted annulus (peak shear 7.07) and the twisted vortex (peak shear 6.0) to past the peak
deformation, their L2 displacement error vs dx, the time of divergence and its diagnosed cause.

    python benchmarks/large_shear.py                 # dx 0.1 / 0.05 / 0.025, JAX fp64 (reduced size)
    python benchmarks/large_shear.py --full          # adds dx 0.0125 (the issue's finest grid)
    python benchmarks/large_shear.py --report        # table + plot from the saved results only

Resumable: every finished run is written to benchmarks/results/large_shear.json at once (keyed by its
configuration) and skipped on the next start. The table goes into benchmarks/large_shear.md between
the ``<!-- table -->`` markers, the plot to benchmarks/results/large_shear_convergence.png.

Axes: solution x transfer x shape function x dx (+ a low-amplitude annulus A = 0.1 and a dt/2 rerun
of the annulus). A new shape function is one more value in ``SHAPES`` (and in
``mpmlab.scenes.large_shear.SHAPE_FUNCTIONS``).
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent
sys.path.insert(0, str(ROOT.parent))

from mpmlab.scenes import large_shear as LS  # noqa: E402

RESULTS = ROOT / "results" / "large_shear.json"
PLOT = ROOT / "results" / "large_shear_convergence.png"
MD = ROOT / "large_shear.md"
SHAPES = LS.SHAPE_FUNCTIONS
TRANSFERS = ("pic", "apic", "mls")
FRAMES = 22                      # t_end = 0.55: frames every 0.025 s; t = 0.1 is frame 4, t = 0.5 frame 20
T_EARLY = 0.1


def configs(full: bool):
    dxs = (0.1, 0.05, 0.025) + ((0.0125,) if full else ())
    for sol in ("annulus", "vortex"):
        for sf in SHAPES:
            for tr in TRANSFERS:
                for dx in dxs:
                    yield {"solution": sol, "A": LS.SOLUTIONS[sol].A, "transfer": tr, "shape_function": sf, "dx": dx,
                           "dt_scale": 1.0}
    for dx in dxs:                                    # a tenth of the amplitude (shear 0.71)
        yield {"solution": "annulus", "A": 0.1, "transfer": "apic", "shape_function": "quadratic", "dx": dx,
               "dt_scale": 1.0}
    for dx in dxs[:2]:                                # halving dt (the old message's advice)
        yield {"solution": "annulus", "A": 1.0, "transfer": "apic", "shape_function": "quadratic", "dx": dx,
               "dt_scale": 0.5}


def key(c) -> str:
    return "|".join(f"{k}={c[k]}" for k in sorted(c))


def load() -> dict:
    return json.loads(RESULTS.read_text()) if RESULTS.exists() else {}


def save(res: dict) -> None:
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    tmp = RESULTS.with_suffix(".tmp")
    tmp.write_text(json.dumps(res, indent=1, default=float))
    os.replace(tmp, RESULTS)


def run_one(c) -> dict:
    tw = LS.solution(c["solution"], A=c["A"])
    out = LS.run(tw, dx=c["dx"], backend="jax", transfer=c["transfer"], precision="fp64",
                 shape_function=c["shape_function"], frames=FRAMES, dt_scale=c["dt_scale"])
    m = out.pop("measures", None) or {}
    out["measures"] = {k: v for k, v in m.items() if not k.startswith("frames_")}
    out["frames_J"] = {k: m.get(k) for k in ("frames_step", "frames_J_min", "frames_J_max", "frames_speed_max")}
    return out


def err_at(r, t):
    for h in r["history"]:
        if abs(h["t"] - t) < 1e-9:
            return h["displacement_error"]
    return None


def orders(rows, t):
    """Observed order between successive dx of the L2 displacement error at time t."""
    pts = [(r["dx"], err_at(r, t)) for r in rows]
    out = []
    for (d1, e1), (d2, e2) in zip(pts, pts[1:]):
        out.append(math.log(e1 / e2) / math.log(d1 / d2) if e1 and e2 else None)
    return out


def fmt(x, f="{:.3g}"):
    return "--" if x is None else f.format(x)


def table(res: dict) -> str:
    rows = list(res.values())
    groups: dict = {}
    for r in rows:
        g = (r["solution"], r["A"], r["transfer"], r["shape_function"], r.get("dt_scale", 1.0))
        groups.setdefault(g, []).append(r)
    lines = ["| solution | A (peak shear) | shape fn | transfer | dt | dx | particles | survives to t = 0.55? | "
             "t diverged | cause | L2 err t=0.1 [m] | order | L2 err t=0.5 [m] | order |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for g in sorted(groups, key=lambda g: (g[0], -g[1], g[3], g[2], -g[4])):
        rs = sorted(groups[g], key=lambda r: -r["dx"])
        o1, o2 = orders(rs, T_EARLY), orders(rs, 0.5)
        for i, r in enumerate(rs):
            lines.append(
                f"| {r['solution']} | {r['A']:g} ({r['peak_shear']:.2f}) | {r['shape_function']} | {r['transfer']} | "
                f"{'dt/2' if r.get('dt_scale', 1.0) != 1.0 else 'dt'} | {r['dx']:g} | {r['particles']} | "
                f"{'no' if r['diverged'] else 'yes'} | {fmt(r.get('t_diverged'), '{:.3f}')} | "
                f"{r.get('cause') or '--'} | {fmt(err_at(r, T_EARLY))} | {fmt(o1[i - 1] if i else None, '{:.2f}')} | "
                f"{fmt(err_at(r, 0.5))} | {fmt(o2[i - 1] if i else None, '{:.2f}')} |")
    return "\n".join(lines)


def plot(res: dict) -> None:
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    groups: dict = {}
    for r in res.values():
        if r.get("dt_scale", 1.0) != 1.0:
            continue
        groups.setdefault((r["solution"], r["A"], r["transfer"], r["shape_function"]), []).append(r)
    for (sol, A, tr, sf), rs in sorted(groups.items()):
        rs = sorted(rs, key=lambda r: r["dx"])
        lab = f"{sol} A={A:g} {tr} {sf}"
        dx = [r["dx"] for r in rs if err_at(r, T_EARLY)]
        e = [err_at(r, T_EARLY) for r in rs if err_at(r, T_EARLY)]
        axes[0].loglog(dx, e, "o-", label=lab)
        td = [r["t_diverged"] if r["diverged"] else r["t_end"] for r in rs]
        axes[1].plot([r["dx"] for r in rs], td, "o-", label=lab)
    d = np.array([0.0125, 0.1])
    axes[0].loglog(d, 0.02 * (d / 0.1) ** 2, "k--", label="slope 2")
    axes[0].loglog(d, 0.02 * (d / 0.1), "k:", label="slope 1")
    axes[0].set(xlabel="dx [m]", ylabel="L2 displacement error at t = 0.1 [m]", title="error before any blow-up")
    axes[1].set(xscale="log", xlabel="dx [m]", ylabel="time of divergence (0.55: survived) [s]",
                title="divergence time (peak shear at t = 0.5)")
    axes[1].axhline(0.5, color="gray", lw=0.8)
    axes[0].legend(fontsize=6)
    axes[1].legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(PLOT, dpi=110)


def write_md(res: dict) -> None:
    if not MD.exists():
        return
    text = MD.read_text()
    a, b = "<!-- table -->", "<!-- /table -->"
    if a in text and b in text:
        text = text[: text.index(a) + len(a)] + "\n" + table(res) + "\n" + text[text.index(b):]
        MD.write_text(text)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--full", action="store_true", help="add dx = 0.0125")
    ap.add_argument("--report", action="store_true", help="table and plot from saved results only")
    ap.add_argument("--only", default="", help="run only configurations whose key contains this")
    args = ap.parse_args()
    res = load()
    if not args.report:
        for c in configs(args.full):
            k = key(c)
            if k in res or args.only not in k:
                continue
            t0 = time.perf_counter()
            r = run_one(c)
            r.update(c)
            res[k] = r
            save(res)
            print(f"{k}: diverged={r['diverged']} t={r.get('t_diverged')} cause={r.get('cause')} "
                  f"err(t=0.1)={err_at(r, T_EARLY)} ({time.perf_counter() - t0:.1f} s)", flush=True)
    print(table(res))
    plot(res)
    write_md(res)


if __name__ == "__main__":
    main()
