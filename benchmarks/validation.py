"""Validation against analytic references: vibrating bar (1a/1c), Ritter dam break (3a), hydrostatic
column (3c) -- verification note /work/shared/notes/verification.md -- on the JAX and Warp backends.

    python benchmarks/validation.py                       # everything (CPU: ~20-30 min on 2 cores)
    python benchmarks/validation.py --cases bar --backends warp
    python benchmarks/validation.py --quick               # coarse smoke run (not the reported numbers)

Writes benchmarks/out/validation.json, one PNG per case in benchmarks/out/, and the Markdown table
benchmarks/validation.md. Scenes and measurements live in ``mpmlab.scenes.validation``.
"""
from __future__ import annotations

import math
import os
import platform
import sys
import time
from pathlib import Path

import _harness as H
from _harness import log

H.quiet_warp(threads=None)
try:  # keep the log readable: no per-kernel "Module ... load" lines
    import warp

    warp.config.quiet = True
except ImportError:  # pragma: no cover
    pass

import numpy as np

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from mpmlab.scenes import validation as V  # noqa: E402

HERE = H.HERE


# ------------------------------------------------------------------------------------------------
# case definitions
# ------------------------------------------------------------------------------------------------
def bar_runs(quick):
    runs = []
    c = 25 if quick else 50
    # (label, transfer, scene kwargs)
    runs.append(("1D strip", "apic", dict(cells=c, lateral="strip")))
    runs.append(("2D free bar, 4 cells high", "apic", dict(cells=c, lateral="free", height_cells=4)))
    runs.append(("2D free bar, 4 cells high, nu=0.3 (plane strain: c = sqrt(E/((1-nu^2) rho)))", "apic",
                 dict(cells=c, lateral="free", height_cells=4, nu=0.3)))
    runs.append(("1D strip, nu=0.3 (laterally confined: c_p = sqrt((lambda+2mu)/rho))", "apic",
                 dict(cells=c, lateral="strip", nu=0.3)))
    if not quick:
        for tr in ("mls", "flip", "pic", "tpic"):
            runs.append(("1D strip", tr, dict(cells=c, lateral="strip")))
        for cc in (13, 25, 100):
            runs.append(("1D strip", "apic", dict(cells=cc, lateral="strip")))
    return runs


def dam_runs(quick, backend):
    """(transfer, scene kwargs, t_end). The library default min_pressure = 0 (no tension) unless given;
    min_pressure = -1e30 is JAX-MPM's Eq. 20 as written (the fluid carries tension)."""
    if quick:
        return [("apic", dict(dx=0.0125), 0.25)]
    runs = [("apic", dict(dx=0.008), 0.45), ("apic", dict(dx=0.004), 0.45)]
    if backend == "warp":  # investigation runs (EOS, transfer, walls): Warp is the faster CPU backend
        runs += [("apic", dict(dx=0.004, min_pressure=-1e30), 0.45), ("apic", dict(dx=0.008, min_pressure=-1e30), 0.45),
                 ("flip", dict(dx=0.008), 0.45), ("tpic", dict(dx=0.008), 0.45),
                 ("apic", dict(dx=0.008, wall="separate"), 0.45),
                 # refinement: is the lag numerical? (2 mm: 100k particles)
                 ("apic", dict(dx=0.002), 0.45),
                 # a 4 m tank (the front reaches the 2 m tank's end wall at t = 0.5 s) scored later,
                 # t sqrt(g/H0) = 6-9: does the flow approach Ritter's long-time solution?
                 ("apic", dict(dx=0.004, length=4.0), 0.9, (0.6, 0.9))]
    return runs


def column_runs(quick, backend):
    if quick:
        return [dict(dx=0.01, width=0.04)]
    if backend == "warp":  # + a 0.05 m slice: with roller sides the column is 1D, the width must not matter
        return [dict(dx=0.01), dict(dx=0.005), dict(dx=0.0025), dict(dx=0.0025, width=0.05)]
    return [dict(dx=0.01), dict(dx=0.005), dict(dx=0.0025)]


