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
T_EARLY = 0.05                   # before the blow-up on every grid (the annulus at dx 0.0125 rings from t ~ 0.1)
T_SCORE = (0.05, 0.1, 0.3, 0.5)


def configs(full: bool):
    dxs = (0.1, 0.05, 0.025) + ((0.0125,) if full else ())
    for sol in ("annulus", "vortex"):
        for sf in SHAPES:
            for tr in TRANSFERS:
                for dx in dxs:
                    yield {"solution": sol, "A": LS.SOLUTIONS[sol].A, "transfer": tr, "shape_function": sf, "dx": dx,
                           "dt_scale": 1.0}
    for sol, A in (("annulus", 0.1), ("annulus", 0.25), ("vortex", 1.5), ("vortex", 0.6)):
        for dx in dxs:                                # smaller amplitudes: shear 0.71 / 1.77 / 1.5 / 0.6
            yield {"solution": sol, "A": A, "transfer": "apic", "shape_function": "quadratic", "dx": dx,
                   "dt_scale": 1.0}
    for extra in ({"law": "hencky"}, {"ppa": 3}):     # another law; 3 x 3 particles per cell
        for dx in dxs[:3]:
            yield {"solution": "annulus", "A": 1.0, "transfer": "apic", "shape_function": "quadratic", "dx": dx,
                   "dt_scale": 1.0, **extra}
    for sol in ("annulus", "vortex"):                  # 4 x 4 particles per cell: particles stay closer than a
        for sf in SHAPES:                             # window's reach along the stretch (spacing x peak stretch ~7)
            for tr in TRANSFERS:
                for dx in dxs:
                    yield {"solution": sol, "A": LS.SOLUTIONS[sol].A, "transfer": tr, "shape_function": sf, "dx": dx,
                           "dt_scale": 1.0, "ppa": 4}
    for dx in dxs:                                    # the surviving pair at dt/2: time or space error at the peak?
        yield {"solution": "vortex", "A": LS.SOLUTIONS["vortex"].A, "transfer": "apic", "shape_function": "cubic",
               "dx": dx, "dt_scale": 0.5, "ppa": 4}
    for dx in dxs:                                    # the surviving pair on the other backend
        yield {"solution": "vortex", "A": LS.SOLUTIONS["vortex"].A, "transfer": "apic", "shape_function": "cubic",
               "dx": dx, "dt_scale": 1.0, "ppa": 4, "backend": "warp"}
    for dx in dxs:                                    # CPDI's surviving pair (2 x 2 per cell) on the other backend
        yield {"solution": "vortex", "A": LS.SOLUTIONS["vortex"].A, "transfer": "apic", "shape_function": "cpdi",
               "dx": dx, "dt_scale": 1.0, "backend": "warp"}
    for extra in ({"dt_scale": 0.5}, {"ppa": 4}):      # CPDI's pair on the finest grid: time step or particles?
        for dx in dxs:
            yield {"solution": "vortex", "A": LS.SOLUTIONS["vortex"].A, "transfer": "apic", "shape_function": "cpdi",
                   "dx": dx, "dt_scale": 1.0, "backend": "warp", **extra}
    for dx in dxs[2:]:                                # ... and dt/4 on the two finest: is the time error the floor?
        yield {"solution": "vortex", "A": LS.SOLUTIONS["vortex"].A, "transfer": "apic", "shape_function": "cpdi",
               "dx": dx, "dt_scale": 0.25, "backend": "warp"}
    for dt_scale in (1.0, 0.5):                       # the disc whose shear vanishes smoothly at the free rim:
        for backend in ("warp", "jax"):               # is vortex's finest-grid floor its rim?
            for dx in dxs:
                yield {"solution": "vortex3", "A": LS.SOLUTIONS["vortex3"].A, "transfer": "apic",
                       "shape_function": "cpdi", "dx": dx, "dt_scale": dt_scale, "backend": backend}
    for dx, dt_scale in ((0.05, 1.5), (0.025, 1.5), (0.0125, 0.75)):   # vortex3's late divergence at the CFL-0.3
        if dx in dxs:                                                   # dt: how does it move with dt?
            yield {"solution": "vortex3", "A": LS.SOLUTIONS["vortex3"].A, "transfer": "apic", "shape_function": "cpdi",
                   "dx": dx, "dt_scale": dt_scale, "backend": "warp"}
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
    tw = LS.solution(c["solution"], A=c["A"], law=c.get("law", "fixed_corotated"))
    out = LS.run(tw, dx=c["dx"], backend=c.get("backend", "jax"), transfer=c["transfer"], precision="fp64",
                 shape_function=c["shape_function"], frames=FRAMES, dt_scale=c["dt_scale"],
                 particles_per_axis=c.get("ppa", 2))
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
        g = (r["solution"], r["A"], r["transfer"], r["shape_function"], r.get("dt_scale", 1.0),
             r.get("law", "fixed_corotated"), r.get("ppa", 2), r.get("backend", "jax"))
        groups.setdefault(g, []).append(r)
    lines = ["| solution | A (peak shear) | law | ppc | shape fn | transfer | backend | dt | dx | particles | survives to t = 0.55? | "
             "t diverged | cause | " + " | ".join(f"L2 err t={t:g} [m] | order" for t in T_SCORE) + " |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|" + "---|---|" * len(T_SCORE)]
    for g in sorted(groups, key=lambda g: (g[0], -g[1], g[5], g[6], g[3], g[2], g[7], -g[4])):
        rs = sorted(groups[g], key=lambda r: -r["dx"])
        od = {t: orders(rs, t) for t in T_SCORE}
        for i, r in enumerate(rs):
            cols = " | ".join(f"{fmt(err_at(r, t))} | {fmt(od[t][i - 1] if i else None, '{:.2f}')}" for t in T_SCORE)
            lines.append(
                f"| {r['solution']} | {r['A']:g} ({r['peak_shear']:.2f}) | {r.get('law', 'fixed_corotated')} | "
                f"{r.get('ppa', 2) ** 2} | {r['shape_function']} | {r['transfer']} | {r.get('backend', 'jax')} | "
                f"{'dt' if r.get('dt_scale', 1.0) == 1.0 else 'dt/%g' % (1.0 / r['dt_scale'])} | {r['dx']:g} | {r['particles']} | "
                f"{'no' if r['diverged'] else 'yes'} | {fmt(r.get('t_diverged'), '{:.3f}')} | "
                f"{r.get('cause') or '--'} | {cols} |")
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
        if r.get("dt_scale", 1.0) != 1.0 or r.get("law", "fixed_corotated") != "fixed_corotated" or r.get("ppa", 2) != 2:
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
    axes[0].loglog(d, 0.01 * (d / 0.1) ** 2, "k--", label="slope 2")
    axes[0].loglog(d, 0.01 * (d / 0.1), "k:", label="slope 1")
    axes[0].set(xlabel="dx [m]", ylabel=f"L2 displacement error at t = {T_EARLY:g} [m]", title="error before any blow-up")
    axes[1].set(xscale="log", xlabel="dx [m]", ylabel="time of divergence (0.55: survived) [s]",
                title="divergence time (peak shear at t = 0.5)")
    axes[1].axhline(0.5, color="gray", lw=0.8)
    axes[0].legend(fontsize=6)
    axes[1].legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(PLOT, dpi=110)