# ------------------------------------------------------------------------------------------------
def run_bar(backends, quick, rows, raw):
    results = []
    for backend in backends:
        for label, tr, kw in bar_runs(quick):
            r = V.run_vibrating_bar(backend=backend, transfer=tr, precision="fp64", periods=3.0, **kw)
            err = r["period_error"]
            row = {
                "case": "1a/1c vibrating bar", "variant": label, "backend": backend, "transfer": tr,
                "precision": "fp64", "resolution": f"{kw['cells']} cells along L=25 (dx={25 / kw['cells']:.3g} m), "
                                                  f"{r['particles']} particles, dt={r['dt']:.3g} s (CFL 0.1)",
                "measured": f"T = {r['period']:.4f} s", "reference": f"T1 = {r['reference']['period']:.4f} s",
                "error": f"{100 * err:+.2f} %", "bar": "|err| <= 1 %", "pass": bool(abs(err) <= 0.01),
                "extra": f"amplitude kept after 3 periods: {100 * r['amplitude_ratio']:.1f} %",
                "wall_s": r["build_s"] + r["run_s"], "run_s": r["run_s"], "key": "bar",
            }
            rows.append(row)
            log(f"[bar] {backend:5s} {tr:5s} {label[:28]:28s} cells={kw['cells']:4d} T={r['period']:.5f} err={100 * err:+.3f}% "
                f"amp={r['amplitude_ratio']:.4f} wall={row['wall_s']:.1f}s")
            raw.append({k: v for k, v in row.items()} | {"period": r["period"], "period_error": err,
                                                          "amplitude_ratio": r["amplitude_ratio"], "cells": kw["cells"]})
            results.append((backend, tr, label, kw, r))
    # plot: centre-of-mass velocity vs analytic; period error vs resolution
    fig, axs = plt.subplots(1, 2, figsize=(13, 4.5))
    ax = axs[0]
    for backend, tr, label, kw, r in results:
        if tr == "apic" and kw["cells"] == (25 if quick else 50) and "nu" not in kw:
            ax.plot(r["time"], r["v_com"], lw=1.2, ls="-" if backend == "jax" else "--",
                    label=f"{backend} {tr} {label}")
    ref = V.bar_reference()
    t = np.linspace(0, 30, 1000)
    ax.plot(t, ref["v_com_amplitude"] * np.cos(ref["omega"] * t), "k:", lw=2, label="analytic (2 v0/pi) cos(w1 t)")
    ax.set_xlabel("t [s]"); ax.set_ylabel("centre-of-mass velocity [m/s]"); ax.legend(fontsize=7)
    ax.set_title("Vibrating bar, first mode (E=100, rho=1, L=25, v0=0.1)")
    ax = axs[1]
    for backend in backends:
        for tr in ("apic", "mls", "flip", "pic", "tpic"):
            pts = sorted((kw["cells"], r["period_error"]) for b, tt, lab, kw, r in results
                         if b == backend and tt == tr and lab == "1D strip")
            if pts:
                c, e = zip(*pts)
                ax.plot(25.0 / np.array(c), 100 * np.abs(e), "o-" if backend == "jax" else "x--",
                        label=f"{backend} {tr}")
    ax.axhline(1.0, color="r", lw=0.8, label="1 % bar")
    ax.set_xscale("log"); ax.set_yscale("log"); ax.set_xlabel("dx [m]"); ax.set_ylabel("|period error| [%]")
    ax.set_title("Period error vs resolution (1D strip)"); ax.legend(fontsize=7)
    fig.tight_layout(); fig.savefig(OUT / "vibrating_bar.png", dpi=110); plt.close(fig)


def run_dam(backends, quick, rows, raw):
    results = []
    for backend in backends:
        for tr, kw, t_end, *win in dam_runs(quick, backend):
            window = win[0] if win else (0.2, min(0.45, t_end))
            r = V.run_dam_break(backend=backend, transfer=tr, precision="fp32", t_end=t_end, window=window, **kw)
            dx = r["scene"].dx
            lv, err = r["levels"], r["error"]
            # verification-note checkpoints x(0.02 m, 0.3 s), x(0.02 m, 0.4 s)
            cps = []
            for tc in (0.3, 0.4):
                if tc <= t_end + 1e-9:
                    f = int(np.argmin(np.abs(r["traj"].time - tc)))
                    xs = V.measure_front(r["traj"].x[f], r["traj"].volume * r["traj"].fields["J"][f], dx, [0.02],
                                         float(r["scene"].domain[1][0]))[0]
                    xr = float(V.ritter_front(0.02, r["traj"].time[f], r["H0"], r["L0"], r["g"]))
                    cps.append((tc, xs, xr))
            dt_label = f"dt={r['dt']:.3g} s" + (" (paper)" if "dt" in kw else " (CFL 0.3)")
            mx, mx_low, mx_wave = r["max_abs_error"], r["max_abs_error_low"], r["max_abs_error_wave"]
            eos = ("Eq. 20 unclamped (min_pressure=-1e30, tension)" if kw.get("min_pressure", 0.0) < 0
                   else "p >= 0 (library default)")
            walls = f", {kw['wall']} walls" if "wall" in kw else ", slip walls"
            walls += f", {kw['length']:g} m tank" if "length" in kw else ""
            row = {
                "case": "3a Ritter dam break",
                "variant": f"{eos}{walls}; y in [2dx, 0.4 H0], t in [{window[0]}, {window[1]}] s",
                "backend": backend, "transfer": tr, "precision": "fp32",
                "resolution": f"dx={dx * 1000:g} mm, 2x2 ppc, {r['particles']} particles, {dt_label}",
                "measured": "; ".join(f"x(0.02 m, {tc} s) = {xs:.4f} m" for tc, xs, xr in cps),
                "reference": "; ".join(f"{xr:.4f} m" for tc, xs, xr in cps) + " (Ritter)",
                "error": f"(A) {100 * mx:.1f} %; (B) {100 * mx_low:.1f} %; (C) {100 * mx_wave:.1f} %",
                "bar": "A <= 5 % (note); B, C: 5 %",
                "pass": bool(mx <= 0.05),
                "extra": f"tip x at t={t_end}: {r['tip'][-1]:.3f} m (Ritter {r['L0'] + 2 * math.sqrt(r['g'] * r['H0']) * t_end:.3f} m); "
                         "per-level max|e|: " + ", ".join(f"{1000 * y:.0f}mm:{100 * np.nanmax(np.abs(err[:, i])):.0f}%"
                                                          for i, y in enumerate(lv)),
                "wall_s": r["build_s"] + r["run_s"], "run_s": r["run_s"], "key": "dam",
            }
            row["extra"] = (f"B: {'pass' if mx_low <= 0.05 else 'fail'}, C: {'pass' if mx_wave <= 0.05 else 'fail'}; "
                            + row["extra"])
            rows.append(row)
            raw.append(dict(row) | {"levels": lv.tolist(), "times": r["times"].tolist(), "x_sim": r["x_sim"].tolist(),
                                    "x_ref": r["x_ref"].tolist(), "max_abs_error": mx, "max_abs_error_low": mx_low,
                                    "max_abs_error_wave": mx_wave, "checkpoints": cps, "dx": dx, "kw": kw})
            log(f"[dam] {backend:5s} {tr:5s} {kw} dt={r['dt']:.3g} A={100 * mx:.1f}% "
                f"B={100 * mx_low:.1f}% C={100 * mx_wave:.1f}% checkpoints={[(tc, round(xs, 4), round(xr, 4)) for tc, xs, xr in cps]} "
                f"tip={r['tip'][-1]:.3f} wall={row['wall_s']:.1f}s")
            results.append((backend, tr, kw, r))
    # plot: profiles of the finest APIC run per backend + error history per level
    fig, axs = plt.subplots(3, 1, figsize=(12, 10))
    first = [x for x in results if x[1] == "apic" and not {"min_pressure", "wall", "length"} & set(x[2])]
    pick = min(first, key=lambda x: (x[3]["scene"].dx, x[0] != "warp", "dt" in x[2]))
    backend, tr, kw, r = pick
    T = r["traj"]
    for k, tt in enumerate((0.2, 0.3, min(0.45, T.time[-1]))):
        f = int(np.argmin(np.abs(T.time - tt)))
        axs[0].scatter(T.x[f, :, 0], T.x[f, :, 1] + 0.12 * k, s=0.1, color=f"C{k}")
        yy = np.linspace(0, r["H0"], 100)
        axs[0].plot(V.ritter_front(yy, T.time[f], r["H0"], r["L0"], r["g"]), yy + 0.12 * k, "k", lw=1)
        axs[0].text(0.02, 0.12 * k + 0.105, f"t = {T.time[f]:.2f} s", fontsize=8)
    axs[0].set_xlim(0, 2.0); axs[0].set_yticks([]); axs[0].set_xlabel("x [m]")
    axs[0].set_title(f"Dam break ({backend}, {tr}, dx={r['scene'].dx * 1000:g} mm): particles (offset per time) vs Ritter (black)")
    for i, y in enumerate(r["levels"]):
        axs[1].plot(r["times"], 100 * r["error"][:, i], label=f"y = {1000 * y:.0f} mm")
    axs[1].axhspan(-5, 5, color="g", alpha=0.15, label="+-5 % bar")
    axs[1].set_xlabel("t [s]"); axs[1].set_ylabel("(x_sim - x_R)/(x_R - L0) [%]"); axs[1].legend(fontsize=7, ncol=4)
    axs[1].set_title("Front error per height (same run)")
    for backend, tr, kw, r in results:
        axs[2].plot(r["traj"].time, r["tip"], label=f"{backend} {tr} dx={r['scene'].dx * 1000:g}mm"
                    + (f" dt={r['dt']:.0e}" if "dt" in kw else "") + (" unclamped" if "min_pressure" in kw else "")
                    + (f" {kw['wall']}" if "wall" in kw else ""))
    t = np.linspace(0, max(x[3]["traj"].time[-1] for x in results), 50)
    axs[2].plot(t, 1.0 + 2 * np.sqrt(9.8 * 0.1) * t, "k--", label="Ritter tip L0 + 2 sqrt(g H0) t")
    axs[2].plot(t, V.ritter_front(0.02, t), "k:", label="Ritter x(y = 20 mm)")
    axs[2].set_xlabel("t [s]"); axs[2].set_ylabel("x [m]"); axs[2].legend(fontsize=7, ncol=2)
    axs[2].set_title("Foremost particle (the one-cell tip, excluded from the bar)")
    fig.tight_layout(); fig.savefig(OUT / "dam_break.png", dpi=110); plt.close(fig)