PLOT_CPDI = ROOT / "results" / "large_shear_cpdi.png"


def plot_cpdi(res: dict) -> None:
    """The survivors: CPDI + APIC (2 x 2 per cell) on the two discs, L2 error against dx at t = 0.3 / 0.5 /
    0.55, JAX (filled) and Warp (open), with order-1 and order-2 slopes; a diverged run ends its line."""
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return
    cases = [("vortex", 0.5, "vortex (shear ~ 1 - R at the rim), dt/2"), ("vortex3", 0.5, "vortex3 (smooth rim), dt/2"),
             ("vortex3", 1.0, "vortex3, CFL-0.3 dt")]
    fig, axes = plt.subplots(1, len(cases), figsize=(5 * len(cases), 4.2), sharey=True)
    for ax, (sol, ds, title) in zip(axes, cases):
        for be, mk in (("jax", "o"), ("warp", "s")):
            rows = sorted([r for r in res.values() if r["solution"] == sol and r["shape_function"] == "cpdi"
                           and r["transfer"] == "apic" and r.get("ppa", 2) == 2 and r.get("dt_scale", 1.0) == ds
                           and r.get("backend", "jax") == be], key=lambda r: -r["dx"])
            for t, col in ((0.3, "tab:blue"), (0.5, "tab:red"), (0.55, "tab:green")):
                pts = [(r["dx"], err_at(r, t)) for r in rows if err_at(r, t)]
                if pts:
                    ax.loglog(*zip(*pts), marker=mk, color=col, mfc=col if be == "jax" else "none",
                              ms=8 if be == "jax" else 4, ls="-" if be == "jax" else ":", label=f"t = {t:g} ({be})")
        d = np.array([0.1, 0.0125])
        ax.loglog(d, 0.06 * (d / 0.1), "k--", lw=0.8, label="order 1")
        ax.loglog(d, 0.06 * (d / 0.1) ** 2, "k:", lw=0.8, label="order 2")
        ax.set(title=title, xlabel="dx [m]")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    axes[0].set_ylabel("L2 displacement error [m]")
    fig.suptitle("CPDI + APIC, 2 x 2 particles per cell, fp64: a missing point is a run that diverged before t")
    fig.tight_layout()
    fig.savefig(PLOT_CPDI, dpi=110)
    plt.close(fig)