def run_column(backends, quick, rows, raw):
    results = []
    ref = V.hydrostatic_base_stress()
    for backend in backends:
        for kw in column_runs(quick, backend):
            r = V.run_hydrostatic_column(backend=backend, transfer="pic", precision="fp64", settle_periods=40.0,
                                         average_periods=4.0,
                                         law="newtonian_fluid", viscosity=0.0, base="slip", **kw)
            dx = kw["dx"]
            cb = V.CBGEO_HYDROSTATIC.get(dx)
            cb_err = None if cb is None else cb / ref - 1.0
            err = r["error"]
            row = {
                "case": "3c hydrostatic column", "variant": f"w={kw.get('width', 0.2)} m, h=0.1 m, K=1e6 Pa, slip base + rollers",
                "backend": backend, "transfer": "pic", "precision": "fp64",
                "resolution": f"dx={dx * 1000:g} mm, 25 ppc, {r['particles']} particles, dt={r['dt']:.3g} s, "
                              f"{r['steps']} steps (40 T1)",
                "measured": f"sigma_yy(0) = {r['base_stress']:.1f} Pa",
                "reference": f"{ref:.1f} Pa" + (f" (CB-Geo: {cb:.1f} Pa, {100 * abs(cb_err):.1f} %)" if cb else ""),
                "error": f"{100 * err:+.2f} %", "bar": "|err| <= CB-Geo" if cb else "(no CB-Geo value)",
                "pass": bool(cb is not None and abs(err) <= abs(cb_err)),
                "extra": f"fit above 2 dx only: {100 * r['error_inner']:+.2f} %; residual |v|max = "
                         f"{100 * r['residual_speed']:.1f} % of the undamped mode amplitude",
                "wall_s": r["build_s"] + r["run_s"], "run_s": r["run_s"], "key": "column",
            }
            rows.append(row)
            raw.append(dict(row) | {"dx": dx, "base_stress": r["base_stress"], "rel_error": err,
                                    "rel_error_inner": r["error_inner"], "cbgeo": cb})
            log(f"[column] {backend:5s} dx={dx * 1000:g}mm base={r['base_stress']:.2f} err={100 * err:+.3f}% "
                f"(inner {100 * r['error_inner']:+.3f}%) resid={r['residual_speed']:.3f} wall={row['wall_s']:.1f}s")
            results.append((backend, kw, r))
    fig, axs = plt.subplots(1, 3, figsize=(15, 4.5))
    for backend, kw, r in results:
        if backend != "warp" and len(backends) > 1 or kw.get("width", 0.2) != 0.2:
            continue
        axs[0].plot(r["sigma_avg"], r["y_avg"], ".", ms=1, label=f"dx={kw['dx'] * 1000:g} mm ({backend})")
    y = np.linspace(0, 0.1, 10)
    axs[0].plot(-1800 * V.G * (0.1 - y), y, "k-", lw=1, label="-rho g (h - y)")
    axs[0].set_xlabel("sigma_yy [Pa] (time average over the last 4 T1)"); axs[0].set_ylabel("y [m]"); axs[0].legend(fontsize=7)
    axs[0].set_title("Hydrostatic column: particle stresses")
    for backend, kw, r in results:
        axs[1].plot(r["history_t"] / r["T1"], r["history_base"], lw=0.6,
                    label=f"{backend} dx={kw['dx'] * 1000:g} mm w={kw.get('width', 0.2)}")
    axs[1].axhline(ref, color="k", ls="--", lw=1, label="-rho g h")
    axs[1].set_ylim(1.6 * ref, 0.3 * ref); axs[1].set_xlabel("t / T1 (T1 = 4h/c)"); axs[1].set_ylabel("fitted base sigma_yy [Pa]")
    axs[1].legend(fontsize=7); axs[1].set_title("Settling (PIC), per-frame fit")
    for backend in backends:
        pts = sorted({kw["dx"]: abs(r["error"]) for b, kw, r in results if b == backend}.items())
        d, e = zip(*pts)
        axs[2].plot(np.array(d) * 1000, 100 * np.array(e), "o-" if backend == "jax" else "x--", label=f"mpmlab {backend}")
    d = sorted(V.CBGEO_HYDROSTATIC)
    axs[2].plot(np.array(d) * 1000, [100 * abs(V.CBGEO_HYDROSTATIC[k] / ref - 1) for k in d], "ks:", label="CB-Geo")
    axs[2].set_xscale("log"); axs[2].set_yscale("log"); axs[2].set_xlabel("dx [mm]"); axs[2].set_ylabel("|base stress error| [%]")
    axs[2].legend(fontsize=7); axs[2].set_title("Convergence")
    fig.tight_layout(); fig.savefig(OUT / "hydrostatic_column.png", dpi=110); plt.close(fig)


# ------------------------------------------------------------------------------------------------
NOTES = """
## How each number is produced

* **Vibrating bar (1a/1c).** `vibrating_bar(cells=50, lateral="strip")`: fixed corotated, E = 100 Pa,
  rho = 1, **nu = 0** (so c = sqrt(E/rho) = 10 m/s), L = 25 m, v(x, 0) = v0 sin(pi x / 2L), v0 = 0.1 m/s,
  2x2 particles per cell, dt = 0.1 dx / c, fp64, 3 analytic periods. mpmlab has no 1D mode, so "1D" is a
  2D strip one cell thick, centred in a 4-cell lateral grid whose faces are 2-cell slip walls: every
  lateral node row has v_y = 0 except the middle one, on the strip's mid-plane, where v_y = 0 by
  symmetry (measured |v_y| <= 1e-16), so the motion is exactly 1D; the "2D free bar" is 4 cells high with free lateral surfaces
  (nu = 0: uniaxial stress, case 1c). Two extra rows use nu = 0.3, where the bar is genuinely 2D:
  the free bar contracts laterally (plane strain, c = sqrt(E/((1-nu^2) rho)), T1 = 9.539 s) and the
  confined strip carries lateral stress (c_p = sqrt((lambda+2mu)/rho), T1 = 8.619 s). The fixed end is a sticky wall (2 cells thick, the inner sticky
  node at x = 0). The period is 2x the least-squares slope of the zero-crossing times of the
  centre-of-mass velocity (linear interpolation between 200 frames per period).
* **Dam break (3a).** `ritter_dam_break(dx)`: water 1.0 x 0.1 m at the back wall of a 2.0 x 0.12 m tank,
  `newtonian_fluid` with c = 35 m/s, viscosity 0, rest density 1000, g = 9.8, slip walls (paper Sec.
  4.1.1), 2x2 particles per cell, fp32; `min_pressure` = 0 (no tension, the library default) unless the
  row says "Eq. 20 unclamped" (min_pressure = -1e30, the paper's EOS). The surface position at height y is where the water depth
  h(x) = sum_p V0_p J_p N(x - x_p) / dx' (quadratic B-spline, dx' = 2 dx) last reaches y; this is
  compared at every 0.01 s frame in the window and at heights y = 2dx, 3dx, ..., 0.4 H0 with Ritter
  x_R = L0 + (2 sqrt(g H0) - 3 sqrt(g y)) t. Error column: (A) max |x_sim - x_R|/(x_R - L0) over all
  heights (the note's metric, pass column); (B) the same over y <= 0.2 H0; (C) max |x_sim - x_R| /
  (2 sqrt(g H0) t) over all heights (relative to the wave length); see Findings 4. The depth-based front
  ignores the one-cell-thick tip by construction; the tip itself is plotted, not scored.
* **Hydrostatic column (3c).** `hydrostatic_column(dx)`: 0.2 x 0.1 m, rho = 1800, K = 1e6 Pa
  (`newtonian_fluid`, c = sqrt(K/rho) = 23.6 m/s, viscosity 0), 25 particles per cell, slip base and
  roller sides, fp64, gravity switched on at t = 0 (no geostatic initial stress). **Damping:** the PIC
  transfer (its dissipation damps the column's oscillation; no artificial viscosity, damping force or
  stress is added) for 40 fundamental periods T1 = 4h/c; then particle sigma_yy (the law's Cauchy
  `sigma` field) and y are time-averaged over the last 4 T1 (10 frames per T1; for the undamped linear
  column the modes have periods T1/(2n-1), so the mean over whole periods *is* the static state) and
  sigma_yy(y) is fitted by least squares through *all* particles, extrapolated to the base y = 0, and
  compared with -rho g h = -1765.8 Pa. "Residual |v|max" is the largest particle speed in the last frame
  relative to the undamped fundamental mode's velocity amplitude pi g h/(4c) = 0.033 m/s.
"""