def write_md(res: dict) -> None:
    if not MD.exists():
        return
    text = MD.read_text()
    for name, body in (("table", lambda: table(res)), ("radius", radius_table)):
        a, b = f"<!-- {name} -->", f"<!-- /{name} -->"
        if a in text and b in text:
            text = text[: text.index(a) + len(a)] + "\n" + body() + "\n" + text[text.index(b):]
    MD.write_text(text)


def modes(dx: float = 0.05, transfer: str = "apic", solution: str = "annulus", nbins: int = 64) -> dict:
    """Evidence for the failure mode: roll the solution out, keeping every frame's J; per frame, the rms
    of J - 1 in radial bands (of the reference radius) and the angular spectrum of J - 1 over the
    current angle in the band where |J - 1| is largest (mode numbers; multiples of 4 are grid-aligned
    on a square grid). Writes benchmarks/results/large_shear_modes.json."""
    from mpmlab.core.errors import SimulationDiverged
    from mpmlab.simulator import build_stepper

    tw = LS.solution(solution)
    sc = LS.scene(tw, dx=dx, t_end=0.55, affine=transfer in ("apic", "mls", "tpic"), step_multiple=FRAMES * 4)
    st = build_stepper(sc, backend="jax", transfer=LS.make_transfer_for(transfer), precision="fp64")
    X0 = sc.particles().x
    R0 = np.linalg.norm(X0, axis=1)
    edges = np.linspace(tw.r_in, tw.r_out, 11)
    band = np.clip(np.digitize(R0, edges) - 1, 0, 9)
    rows = []

    def on_frame(i, npstate):
        F = np.asarray(npstate["F"], float)
        J = F[:, 0, 0] * F[:, 1, 1] - F[:, 0, 1] * F[:, 1, 0]
        x = np.asarray(npstate["x"], float)
        t = float(npstate["time"])
        gam = np.abs(LS.exact(tw, X0, t)["gamma"])
        rms = [float(np.sqrt(np.mean((J[band == b] - 1) ** 2))) for b in range(10)]
        b = int(np.argmax(rms))
        sel = band == b
        th = np.arctan2(x[sel, 1], x[sel, 0])
        k = np.clip(((th + np.pi) / (2 * np.pi) * nbins).astype(int), 0, nbins - 1)
        prof = np.bincount(k, weights=J[sel] - 1, minlength=nbins) / np.maximum(np.bincount(k, minlength=nbins), 1)
        spec = np.abs(np.fft.rfft(prof)) / nbins
        top = [int(m) for m in np.argsort(spec[1:])[::-1][:4] + 1]
        sp = np.linalg.norm(np.asarray(npstate["v"], float), axis=1)
        ex = np.linalg.norm(LS.exact(tw, X0, t)["v"], axis=1)
        rows.append({"t": t, "rms_J_minus_1_by_band": rms, "band_R": [float(edges[b]), float(edges[b + 1])],
                     "band_shear": float(np.max(gam[sel])), "max_shear": float(np.max(gam)),
                     "top_angular_modes": top, "mode_amplitudes": [float(spec[m]) for m in top],
                     "mean_mode_0": float(spec[0]), "max_speed": float(sp.max()), "max_exact_speed": float(ex.max()),
                     "cells_crossed_per_step_max": float(ex.max() * st.dt / dx)})

    out = {"dx": dx, "transfer": transfer, "solution": solution, "band_edges": edges.tolist(), "dt": st.dt,
           "shear_wave_speed": tw.wave_speeds()[0]}
    try:
        st.rollout(steps=int(round(0.55 / st.dt)), every=int(round(0.55 / st.dt)) // (FRAMES * 4), progress=False,
                   on_frame=on_frame, keep_frames=False)
        out["diverged"] = None
    except SimulationDiverged as e:
        out["diverged"] = {"step": e.step, "t": e.step * st.dt, "cause": e.cause, "message": str(e)}
    out["frames"] = rows
    path = ROOT / "results" / f"large_shear_modes_{solution}_{transfer}_{dx:g}.json"
    path.write_text(json.dumps(out, indent=1))
    return out