FINDINGS = """
## Findings (numbers from the run of 2026-11-22; both backends, CPU)

**Verdict.** Vibrating bar: passes the 1 % bar on both backends with every transfer from 50 cells
along the bar. Hydrostatic column: passes -- more accurate than CB-Geo at all three dx on both
backends (+3.78 / +2.00 / +1.02 % vs CB-Geo's 4.85 / 2.33 / 1.08 %). Ritter dam break: **fails** the
recommended 5 % bar on both backends at every resolution, transfer and time step tried; item 4
explains the metric, the cause fixed (the fluid law carried tension; now `min_pressure`, default
p >= 0) and what remains.

1. **JAX and Warp agree** to 4+ significant digits in every case: bar periods identical to 1e-12
   (fp64); dam-break front positions within 0.6 mm (fp32, 4 mm); column base stress identical to
   0.01 Pa (fp64).
2. **Bar: first-order period error, from the fixed end.** +2.55 / +1.28 / +0.63 / +0.31 % at 13 / 25 /
   50 / 100 cells: the bar vibrates as if ~0.32 dx longer. The sticky wall is the cause: the same
   mode on a free-free bar of length 2L (no wall; its midpoint is a node by symmetry) has period
   errors of +0.054 % (25 cells) and +0.014 % (50 cells), i.e. second order (checked outside this
   script). With quadratic B-splines the first free node's basis function overlaps the clamped
   nodes, so the clamp is smeared over about a cell. The 1 % bar needs >= ~35 cells along the bar
   (fails at 13 and 25 cells, which the table shows). Transfers at 50 cells: MLS +0.36 % (best),
   TPIC +0.63 %, APIC +0.63 %, FLIP +0.65 %, PIC +0.70 % -- PIC keeps only 54 % of the amplitude
   after 3 periods (APIC 99.75 %). nu = 0.3 (genuinely 2D): plane-strain free bar +0.42 %, laterally
   confined strip +0.63 %.
3. **Column: the error sits in a boundary layer next to the base.** Fitting only the particles more
   than 2 dx above the base gives +0.20 / +0.08 / +0.02 %: the particle stresses in the two cells
   next to the base deviate (10 mm: bottom row -1362 Pa, next rows -2050 / -2000 Pa where -1748 /
   -1695 / -1625 Pa are exact), because the first free node's B-spline does not vanish on the wall,
   so the discrete equilibrium is not the linear profile there. The layer thickness scales with
   dx, hence first order, like CB-Geo (whose error has the opposite sign). The **roller sides** show
   the same kind of layer, larger: the first particle column next to each side wall carries only
   29 % of the hydrostatic sigma_yy, the next ones 131 %, 122 %, 93 %, 92 %, 105 % (10 mm; the
   "fans" in hydrostatic_column.png). They balance, so the fitted base value is barely affected.
   With roller sides the column is 1D: a 0.05 m wide slice gives +1.010 % vs +1.019 % at full width
   (2.5 mm). **Settling:** PIC's damping vanishes as dx shrinks: at 2.5 mm the per-frame fit still
   swings by +-1.5 % after 40 T1, and one-period means between 12.5 and 40 T1 scatter within
   0.88-1.17 %. So the 2.5 mm number carries about +-0.1 % of uncertainty: it beats CB-Geo's
   1.08 % only narrowly.
4. **Dam break (3a): what 5 % can mean, and what is met.** Three measures over heights
   y = 2dx ... 0.4 H0 (step dx) and every 0.01 s frame in t in [0.2, 0.45] s:
   (A) the note's |x_sim - x_R| / (x_R - L0); (B) the same for y <= 0.2 H0 only; (C) |x_sim - x_R| /
   (2 sqrt(g H0) t), the error relative to the Ritter wave length (dam site to tip).
   * **(A) is ill-posed at the top of its range.** x_R - L0 = (2 - 3 sqrt(y/H0)) sqrt(g H0) t: at
     y = 0.4 H0 that is 0.103 sqrt(g H0) t = 20 mm at t = 0.2 s, so 5 % is 1 mm = dx/4 at the paper's
     dx = 4 mm -- sub-cell accuracy of one surface point, at the height where the shallow-water
     (hydrostatic) assumption is worst (next to the dam site, t sqrt(g/H0) = 2-4.5 in the window). The
     errors at 0.4 H0 are 6-11 mm (a cell or two) yet read as 24-41 %.
   * **Cause 1, fixed: the EOS carried tension.** JAX-MPM Eq. 20, p = c^2 rho0 (1/J - 1), gives
     p = -25 to -33 kPa (J = 1.02-1.027) in the stretching front, 30x the largest hydrostatic pressure,
     and holds the front back. `newtonian_fluid` now has `min_pressure` (default 0: no tension, the
     standard weakly compressible practice; `-1e30` = Eq. 20 as written, a documented deviation from
     the paper). Unclamped vs clamped, APIC: 8 mm A 119 % -> 41 %, B 12 % -> 8 %; 4 mm A 84 % -> 32 %,
     tip at 0.45 s 1.52/1.64 m -> 1.66/1.71 m (Ritter 1.89 m; the one-cell tip is not scored).
   * **What remains (p >= 0, 4 mm, APIC):** heights 16-32 mm lag Ritter by 12-18 % of (x_R - L0) at
     t = 0.2 s, 10-13 % at 0.3 s and 6-8 % at 0.45 s: the error shrinks with time, as the early
     non-hydrostatic flow relaxes towards the shallow-water solution, but it is not inside 5 % in the
     window. Going 8 -> 4 mm does not reduce B (8 % -> 15 %): at 8 mm the scored heights are only 16, 24,
     32, 40 mm and 8 mm's extra numerical smoothing happens to sit closer to Ritter; this is not
     convergence. C is 3.1 % at 8 mm and 5.2 % at 4 mm.
   * *Boundaries* -- the floor and back wall are exactly y = 0 and x = 0 (node 1 of the 2-cell wall
     layer), the body starts on them, Ritter's x uses the same origin with the dam at L0 = 1 m; the
     back wall is not reached by the rarefaction before t = 1.01 s. The front measure is depth based
     (h(x) = sum V0 J N / dx'), so it does not depend on where exactly the floor plane is. `separate`
     instead of `slip` walls (8 mm) changes the numbers by several % either way (A 27 %, B 11 %, C 4.3 %,
     tip 1.76 m): the wall treatment at the 1-2-cell-thick front matters at this resolution.
   * *Transfer* (8 mm, p >= 0): APIC A/B/C = 41/8/3.1 %, TPIC 43/10/4.0 %, FLIP 0.99 74/12/4.6 %.
     *Time step*: the paper's dt = 1e-5 s gave the same picture as CFL 0.3 in the unclamped runs
     (4 mm: 97 % vs 84 %; earlier run, not repeated here).
   * *Measurement* -- the depth-based front and the literal "rightmost particle reaching y" agree
     within a few % (checked earlier, unclamped); the one-cell tip is excluded by construction.
   * **Refinement and a later window: the lag is the early, non-hydrostatic flow, not numerics.**
     (a) dx = 8 -> 4 -> 2 mm (APIC, Warp): the mid-height error does not shrink with dx; it settles --
     at t = 0.3 s, heights 20 / 24 / 28 mm: 8 mm -4 / -5 / -4 %, 4 mm -12 / -13 / -13 %, 2 mm
     -14 / -16 / -16 % -- so the simulation converges to a flow that differs from Ritter (the coarse
     grid's numerical smoothing sat closer to Ritter by accident) (a sound speed of 70
     instead of 35 m/s changes A by 3 points: compressibility is not the cause either).
     (b) In a 4 m tank (the 2 m tank's end wall is hit at t = 0.5 s), 4 mm, the error at every height
     decays like 1/t: heights 16-32 mm go from -10..-18 % (t = 0.2 s, t sqrt(g/H0) = 2) to -6..-8 %
     (0.5 s), -3..-5 % (0.7 s) and -1..-3 % (0.9 s); the tip moves at Ritter's 2 sqrt(g H0) (1.92 m/s
     measured over 0.5-0.9 s vs 1.98) with a constant lag of ~0.19 m = a start delay of ~0.1 s, the
     finite initial acceleration that Ritter's shallow-water solution (infinite at t = 0) leaves out.
     At 40 mm = 0.4 H0 (next to the dam-site depth 4/9 H0) the error stays 8-9 % (the ill-posed level,
     2 cells). The row "4 m tank, t in [0.6, 0.9] s" scores this window.
   **Verdict:** the note's bar (A <= 5 %) for t in [0.2, 0.45] s is not met, and a converged solver
   should not meet it: in that window (t sqrt(g/H0) = 2-4.5) the flow has not yet reached Ritter's
   long-time shallow-water state. B (y <= 0.2 H0): 8 % at 8 mm, 15 % at 4 mm, not met; C (relative to
   the wave length): 3.1 % at 8 mm, 5.2 % at 4 mm. Ritter is approached as t grows: within 5 % at every
   height up to 0.36 H0 for t >= 0.7 s (4 m tank, 0.1 s samples; the row's score over every 0.01 s frame
   of [0.6, 0.9] s: A 9.3 % (the 0.4 H0 level), B 6.5 %, C 3.8 %). Meeting the issue's bar as written needs either a
   later window (t sqrt(g/H0) >= 6) or a non-hydrostatic reference (e.g. a converged Navier-Stokes /
   VOF dam break) for [0.2, 0.45] s.
5. **Speed (CPU).** Warp's CPU backend is about 2x faster than JAX's here (current code): dam break
   4 mm 30 s vs 61 s, column 2.5 mm 149 s vs 305 s. Wall times come from 2 cores shared with other
   jobs and vary 2-3x between runs. "+dirty" in the code line above means colleagues' uncommitted
   Warp kernel edits were in the tree; the numbers matched the earlier runs to every printed digit.
"""


def write_markdown(rows, meta, path):
    def esc(s):
        return str(s).replace("|", "\\|")

    lines = ["# mpmlab validation against analytic references", "",
             f"Generated by `python benchmarks/validation.py` on {meta['date']} ({meta['machine']}; "
             f"{meta['cpus']} CPU cores shared, no GPU; Warp runs on its CPU device). "
             "Plots: `benchmarks/out/vibrating_bar.png`, `benchmarks/out/dam_break.png`, "
             "`benchmarks/out/hydrostatic_column.png`; "
             "raw numbers: `benchmarks/out/validation.json`. Rerun one case into the table with "
             "`--cases <case> --merge`; `--render` rewrites this file from the JSON.", "",
             "Wall time = stepper build (incl. JIT / kernel compile, cached Warp kernels load in ms) + rollout.", ""]
    if meta.get("runs"):
        lines += ["Code per case: " + "; ".join(f"{k}: {v['code']} ({v['date']})" for k, v in meta["runs"].items()) + ".",
                  ""]
    for case in dict.fromkeys(r["case"] for r in rows):
        lines += [f"## {case}", "",
                  *H.md_table(["variant", "backend", "transfer", "resolution", "measured", "reference", "error", "bar",
                               "pass", "wall [s]", "notes"],
                              ([esc(x) for x in (r["variant"], r["backend"], r["transfer"], r["resolution"],
                                                 r["measured"], r["reference"], r["error"], r["bar"],
                                                 "yes" if r["pass"] else "**no**", f"{r['wall_s']:.1f}", r["extra"])]
                               for r in rows if r["case"] == case))]
        lines.append("")
    lines.append(NOTES.strip("\n"))
    lines += ["", FINDINGS.strip("\n")]
    path.write_text("\n".join(lines) + "\n")