def by_radius(solution: str = "vortex", dxs=(0.05, 0.025, 0.0125), dt_scale: float = 0.5, backend: str = "warp",
              times=(0.3, 0.4, 0.5, 0.55), nbands: int = 10) -> dict:
    """Where the error sits: CPDI + APIC runs of ``solution`` on each dx, the RMS displacement error in
    bands of the reference radius (and its tangential mean: a lag or lead of the band) at ``times``, and
    the observed order per band between successive dx. Writes results/large_shear_radius_<solution>.json."""
    from mpmlab.simulator import build_stepper

    tw = LS.solution(solution)
    edges = np.linspace(tw.r_in, tw.r_out, nbands + 1)
    out = {"solution": solution, "dt_scale": dt_scale, "backend": backend, "band_edges": edges.tolist(), "runs": {}}
    for dx in dxs:
        sc = LS.scene(tw, dx=dx, t_end=0.55, affine=True, step_multiple=FRAMES, dt_scale=dt_scale)
        steps = int(round(0.55 / sc.resolve_dt()))
        X0 = sc.particles().x
        band = np.clip(np.digitize(np.linalg.norm(X0, axis=1), edges) - 1, 0, nbands - 1)
        st = build_stepper(sc, backend=backend, transfer=LS.make_transfer_for("apic", "cpdi"), precision="fp64",
                           shape="cpdi")
        rows = {}

        def frame(i, s):
            t = float(s["time"])
            if not any(abs(t - tt) < 1e-9 for tt in times):
                return
            ex = LS.exact(tw, X0, t)
            e = np.asarray(s["x"], float) - ex["x"]
            er = ex["x"] / np.maximum(np.linalg.norm(ex["x"], axis=1, keepdims=True), 1e-12)
            et = er[:, 0] * e[:, 1] - er[:, 1] * e[:, 0]
            rows[f"{t:.3f}"] = {"rms": float(np.sqrt(np.mean(np.sum(e**2, 1)))),
                                "rms_in_band": [float(np.sqrt(np.mean(np.sum(e[band == b] ** 2, 1)))) for b in range(nbands)],
                                "tangential_mean_in_band": [float(np.mean(et[band == b])) for b in range(nbands)]}

        st.rollout(steps=steps, every=max(1, steps // FRAMES), progress=False, on_frame=frame, keep_frames=False)
        out["runs"][str(dx)] = rows
    for t in [f"{t:.3f}" for t in times]:
        e = [np.asarray(out["runs"][str(dx)][t]["rms_in_band"]) for dx in dxs if t in out["runs"][str(dx)]]
        out.setdefault("band_orders", {})[t] = [(np.log(a / b) / np.log(2.0)).tolist() for a, b in zip(e, e[1:])]
    (ROOT / "results" / f"large_shear_radius_{solution}.json").write_text(json.dumps(out, indent=1))
    return out


def radius_table(solutions=("vortex", "vortex3")) -> str:
    """Markdown: the band RMS errors on the finest grid and the band orders of the last refinement."""
    lines = []
    for sol in solutions:
        f = ROOT / "results" / f"large_shear_radius_{sol}.json"
        if not f.exists():
            continue
        o = json.loads(f.read_text())
        edges = o["band_edges"]
        dxs = list(o["runs"])
        lines += [f"**{sol}** (CPDI + APIC, {o['backend']}, dt x {o['dt_scale']:g}): per band of the reference radius R, "
                  f"RMS error on dx {dxs[-1]} [m] / order of the last refinement ({dxs[-2]} -> {dxs[-1]})", "",
                  "| t | " + " | ".join(f"R {a:.1f}-{b:.1f}" for a, b in zip(edges, edges[1:])) + " | all |",
                  "|---|" + "---|" * (len(edges))]
        for t, ords in o["band_orders"].items():
            fin = o["runs"][dxs[-1]][t]
            prev = o["runs"][dxs[-2]][t]
            tot = math.log(prev["rms"] / fin["rms"]) / math.log(2.0)
            lines.append(f"| {float(t):.2f} | " + " | ".join(f"{e:.1e} / {p:.2f}" for e, p in zip(fin["rms_in_band"], ords[-1]))
                         + f" | {fin['rms']:.2e} / {tot:.2f} |")
        lines.append("")
    return "\n".join(lines)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--full", action="store_true", help="add dx = 0.0125")
    ap.add_argument("--report", action="store_true", help="table and plot from saved results only")
    ap.add_argument("--only", nargs="*", default=[], help="run only configurations whose key contains each of these")
    ap.add_argument("--modes", nargs="*", metavar="SOLUTION:TRANSFER:DX",
                    help="failure-mode evidence runs (J - 1 by radius and angular mode), e.g. annulus:apic:0.05")
    ap.add_argument("--by-radius", nargs="*", metavar="SOLUTION",
                    help="error by radius band, CPDI + APIC, dx 0.05/0.025/0.0125 at dt/2 on Warp (default: vortex vortex3)")
    args = ap.parse_args()
    if args.by_radius is not None:
        for sol in args.by_radius or ["vortex", "vortex3"]:
            by_radius(sol)
        print(radius_table())
        write_md(load())
        return
    if args.modes is not None:
        for spec in args.modes or ["annulus:apic:0.05"]:
            sol, tr, dx = spec.split(":")
            o = modes(float(dx), tr, sol)
            for r in o["frames"][::4]:
                print(f"t={r['t']:.3f} band R {r['band_R'][0]:.3f}-{r['band_R'][1]:.3f} (shear {r['band_shear']:.2f}, "
                      f"max {r['max_shear']:.2f}) rms|J-1| by band {[round(v, 3) for v in r['rms_J_minus_1_by_band']]} "
                      f"modes {r['top_angular_modes']} amp {[round(a, 4) for a in r['mode_amplitudes']]} "
                      f"speed {r['max_speed']:.2f}/{r['max_exact_speed']:.2f}")
            print(o["diverged"])
        return
    res = load()
    if not args.report:
        for c in configs(args.full):
            k = key(c)
            if k in res or not all(o in k for o in args.only):
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
    plot_cpdi(res)
    write_md(res)


if __name__ == "__main__":
    main()