CASE_KEYS = {"1a/1c vibrating bar": "bar", "3a Ritter dam break": "dam", "3c hydrostatic column": "column"}
ORDER = ("bar", "dam", "column")


def _git_version():
    """HEAD commit of the checkout, with '+dirty' when tracked files differ from it."""
    import subprocess

    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=HERE, capture_output=True, text=True,
                              check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=HERE,
                               capture_output=True, text=True, check=True).stdout.strip()
        return head + ("+dirty" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def _key(row):
    return row.get("key") or CASE_KEYS.get(row["case"], row["case"])


def main(argv=None):
    global OUT
    ap = H.parser(__doc__, raw=True)
    ap.add_argument("--cases", default="bar,dam,column", help="comma list of bar, dam, column")
    H.add_backends(ap)
    H.add_quick(ap, "coarse smoke run (not the reported numbers)")
    ap.add_argument("--out", default=str(H.OUT))
    ap.add_argument("--md", default=None, help="Markdown table (default benchmarks/validation.md; quick: out/)")
    ap.add_argument("--merge", action="store_true",
                    help="keep the rows of cases not run now from the existing JSON (rerun one case)")
    ap.add_argument("--render", action="store_true", help="run nothing; rewrite the Markdown from the JSON")
    a = ap.parse_args(argv)
    OUT = Path(a.out)
    OUT.mkdir(parents=True, exist_ok=True)
    backends = a.backends.split(",")
    cases = [] if a.render else a.cases.split(",")
    stem = "validation_quick" if a.quick else "validation"
    jpath = OUT / f"{stem}.json"
    old = H.read_json(jpath) if (a.merge or a.render) else None
    rows, raw = [], {"bar": [], "dam": [], "column": []}
    t0 = time.time()
    runners = {"bar": run_bar, "dam": run_dam, "column": run_column}
    for key in ORDER:
        if key in cases:
            runners[key](backends, a.quick, rows, raw[key])
        elif old is not None:
            rows += [r for r in old["rows"] if _key(r) == key]
            raw[key] = old["raw"].get(key, [])
    meta = {"date": time.strftime("%Y-%m-%d"), "machine": platform.platform(), "cpus": os.cpu_count(),
            "python": sys.version.split()[0], "quick": a.quick, "total_s": time.time() - t0}
    code = _git_version()
    runs = dict(old["meta"].get("runs", {})) if old is not None else {}
    runs = {k: v for k, v in runs.items() if k in ORDER}
    runs.update({k: {"date": time.strftime("%Y-%m-%d %H:%M"), "code": code} for k in cases})
    if old is not None:
        meta = old["meta"] | ({"rerun": {"date": meta["date"], "cases": cases}} if cases else {})
    meta["runs"] = runs
    H.write_json(jpath, {"meta": meta, "rows": rows, "raw": raw}, default=float)
    md = Path(a.md) if a.md else (OUT / "validation_quick.md" if a.quick else HERE / "validation.md")
    write_markdown(rows, meta, md)
    log(f"wrote {md} and {jpath} in {time.time() - t0:.0f} s")
    return rows


OUT = H.OUT

if __name__ == "__main__":
    main()
