"""Granular collapses of JAX-MPM (Du & He 2025) Sec. 4.1.2 and 4.2.2-4.2.3 (issue 18 items 3 and 4):
convergence of the run-out in dx and particles per cell (2D plane strain), the aspect-ratio study
(d_n against the paper's 2.05 / 3.97 / 7.76 / 10.65), the friction-angle study and the aluminium-bar
deposit with its failure surface.

    python benchmarks/granular.py                       # every part at the default (affordable) sizes
    python benchmarks/granular.py --part convergence    # one part (convergence|aspect|friction|bars|aspect3d)
    python benchmarks/granular.py --full                # adds the finest grids (dx 1.25 mm in 2D, ...)
    python benchmarks/granular.py --report              # tables + plots from the saved results only
    python benchmarks/granular.py --only a=2            # only configurations whose key contains this

Every run is one ``scene=granular_collapse_2d`` (or ``granular_column_3d``) composed with overrides
(``mpmlab.config.compose`` / ``build_scene``), stepped on ``backend=warp`` (fp32 unless the
configuration says fp64) with FLIP, measured at every frame (0.01 s) by ``mpmlab.analysis.runout``'s
:class:`RunoutMonitor` with task.runout's default rule (front and height at the wall moved < 0.1 cell
over 0.1 s and kinetic energy < 1e-3 of its peak); the run ends at the first settled frame or at
``t_max``, whichever comes first (an unsettled run says so: ``settled`` false and the front's speed).

Resumable at two levels: every finished run is written to benchmarks/results/granular.json at once
(keyed by its configuration) and skipped on the next start; a run in progress writes a checkpoint
(the stepper state from ``stepper.to_numpy`` and the monitor's frames) to
benchmarks/results/granular_ckpt/<key>.npz every ``--checkpoint-s`` seconds of wall time (default 120)
and continues from it on the next start (:func:`restore_warp` assigns the saved arrays to a fresh
``stepper.init()``; the stress is recomputed from the law state). The tables go into
benchmarks/granular.md between the ``<!-- name -->`` markers, the plots to benchmarks/results/granular_*.png.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np
from omegaconf import OmegaConf

ROOT = Path(__file__).resolve().parent
sys.path.insert(0, str(ROOT.parent))
from mpmlab.config import CONF_DIR  # noqa: E402  (this checkout's, after the path above)

RESULTS = ROOT / "results" / "granular.json"
CKPT = ROOT / "results" / "granular_ckpt"
FINAL = ROOT / "results" / "granular_final"      # final particle positions + eps_p of selected runs (npz)
MD = ROOT / "granular.md"
PLOTS = ROOT / "results"

#: JAX-MPM Sec. 4.2.2: d_n at a = 0.5 / 1 / 2 / 3
PAPER_DN = {0.5: 2.05, 1.0: 3.97, 2.0: 7.76, 3.0: 10.65}
ASPECTS = (0.5, 1.0, 2.0, 3.0)
#: aluminium bars (Sec. 4.1.2): c_p = sqrt((K + 4G/3) / rho) = 20.7 m/s; dt = 0.01 dx is CFL 0.21
DT_PER_DX = 0.01
#: the PIC blend's time constant equal to flip_ratio 0.99 at dx 5 mm (dt = DT_PER_DX dx): -dt / ln 0.99
PIC_TIME_5MM = round(-DT_PER_DX * 0.005 / math.log(0.99), 9)
#: the granular scenes' PIC blend time since session 31 (conf/transfer/flip_pic_time.yaml)
SCENE_PIC_TIME = float(OmegaConf.load(CONF_DIR / "transfer" / "flip_pic_time.yaml").pic_time)
FRAME_S = 0.01                   # the monitor's frame spacing [s] (the stop rule's window is 0.1 s)
L0_COLUMN = 0.08                 # granular_column_3d's L0 (the paper does not give one)


# ------------------------------------------------------------------------------------------------
# configurations
# ------------------------------------------------------------------------------------------------
def cfg(**kw) -> dict:
    c = {"setup": "bui", "dim": 2, "dx": 0.005, "ppc": 4, "precision": "fp32", "phi": 19.8, "a": None}
    c.update(kw)
    if c["setup"] == "bui":
        c["a"] = None
    return c


def configs(part: str, full: bool, aspect_dx: float):
    if part == "convergence":
        dxs = (0.01, 0.005, 0.0025) + ((0.00125,) if full else ())
        for dx in dxs:                                   # dx at 4 particles per cell (2 x 2)
            yield cfg(setup="bui", dx=dx)
        for ppc in (1, 9, 16):                           # particles per cell at dx 5 mm
            yield cfg(setup="bui", ppc=ppc)
        yield cfg(setup="bui", dx=0.01, precision="fp64")  # fp32 vs fp64 once, at the smallest size
        for dx in (0.01, 0.005, 0.0025) + ((0.00125,) if full else ()):
            yield cfg(setup="column", a=2.0, dx=dx)
        for ppc in (1, 9, 16):
            yield cfg(setup="column", a=2.0, ppc=ppc)
    elif part == "aspect":
        for a in (0.5, 1.0, 2.0, 3.0):
            yield cfg(setup="column", a=a, dx=aspect_dx)
    elif part == "friction":
        for phi in (20.0, 25.0, 35.0, 40.0):
            yield cfg(setup="column", a=2.0, dx=0.005, phi=phi)
    elif part == "aspect3d":
        for a in (0.5, 1.0, 2.0, 3.0):
            yield cfg(setup="column3d", dim=3, a=a, dx=0.02, ppc=8)
        if full:
            for a in (0.5, 1.0, 2.0, 3.0):
                yield cfg(setup="column3d", dim=3, a=a, dx=0.01, ppc=8)
    elif part == "aspect3d_fine":                       # granular_column_3d's 'fine' size: 16 cells across L0
        for a in (0.5, 1.0, 2.0, 3.0):
            yield cfg(setup="column3d", dim=3, a=a, dx=0.005, ppc=8)
    elif part == "boundary":                            # sensitivity: the no-slip base one node layer thick
        for dx in (0.01, 0.005, 0.0025):
            yield cfg(setup="bui", dx=dx, walls=1)
    elif part == "flow_rule":                           # associated flow (psi = phi): is the dx dependence the
        for dx in (0.01, 0.005, 0.0025) + ((0.00125,) if full else ()):   # non-associated law's ill-posedness?
            yield cfg(setup="bui", dx=dx, psi=19.8)
    elif part == "transfer":                            # APIC instead of the paper's FLIP: the transfer's share
        for dx in (0.01, 0.005, 0.0025):                # of the dx dependence
            yield cfg(setup="bui", dx=dx, transfer="apic")
        for dx in (0.01, 0.005, 0.0025):                # pure FLIP (JAX-MPM Eq. 15; the scenes blend 1 % PIC)
            yield cfg(setup="bui", dx=dx, flip_ratio=1.0)
    elif part == "scale":                               # Sec. 4.1.2's column at 32 cells across L0 (as a = 0.5 at
        yield cfg(setup="bui", dx=0.00625)              # L0 0.08, dx 2.5 mm): d_n should not depend on L0
    elif part == "aspect_pure_flip":                   # Sec. 4.2.2 with the paper's Eq. 15 as written (pure FLIP)
        for dx in (0.005, 0.0025):
            for a in (0.5, 1.0, 2.0, 3.0):
                yield cfg(setup="column", a=a, dx=dx, flip_ratio=1.0)
        if full:                                        # 64 cells across L0 (a = 3 there: ~1 h here, checkpointed)
            for a in (0.5, 1.0, 2.0, 3.0):
                yield cfg(setup="column", a=a, dx=0.00125, flip_ratio=1.0)
    elif part == "cylinder3d":                         # Sec. 4.2.3: the 3D cylinder at its cpu size (16 cells across
        for phi in (20.0, 25.0, 35.0, 40.0):            # its base, 22k particles), the paper's four friction angles
            yield cfg(setup="cylinder3d", dim=3, dx=0.0125, ppc=8, phi=phi)
    elif part == "flip_dt":                             # is the run-out converged in dt? The 1 % PIC blend is
        for dts in (1.0, 0.5):                          # applied per step: its damping rate is 0.01 / dt
            more = {} if dts == 1.0 else {"dt_scale": dts}  # (dt_scale 1: the convergence / transfer parts' runs)
            yield cfg(setup="bui", dx=0.005, **more)
            yield cfg(setup="bui", dx=0.005, flip_ratio=1.0, **more)
            # the blend as a time constant (transfer.pic_time): the scenes' 0.99 at dt, exp(-dt / tau) at dt/2
            yield cfg(setup="bui", dx=0.005, pic_time=PIC_TIME_5MM, **more)
    elif part == "pic_time_dx":                         # the dx study with the blend's damping per second fixed
        for dx in (0.01, 0.005, 0.0025) + ((0.00125,) if full else ()):   # (transfer.pic_time; dt = 0.01 dx)
            yield cfg(setup="bui", dx=dx, pic_time=PIC_TIME_5MM)
    elif part == "pic_time_tau":                        # how little damping does the stop rule need? The blend's
        for tau in (0.01, 0.02, 0.05, 0.1, 0.2, 0.5):   # time constant from 10 to 500 ms (pure FLIP: part
            for dx in (0.005, 0.0025):                  # transfer; 4.97 ms: pic_time_dx), scene dx and half
                yield cfg(setup="bui", dx=dx, pic_time=tau)
        for tau in (0.2, 0.5):                          # the tall columns settle last: do they within t_max?
            for a in (0.5, 1.0, 2.0, 3.0):
                yield cfg(setup="column", a=a, dx=0.005, pic_time=tau)
    elif part == "default_dx":                          # the scenes' default since session 31 (transfer=
        for dx in (0.01, 0.005, 0.0025) + ((0.00125,) if full else ()):   # flip_pic_time, 0.2 s) in dx
            yield cfg(setup="bui", dx=dx, pic_time=SCENE_PIC_TIME)
            yield cfg(setup="column", a=2.0, dx=dx, pic_time=SCENE_PIC_TIME)
        for ppc in (1, 9, 16):                           # and in particles per cell at dx 5 mm
            yield cfg(setup="bui", ppc=ppc, pic_time=SCENE_PIC_TIME)
            yield cfg(setup="column", a=2.0, ppc=ppc, pic_time=SCENE_PIC_TIME)
    elif part == "base_friction":                       # the paper states the base only for Sec. 4.1.2 (no-slip):
        for mu in (0.2, 0.36, 0.5, 0.1):                 # a Coulomb base, mu 0.36 = tan 19.8 deg (the bars' own
            for a in (0.5, 1.0, 2.0, 3.0):              # friction), at the scenes' default transfer, dx 5 mm
                yield cfg(setup="column", a=a, dx=0.005, pic_time=SCENE_PIC_TIME, base_mu=mu)
        for mu in (0.2, 0.36, None):                     # and at dx 2.5 mm (32 cells across L0), beside the
            for a in (0.5, 1.0, 2.0, 3.0):              # scenes' no-slip base
                yield cfg(setup="column", a=a, dx=0.0025, pic_time=SCENE_PIC_TIME,
                          **({} if mu is None else {"base_mu": mu}))
    elif part == "bars":
        return                                          # uses the convergence part's Bui runs
    else:
        raise SystemExit(f"unknown part {part!r}")


def key(c) -> str:
    return "|".join(f"{k}={c[k]}" for k in sorted(c))


def t_max(c) -> float:
    """The longest simulated time a run may take (the stop rule ends it earlier once settled)."""
    if c["setup"] == "bui":
        return 1.5               # the paper runs 0.65 s
    if c["setup"] == "cylinder3d":
        return 1.5               # the paper runs 1 s
    return 3.0                   # the paper runs 2 s


def geometry(c) -> dict:
    """L0, H0 and the 2D domain of a configuration."""
    if c["setup"] == "bui":
        return {"L0": 0.2, "H0": 0.1, "hi": (0.6, 0.12)}
    if c["setup"] == "cylinder3d":               # granular_cylinder_3d: radius 0.1 m, height 0.17 m, axis at (0.5, 0.5)
        return {"L0": 0.1, "H0": 0.17, "hi": (1.0, 1.0, 0.25), "center": (0.5, 0.5), "reach": 0.5}
    L0 = L0_COLUMN
    H0 = c["a"] * L0
    if c["setup"] == "column3d":
        return {"L0": L0, "H0": H0, "hi": (1.0, 0.08, 0.5)}
    dn = PAPER_DN.get(float(c["a"]), 3.5 * c["a"])
    # long enough for 1.6x the paper's run-out (capped at the paper's 1.0 m); height: the column + 4 cm
    length = min(1.2, max(0.4, L0 * (1 + 1.6 * dn)))
    length = math.ceil(length / 0.04) * 0.04
    return {"L0": L0, "H0": H0, "hi": (round(length, 6), round(H0 + 0.04, 6))}


def overrides(c) -> list[str]:
    g = geometry(c)
    dt = DT_PER_DX * c["dx"] * c.get("dt_scale", 1.0)
    every = max(1, int(round(FRAME_S / dt)))
    body = "column"
    if c["setup"] == "column3d":
        ov = ["scene=granular_column_3d", f"scene.vars.aspect_ratio={c['a']}", f"scene.vars.L0={g['L0']}"]
    elif c["setup"] == "cylinder3d":
        ov, body = ["scene=granular_cylinder_3d"], "cylinder"
    else:
        ov = ["scene=granular_collapse_2d", f"scene.vars.L0={g['L0']}", f"scene.vars.H0={g['H0']}",
              f"scene.domain.hi=[{g['hi'][0]},{g['hi'][1]}]"]
    if c.get("walls") is not None:
        ov.append(f"scene.boundaries.walls.thickness={c['walls']}")
    if c.get("base_mu") is not None:                     # a Coulomb-friction base (JAX-MPM Eqs. 35-36) instead
        face = "y-" if c["dim"] == 2 else "z-"           # of the no-slip one: open wall, friction_walls there
        ov += [f"scene.boundaries.walls.faces.{face}=none",
               # (a new boundary merges as a whole dict: Hydra cannot add one key by key to the typed boundaries)
               f"+scene.boundaries={{base:{{kind:friction_walls,face:{face},along:x,mu:[{c['base_mu']}],thickness:2}}}}"]
    if c.get("psi") is not None:
        ov.append(f"material.params.dilation_angle={c['psi']}")
    ov += [f"scene.dx={c['dx']}", f"scene.dt={dt}", f"scene.frame_every={every}",
           f"scene.steps={int(round(t_max(c) / dt))}", f"scene.bodies.{body}.particles_per_cell={c['ppc']}",
           f"material.params.friction_angle={c['phi']}"]
    return ov


# ------------------------------------------------------------------------------------------------
# state save / restore (Warp)
# ------------------------------------------------------------------------------------------------
def restore_warp(stepper, d: dict):
    """A Warp state holding the arrays of ``stepper.to_numpy(state)`` (``d``): a fresh ``init()`` with
    x, v, C (affine transfers) and every law state field assigned (scene order, as to_numpy gives
    them), the stress recomputed from the law state, and the time set. The particles are re-sorted by
    cell at the next step (as after ``init()``), so a resumed run equals the uninterrupted one up to
    the summation order of P2G (round-off)."""
    import warp as wp

    T, dev = stepper.T, stepper.device
    s = stepper.init()
    s.x.assign(wp.array(np.asarray(d["x"], stepper.np_dtype), dtype=T.vec, device=dev))
    s.v.assign(wp.array(np.asarray(d["v"], stepper.np_dtype), dtype=T.vec, device=dev))
    if stepper.transfer.needs_affine:
        s.C.assign(wp.array(np.asarray(d["C"], stepper.np_dtype), dtype=T.mat, device=dev))
    for i, (g, st, k) in enumerate(zip(stepper.groups, s.law, stepper.k_laws)):
        for name, arr in st.items():
            idx = np.asarray(d[name + "_particles"])
            sel = (idx >= g.start) & (idx < g.stop)
            vals = np.asarray(d[name])[sel][np.argsort(idx[sel])]
            arr.assign(wp.array(np.asarray(vals, stepper.np_dtype), dtype=arr.dtype, device=dev))
        wp.launch(k.stress, dim=g.count, inputs=[*stepper._law_args(i, st), g.start, s.tau], device=dev)
    s.t = float(d["t"])
    return s


_MONITOR_LISTS = ("times", "fronts", "heights", "kinetic", "left_out")


def save_checkpoint(path: Path, npstate: dict, step: int, monitor, wall_s: float) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    arrays = {k: np.asarray(v) for k, v in npstate.items() if k not in ("time", "step")}
    arrays.update({f"mon_{k}": np.asarray(getattr(monitor, k), dtype=np.float64) for k in _MONITOR_LISTS})
    arrays["mon_settled_index"] = np.asarray(-1 if monitor.settled_index is None else monitor.settled_index)
    arrays["step"] = np.asarray(step)
    arrays["wall_s"] = np.asarray(wall_s)
    tmp = path.with_name(path.stem + ".tmp.npz")
    np.savez_compressed(tmp, **arrays)
    os.replace(tmp, path)


def load_checkpoint(path: Path, monitor) -> tuple[dict, int, float]:
    z = dict(np.load(path))
    for k in _MONITOR_LISTS:
        vals = z.pop(f"mon_{k}").tolist()
        setattr(monitor, k, [int(v) for v in vals] if k == "left_out" else vals)
    si = int(z.pop("mon_settled_index"))
    monitor.settled_index = None if si < 0 else si
    monitor.last_x = np.asarray(z["x"], dtype=np.float64)
    step, wall = int(z.pop("step")), float(z.pop("wall_s"))
    z["t"] = float(z["t"])
    return z, step, wall


# ------------------------------------------------------------------------------------------------
# one run
# ------------------------------------------------------------------------------------------------
def build(c):
    from mpmlab.analysis.runout import RunoutGeometry, RunoutMonitor
    from mpmlab.config import build_scene, compose
    from mpmlab.simulator import build_stepper

    conf = compose(overrides(c))
    scene = build_scene(conf)
    from mpmlab.transfers import make_transfer

    if c.get("pic_time") is not None:
        tr = make_transfer("flip", pic_time=c["pic_time"])
    elif c.get("flip_ratio") is not None:
        tr = make_transfer("flip", flip_ratio=c["flip_ratio"])
    else:
        tr = c.get("transfer") or "flip"
    stepper = build_stepper(scene, "warp", tr, c["precision"])
    dim = scene.dim
    center = geometry(c).get("center")
    geo = (RunoutGeometry(dim=dim, up=dim - 1, center=center, base=0.0) if center is not None else
           RunoutGeometry(dim=dim, up=dim - 1, axis=0, wall=0.0, direction=1, base=0.0))
    P = scene.particles()
    size = np.asarray(P.volume, dtype=np.float64) ** (1.0 / dim)
    mon = RunoutMonitor(geo, float(scene.dx), mass=np.asarray(P.mass, dtype=np.float64), particle_size=size)
    return scene, stepper, mon


def run_one(c, checkpoint_s: float = 120.0, deadline: float | None = None, log=print) -> dict | None:
    """Run configuration ``c`` to settling (or t_max); None when ``deadline`` (epoch seconds) came first
    (the checkpoint holds the progress)."""
    from mpmlab.analysis.runout import summarize

    g = geometry(c)
    scene, stepper, mon = build(c)
    dt = stepper.dt
    every = max(1, int(round(FRAME_S / dt)))
    total = int(round(t_max(c) / dt))
    ck = CKPT / (hashlib.sha1(key(c).encode()).hexdigest()[:16] + ".npz")
    wall0 = 0.0
    if ck.exists():
        d, step, wall0 = load_checkpoint(ck, mon)
        state = restore_warp(stepper, d)
        log(f"  resumed from {ck.name} at step {step} (t = {step * dt:.3f} s, {wall0:.0f} s of wall time before)")
    else:
        state, step = stepper.init(), 0
        npst = stepper.to_numpy(state)
        mon.update(0.0, npst["x"], npst["v"])
    t_start = time.perf_counter()
    last_ck = t_start
    status = "ok"
    while step < total and not mon.settled:
        n = min(every, total - step)
        state = stepper._advance(state, n)
        step += n
        if stepper._is_bad(state):
            status = "diverged"
            break
        npst = stepper.to_numpy(state)
        mon.update(step * dt, npst["x"], npst["v"])
        now = time.perf_counter()
        if now - last_ck > checkpoint_s:
            save_checkpoint(ck, npst, step, mon, wall0 + now - t_start)
            last_ck = now
            log(f"  t = {step * dt:.2f} s, front {mon.fronts[-1]:.4f} m, checkpoint ({wall0 + now - t_start:.0f} s)")
        if deadline is not None and time.time() > deadline:
            save_checkpoint(ck, npst, step, mon, wall0 + now - t_start)
            log(f"  deadline: stopped at t = {step * dt:.3f} s, checkpoint {ck.name}")
            return None
    npst = stepper.to_numpy(state)
    r = summarize(mon, g["L0"], g["H0"])
    r.update(status=status, steps=step, dt=dt, t_end=step * dt, particles=int(scene.particles().count),
             cells=list(scene.cells), wall_s=wall0 + time.perf_counter() - t_start, domain_hi=list(g["hi"]),
             series={"t": list(mon.times), "front": list(mon.fronts), "height": list(mon.heights),
                     "kinetic": list(mon.kinetic)})
    # the front at the domain's far wall: the run-out is cut there
    r["front_at_domain_end"] = bool(r["L_f"] > g.get("reach", g["hi"][0]) - 2.5 * c["dx"])
    r["deposit_angle_deg"] = deposit_angle(r)
    if c["setup"] == "bui" or c.get("save_final"):
        FINAL.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(FINAL / (hashlib.sha1(key(c).encode()).hexdigest()[:16] + ".npz"),
                            x=npst["x"], eps_p=npst.get("eps_p", np.zeros(len(npst["x"]))),
                            x0=np.asarray(scene.particles().x))
    if ck.exists():
        ck.unlink()
    return r


def deposit_angle(r: dict) -> float | None:
    """Mean slope of the deposit's free surface [deg]: the least-squares line through the profile's bin
    tops whose height lies between 10 % and 90 % of the height at the wall."""
    p = r.get("profile") or {}
    d, h = np.asarray(p.get("distance", [])), np.asarray(p.get("height", []))
    hw = r.get("H_wall") or 0.0
    sel = (h > 0.1 * hw) & (h < 0.9 * hw)
    if sel.sum() < 3:
        return None
    slope = np.polyfit(d[sel], h[sel], 1)[0]
    return float(math.degrees(math.atan(-slope)))


# ------------------------------------------------------------------------------------------------
# analysis: observed order, Richardson extrapolation, scaling exponents
# ------------------------------------------------------------------------------------------------
def richardson(h: list[float], f: list[float]) -> dict:
    """Observed order and extrapolated value from the three finest of (h, f) (any constant ratio of h;
    the ratio of the finest pair is used). ``order`` None when the differences change sign
    (oscillating, not in the asymptotic range) or vanish."""
    pts = sorted(zip(h, f), key=lambda t: -t[0])
    out = {"order": None, "extrapolated": None, "ratio": None, "error_finest": None}
    if len(pts) < 3:
        if len(pts) == 2:
            out["change_last"] = pts[1][1] - pts[0][1]
        return out
    (h1, f1), (h2, f2), (h3, f3) = pts[-3:]
    r = h2 / h3
    out["ratio"] = r
    e12, e23 = f1 - f2, f2 - f3
    out["change_last"] = f3 - f2
    if e12 == 0 or e23 == 0 or (e12 > 0) != (e23 > 0):
        return out
    p = math.log(e12 / e23) / math.log(r)
    out["order"] = p
    if p > 0:
        fe = f3 + (f3 - f2) / (r ** p - 1)
        out["extrapolated"] = fe
        out["error_finest"] = (f3 - fe) / fe if fe else None
    return out


def power_fit(a: list[float], y: list[float]) -> float | None:
    """Exponent of y ~ a^n from a least-squares line in log-log (None with fewer than two positive points)."""
    pts = [(x, v) for x, v in zip(a, y) if x and v and x > 0 and v > 0]
    if len(pts) < 2:
        return None
    la, ly = np.log([p[0] for p in pts]), np.log([p[1] for p in pts])
    return float(np.polyfit(la, ly, 1)[0])


# ------------------------------------------------------------------------------------------------
# report
# ------------------------------------------------------------------------------------------------
def load() -> dict:
    return json.loads(RESULTS.read_text()) if RESULTS.exists() else {}


def save(res: dict) -> None:
    """Write ``res`` merged over what the file holds now: another invocation (another part) may have added
    runs since this one loaded it, and those are kept; ``res`` is updated with them too."""
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    for k, v in load().items():
        res.setdefault(k, v)
    tmp = RESULTS.with_suffix(f".{os.getpid()}.tmp")
    tmp.write_text(json.dumps(res, indent=1, default=float))
    os.replace(tmp, RESULTS)


def fmt(x, f="{:.4g}"):
    return "--" if x is None else f.format(x)


#: optional configuration keys (absent from the default runs' keys): a row matches only if they agree
VARIANTS = ("walls", "psi", "transfer", "flip_ratio", "dt_scale", "pic_time", "base_mu")


def _rows(res, **match):
    out = []
    for r in res.values():
        c = r["config"]
        if all(c.get(k) == v for k, v in match.items()) and all(c.get(k) == match.get(k) for k in VARIANTS):
            out.append(r)
    return out


def t_paper(c) -> float:
    """The paper's simulated time: 0.65 s (Sec. 4.1.2), 2 s (Sec. 4.2.2)."""
    return 0.65 if c["setup"] == "bui" else 2.0


def at_time(r, t: float, what: str = "front"):
    """A per-frame series (front, height) at the last frame at or before time t (None past the run's end)."""
    s = r.get("series") or {}
    ts = np.asarray(s.get("t", []))
    if not ts.size or ts[-1] < t - 1e-9:
        return float(s[what][-1]) if ts.size and r.get("settled") else None   # settled earlier: its final value
    return float(np.asarray(s[what])[np.nonzero(ts <= t + 1e-9)[0][-1]])


def _run_cols(r) -> str:
    c = r["config"]
    settled = f"yes, {r['settled_time']:.2f} s" if r["settled"] else f"NO (front {fmt(r['front_speed_cells_per_s'], '{:.2g}')} cells/s)"
    flags = []
    if r.get("front_at_domain_end"):
        flags.append("front at domain end")
    if r.get("status") != "ok":
        flags.append(r.get("status"))
    if r.get("particles_left_out"):
        flags.append(f"{r['particles_left_out']} particles left out")
    return (f"{c['dx'] * 1e3:g} | {c['ppc']} | {c['precision']} | {r['particles']} | {fmt(r['L_f'])} | "
            f"{fmt(r['d_n'], '{:.3f}')} | {fmt(at_time(r, t_paper(c)))} | {fmt(r['H_wall'])} | {fmt(r['H_wall_over_H0'], '{:.3f}')} | "
            f"{settled} | {r['t_end']:.2f} | {r['wall_s'] / 60:.1f} | {'; '.join(flags) or '--'}")


_HEAD = ("dx [mm] | ppc | precision | particles | L_f [m] | d_n | L_f at the paper's t_end [m] | H_wall [m] | H_wall/H0 | settled | "
         "t_end [s] | wall [min] | notes")


def table_convergence(res) -> str:
    lines = []
    for setup, a, title in (("bui", None, "Sec. 4.1.2 column (L0 0.2 m, H0 0.1 m, a = 0.5)"),
                            ("column", 2.0, f"aspect-ratio column a = 2 (L0 {L0_COLUMN} m, H0 {2 * L0_COLUMN:g} m)")):
        rows = [r for r in _rows(res, setup=setup, dim=2, phi=19.8) if setup == "bui" or r["config"]["a"] == a]
        if not rows:
            continue
        lines += [f"**{title}**", "", "| " + _HEAD + " |", "|" + "---|" * (_HEAD.count("|") + 1)]
        for r in sorted(rows, key=lambda r: (r["config"]["precision"], -r["config"]["dx"], r["config"]["ppc"])):
            lines.append("| " + _run_cols(r) + " |")
        lines.append("")
        dxr = sorted([r for r in rows if r["config"]["ppc"] == 4 and r["config"]["precision"] == "fp32"
                      and r["config"]["dx"] in (0.01, 0.005, 0.0025, 0.00125)],
                     key=lambda r: -r["config"]["dx"])
        tp = 0.65 if setup == "bui" else 2.0
        for q, name in (("L_f", "run-out L_f (settled)"), ("H_wall", "height at the wall (settled)"),
                        ("L_tp", f"run-out at t = {tp:g} s (the paper's end time)")):
            vals = [at_time(r, tp) if q == "L_tp" else r[q] for r in dxr]
            if any(v is None for v in vals):
                continue
            rr = richardson([r["config"]["dx"] for r in dxr], vals)
            dxs = ", ".join(f"{r['config']['dx'] * 1e3:g}" for r in dxr)
            lines.append(f"- {name} in dx ({dxs} mm, 4 ppc): observed order {fmt(rr['order'], '{:.2f}')}, "
                         f"Richardson value {fmt(rr['extrapolated'])} m, finest grid off it by "
                         f"{fmt(None if rr['error_finest'] is None else 100 * rr['error_finest'], '{:.1f}')} %, "
                         f"last change {fmt(rr.get('change_last'), '{:+.4f}')} m")
        pr = sorted([r for r in rows if r["config"]["dx"] == 0.005 and r["config"]["precision"] == "fp32"],
                    key=lambda r: r["config"]["ppc"])
        if len(pr) > 1:
            lf = [r["L_f"] for r in pr]
            lines.append(f"- particles per cell at dx 5 mm ({', '.join(str(r['config']['ppc']) for r in pr)}): "
                         f"L_f {', '.join(fmt(v) for v in lf)} m (spread {100 * (max(lf) - min(lf)) / np.mean(lf):.1f} %); "
                         f"H_wall {', '.join(fmt(r['H_wall']) for r in pr)} m")
        p32 = [r for r in rows if r["config"]["dx"] == 0.01 and r["config"]["ppc"] == 4]
        if len(p32) == 2:
            a32 = [r for r in p32 if r["config"]["precision"] == "fp32"][0]
            a64 = [r for r in p32 if r["config"]["precision"] == "fp64"][0]
            lines.append(f"- fp32 vs fp64 at dx 10 mm: L_f {fmt(a32['L_f'])} / {fmt(a64['L_f'])} m, "
                         f"H_wall {fmt(a32['H_wall'])} / {fmt(a64['H_wall'])} m")
        lines.append("")
    return "\n".join(lines)


def table_boundary(res) -> str:
    lines = ["| dx [mm] | L_f, walls 2 cells (scene) [m] | L_f, walls 1 cell [m] | L_f at 0.65 s, 2 cells / 1 cell [m] | "
             "H_wall 2 / 1 [m] |", "|---|---|---|---|---|"]
    for r1 in sorted(_rows(res, setup="bui", ppc=4, precision="fp32", walls=1), key=lambda r: -r["config"]["dx"]):
        dx = r1["config"]["dx"]
        r2 = [r for r in _rows(res, setup="bui", ppc=4, precision="fp32", dx=dx, phi=19.8)]
        r2 = r2[0] if r2 else None
        l1 = fmt(r1["L_f"]) if r1["status"] == "ok" else f"{r1['status']} at t = {r1['t_end']:.2f} s (guard)"
        lines.append(f"| {dx * 1e3:g} | {fmt(r2 and r2['L_f'])} | {l1} | {fmt(r2 and at_time(r2, 0.65))} / "
                     f"{fmt(at_time(r1, 0.65))} | {fmt(r2 and r2['H_wall'])} / {fmt(r1['H_wall'] if r1['status'] == 'ok' else None)} |")
    return "\n".join(lines)


def table_aspect(res, **variant) -> str:
    """Sec. 4.2.2 in 2D: d_n per a and dx beside the paper's, and the scaling exponents (``variant``: e.g.
    ``flip_ratio=1.0`` for the pure-FLIP runs)."""
    rows = sorted([r for r in _rows(res, setup="column", dim=2, phi=19.8, ppc=4, precision="fp32", **variant)],
                  key=lambda r: (r["config"]["dx"], r["config"]["a"]))
    by_dx: dict = {}
    for r in rows:
        by_dx.setdefault(r["config"]["dx"], []).append(r)
    lines = ["| a | dx [mm] | cells across L0 | L_f [m] | d_n (mpmlab, settled) | d_n at t = 2 s | d_n (paper) | "
             "mpmlab / paper | H_wall/H0 | settled | wall [min] | notes |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    fits = []
    for dx, rs in sorted(by_dx.items(), reverse=True):
        for r in sorted(rs, key=lambda r: r["config"]["a"]):
            a = r["config"]["a"]
            p = PAPER_DN.get(a)
            flags = "front at domain end" if r.get("front_at_domain_end") else "--"
            st = f"yes, {r['settled_time']:.2f} s" if r["settled"] else "NO"
            lines.append(f"| {a:g} | {dx * 1e3:g} | {L0_COLUMN / dx:.0f} | {fmt(r['L_f'])} | {fmt(r['d_n'], '{:.3f}')} | "
                         f"{fmt(None if at_time(r, 2.0) is None else (at_time(r, 2.0) - r['L0']) / r['L0'], '{:.3f}')} | "
                         f"{fmt(p, '{:.2f}')} | {fmt(None if p is None else r['d_n'] / p, '{:.2f}')} | "
                         f"{fmt(r['H_wall_over_H0'], '{:.3f}')} | {st} | {r['wall_s'] / 60:.1f} | {flags} |")
        d = {r["config"]["a"]: r["d_n"] for r in rs}
        lo = power_fit([a for a in (0.5, 1.0) if a in d], [d[a] for a in (0.5, 1.0) if a in d])
        hi = power_fit([a for a in (2.0, 3.0) if a in d], [d[a] for a in (2.0, 3.0) if a in d])
        fits.append(f"- dx {dx * 1e3:g} mm: exponent of d_n ~ a^n for a = 0.5-1: {fmt(lo, '{:.2f}')} (paper's "
                    f"values {power_fit([0.5, 1.0], [2.05, 3.97]):.2f}, its claim 1); for a = 2-3: {fmt(hi, '{:.2f}')} "
                    f"(paper's values {power_fit([2.0, 3.0], [7.76, 10.65]):.2f}, its claim 0.7)")
    return "\n".join(lines + [""] + fits)


def table_friction(res) -> str:
    rows = sorted([r for r in _rows(res, setup="column", dim=2, a=2.0, dx=0.005, ppc=4, precision="fp32")],
                  key=lambda r: r["config"]["phi"])
    lines = ["| phi [deg] | L_f [m] | d_n | H_wall/H0 | deposit slope [deg] | settled | wall [min] |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        st = f"yes, {r['settled_time']:.2f} s" if r["settled"] else "NO"
        lines.append(f"| {r['config']['phi']:g} | {fmt(r['L_f'])} | {fmt(r['d_n'], '{:.3f}')} | "
                     f"{fmt(r['H_wall_over_H0'], '{:.3f}')} | {fmt(r.get('deposit_angle_deg'), '{:.1f}')} | {st} | "
                     f"{r['wall_s'] / 60:.1f} |")
    return "\n".join(lines)


def front_at_thickness(profile: dict, h: float) -> float | None:
    """The farthest distance from the wall where the deposit profile is at least ``h`` thick (linear
    between the profile's bins): a front that does not count a toe thinner than h."""
    d, H = np.asarray(profile["distance"], float), np.asarray(profile["height"], float)
    idx = np.nonzero(H >= h)[0]
    if not idx.size:
        return None
    i = idx[-1]
    if i + 1 < len(H) and H[i] != H[i + 1]:
        return float(d[i] + (d[i + 1] - d[i]) * (H[i] - h) / (H[i] - H[i + 1]))
    return float(d[i])


THICKNESS = (0.01, 0.02, 0.03)   # [m] fronts of the deposit at these thicknesses (table_flow_rule)


#: the Sec. 4.1.2 column's model variants (parts ``convergence``, ``flow_rule``, ``transfer``)
SENSITIVITY = (("the scenes until session 31: psi = 0, FLIP with 1 % PIC per step", {}), ("psi = phi (associated flow)", {"psi": 19.8}),
               ("APIC", {"transfer": "apic"}), ("pure FLIP (JAX-MPM Eq. 15 as written)", {"flip_ratio": 1.0}),
               ("FLIP, PIC blend time 4.97 ms (transfer.pic_time: the damping per second of the scene's blend at 5 mm, "
                "at every dx)", {"pic_time": PIC_TIME_5MM}),
               (f"the scenes since session 31: FLIP, PIC blend time {SCENE_PIC_TIME:g} s (transfer=flip_pic_time)",
                {"pic_time": SCENE_PIC_TIME}))


def table_sensitivity(res) -> str:
    """The Sec. 4.1.2 column against dx for each model variant of SENSITIVITY: L_f, the fronts where the
    deposit is THICKNESS thick, H_wall; under the table, the observed order and Richardson value of each."""
    head = ("| variant | dx [mm] | L_f [m] | d_n | " + " | ".join(f"front at {h * 100:g} cm thick [m]" for h in THICKNESS)
            + " | H_wall [m] | settled |")
    lines = [head, "|---|---|---|---|" + "---|" * len(THICKNESS) + "---|---|"]
    notes = []
    for name, var in SENSITIVITY:
        rows = sorted([r for r in _rows(res, setup="bui", dim=2, phi=19.8, ppc=4, precision="fp32", **var)
                       if r["config"]["dx"] in (0.01, 0.005, 0.0025, 0.00125)], key=lambda r: -r["config"]["dx"])
        for r in rows:
            st = f"yes, {r['settled_time']:.2f} s" if r["settled"] else "NO"
            fr = [front_at_thickness(r["profile"], h) for h in THICKNESS]
            lines.append(f"| {name} | {r['config']['dx'] * 1e3:g} | {fmt(r['L_f'])} | {fmt(r['d_n'], '{:.3f}')} | " +
                         " | ".join(fmt(v) for v in fr) + f" | {fmt(r['H_wall'])} | {st} |")
        if len(rows) >= 3:
            dxs = [r["config"]["dx"] for r in rows]
            parts = []
            for q, vals in [("L_f", [r["L_f"] for r in rows])] + [
                    (f"{h * 100:g} cm front", [front_at_thickness(r["profile"], h) for r in rows]) for h in THICKNESS]:
                if any(v is None for v in vals):
                    continue
                rr = richardson(dxs, vals)
                parts.append(f"{q} order {fmt(rr['order'], '{:.2f}')} (Richardson {fmt(rr['extrapolated'])} m)")
            notes.append(f"- {name}: " + "; ".join(parts))
    return "\n".join(lines + [""] + notes)


def table_default_dx(res) -> str:
    """The a = 2 column (L0 0.08 m) against dx with the scenes' default since session 31 (pic_time 0.2 s)
    and with pure FLIP: L_f, d_n, H_wall / H0; under it the observed order and Richardson value of L_f."""
    lines = ["| transfer | dx [mm] | cells across L0 | L_f [m] | d_n | H_wall/H0 | settled |", "|---|---|---|---|---|---|---|"]
    notes = []
    for name, var in ((f"pic_time {SCENE_PIC_TIME:g} s (the scenes)", {"pic_time": SCENE_PIC_TIME}),
                      ("pure FLIP", {"flip_ratio": 1.0})):
        rows = sorted(_rows(res, setup="column", a=2.0, dim=2, phi=19.8, ppc=4, precision="fp32", **var),
                      key=lambda r: -r["config"]["dx"])
        for r in rows:
            st = f"yes, {r['settled_time']:.2f} s" if r["settled"] else "NO"
            lines.append(f"| {name} | {r['config']['dx'] * 1e3:g} | {L0_COLUMN / r['config']['dx']:.0f} | {fmt(r['L_f'])} | "
                         f"{fmt(r['d_n'], '{:.3f}')} | {fmt(r['H_wall_over_H0'], '{:.3f}')} | {st} |")
        if len(rows) >= 3:
            rr = richardson([r["config"]["dx"] for r in rows], [r["L_f"] for r in rows])
            notes.append(f"- {name}: L_f order {fmt(rr['order'], '{:.2f}')} (Richardson {fmt(rr['extrapolated'])} m)")
    for label, sel in (("Sec. 4.1.2 column", {"setup": "bui"}), ("a = 2 column", {"setup": "column", "a": 2.0})):
        got = []
        for ppc in (1, 4, 9, 16):
            rows = _rows(res, dim=2, dx=0.005, phi=19.8, ppc=ppc, precision="fp32", pic_time=SCENE_PIC_TIME, **sel)
            if rows:
                got.append((ppc, rows[0]))
        if len(got) > 1:
            Ls = [r["L_f"] for _, r in got]
            L4 = [r["L_f"] for p_, r in got if p_ >= 4]
            notes.append(f"- {label}, pic_time {SCENE_PIC_TIME:g} s, particles per cell at dx 5 mm ({', '.join(str(p) for p, _ in got)}): "
                         f"L_f {', '.join(fmt(v) for v in Ls)} m (spread from 4 up {100 * (max(L4) - min(L4)) / max(L4):.1f} %); "
                         f"H_wall {', '.join(fmt(r['H_wall']) for _, r in got)} m")
    return "\n".join(lines + [""] + notes)


def table_flip_dt(res) -> str:
    """The Sec. 4.1.2 column at dx 5 mm, at dt and dt/2, with the scenes' FLIP (1 % PIC per step) and with
    pure FLIP: the run-out's change with dt alone."""
    lines = ["| transfer | dt [s] | L_f [m] | largest front [m] | front at 0.65 s [m] | H_wall [m] | kinetic energy at the end / peak | settled |",
             "|---|---|---|---|---|---|---|---|"]
    notes = []
    for name, var in (("FLIP + 1 % PIC per step (the scenes)", {}), ("pure FLIP (JAX-MPM Eq. 15)", {"flip_ratio": 1.0}),
                      (f"FLIP, PIC blend time {PIC_TIME_5MM * 1e3:.3g} ms (transfer.pic_time)", {"pic_time": PIC_TIME_5MM})):
        got = {}
        for dts in (None, 0.5):
            rows = _rows(res, setup="bui", dim=2, dx=0.005, phi=19.8, ppc=4, precision="fp32", dt_scale=dts, **var)
            if not rows:
                continue
            r = rows[0]
            ser = r["series"]
            ke = np.asarray(ser["kinetic"], float)
            t = np.asarray(ser["t"], float)
            f065 = float(np.interp(0.65, t, ser["front"]))
            st = f"yes, {r['settled_time']:.2f} s" if r["settled"] else "NO"
            lines.append(f"| {name} | {r['dt']:.3g} | {fmt(r['L_f'])} | {fmt(max(ser['front']))} | {fmt(f065)} | "
                         f"{fmt(r['H_wall'])} | {ke[-1] / ke.max():.1e} | {st} |")
            got[dts] = r
        if len(got) == 2:
            a, b = got[None], got[0.5]
            notes.append(f"- {name}: halving dt changes L_f by {100 * (b['L_f'] / a['L_f'] - 1):+.1f} % and the "
                         f"largest front by {100 * (max(b['series']['front']) / max(a['series']['front']) - 1):+.1f} %")
    return "\n".join(lines + [""] + notes)


def table_pic_time_tau(res) -> str:
    """The PIC blend's time constant from 10 ms to 0.5 s against pure FLIP and the per-step 0.99: the
    Sec. 4.1.2 column at dx 5 and 2.5 mm, the Sec. 4.2.2 columns at 5 mm; does each settle, and how far
    is its run-out from pure FLIP's (JAX-MPM Eq. 15)?"""
    taus = (PIC_TIME_5MM, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5)
    lines = ["| column | dx [mm] | transfer | L_f [m] | vs pure FLIP | settled | H_wall [m] |", "|---|---|---|---|---|---|---|"]
    setups = [("Sec. 4.1.2 (a = 0.5, L0 0.2 m)", {"setup": "bui"}, (0.005, 0.0025))]
    setups += [(f"Sec. 4.2.2, a = {a:g}", {"setup": "column", "a": a}, (0.005,)) for a in (0.5, 1.0, 2.0, 3.0)]
    for name, sel, dxs in setups:
        for dx in dxs:
            base = dict(dim=2, dx=dx, phi=19.8, ppc=4, precision="fp32", **sel)
            flip = _rows(res, flip_ratio=1.0, **base)
            ref = flip[0]["L_f"] if flip else None
            variants = [("FLIP + 1 % PIC per step", {})] + [
                (f"pic_time {t * 1e3:.3g} ms", {"pic_time": t}) for t in taus] + [("pure FLIP", {"flip_ratio": 1.0})]
            for label, var in variants:
                rows = _rows(res, **base, **var)
                if not rows:
                    continue
                r = rows[0]
                rel = f"{100 * (r['L_f'] / ref - 1):+.1f} %" if ref and var.get("flip_ratio") != 1.0 else "--"
                st = f"yes, {r['settled_time']:.2f} s" if r["settled"] else f"NO (t_max {r['t_end']:.1f} s)"
                lines.append(f"| {name} | {dx * 1e3:g} | {label} | {fmt(r['L_f'])} | {rel} | {st} | {fmt(r['H_wall'])} |")
    return "\n".join(lines)


def table_base_friction(res) -> str:
    """Sec. 4.2.2's columns on a Coulomb base (friction_walls, mu) against the no-slip base, at the scenes'
    default transfer (pic_time 0.2 s): d_n per aspect ratio, its ratio to the paper's and the exponents."""
    lines = ["| base | dx [mm] | " + " | ".join(f"d_n, a = {a:g} (paper {PAPER_DN[a]:g})" for a in ASPECTS)
             + " | exponent a = 0.5-1 (paper 0.95, claim 1) | exponent a = 2-3 (paper 0.78, claim 0.7) | settled |",
             "|---|---|" + "---|" * len(ASPECTS) + "---|---|---|"]
    for mu in (None, 0.5, 0.36, 0.2, 0.1):
        for dx in (0.005, 0.0025):
            got = {}
            for a in ASPECTS:
                rows = _rows(res, setup="column", a=a, dim=2, dx=dx, phi=19.8, ppc=4, precision="fp32",
                             pic_time=SCENE_PIC_TIME, base_mu=mu)
                if rows:
                    got[a] = rows[0]
            if not got:
                continue
            cells = []
            for a in ASPECTS:
                r = got.get(a)
                if r is None:
                    cells.append("--")
                    continue
                cut = " (front at the domain's end)" if r.get("front_at_domain_end") else ""
                cells.append(f"{r['d_n']:.2f} ({r['d_n'] / PAPER_DN[a]:.2f}){cut}")
            e1 = power_fit([0.5, 1.0], [got[a]["d_n"] for a in (0.5, 1.0)]) if all(a in got for a in (0.5, 1.0)) else None
            e2 = power_fit([2.0, 3.0], [got[a]["d_n"] for a in (2.0, 3.0)]) if all(a in got for a in (2.0, 3.0)) else None
            st = "all" if all(r["settled"] for r in got.values()) else ", ".join(f"a = {a:g}: NO" for a, r in got.items() if not r["settled"])
            name = "no-slip (the scenes)" if mu is None else f"Coulomb, mu = {mu:g}" + (" (tan phi)" if mu == 0.36 else "")
            lines.append(f"| {name} | {dx * 1e3:g} | " + " | ".join(cells) + f" | {fmt(e1, '{:.2f}')} | {fmt(e2, '{:.2f}')} | {st} |")
    return "\n".join(lines)


def table_cylinder(res) -> str:
    """Sec. 4.2.3: the 3D cylinder's radial run-out, height at the axis and deposit slope against phi."""
    rows = sorted(_rows(res, setup="cylinder3d"), key=lambda r: r["config"]["phi"])
    lines = ["| phi [deg] | dx [mm] | particles | L_f (radius of the deposit) [m] | d_n = (L_f - R0) / R0 | "
             "height at the axis / H0 | deposit slope [deg] | settled | wall [min] |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        c = r["config"]
        st = f"yes, {r['settled_time']:.2f} s" if r["settled"] else f"NO (t_end {r['t_end']:.2f} s)"
        lines.append(f"| {c['phi']:g} | {c['dx'] * 1e3:g} | {r['particles']} | {fmt(r['L_f'])} | {fmt(r['d_n'], '{:.3f}')} | "
                     f"{fmt(r['H_wall_over_H0'], '{:.3f}')} | {fmt(r.get('deposit_angle_deg'), '{:.1f}')} | {st} | "
                     f"{r['wall_s'] / 60:.1f} |")
    return "\n".join(lines)


def table_aspect3d(res) -> str:
    rows = sorted(_rows(res, setup="column3d"), key=lambda r: (-r["config"]["dx"], r["config"]["a"]))
    lines = ["| a | dx [mm] | cells across L0 | particles | L_f [m] | d_n (mpmlab 3D) | d_n (paper) | settled | "
             "wall [min] |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        c = r["config"]
        st = f"yes, {r['settled_time']:.2f} s" if r["settled"] else "NO"
        lines.append(f"| {c['a']:g} | {c['dx'] * 1e3:g} | {L0_COLUMN / c['dx']:.0f} | {r['particles']} | {fmt(r['L_f'])} | "
                     f"{fmt(r['d_n'], '{:.3f}')} | {fmt(PAPER_DN.get(c['a']), '{:.2f}')} | {st} | {r['wall_s'] / 60:.1f} |")
    return "\n".join(lines)


def plot(res: dict) -> None:
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return
    # convergence in dx
    fig, axes = plt.subplots(2, 2, figsize=(12, 8))
    axes = axes.ravel()
    for setup, a, lab in (("bui", None, "Sec. 4.1.2 (a = 0.5, L0 0.2)"), ("column", 2.0, "a = 2, L0 0.08")):
        rows = [r for r in _rows(res, setup=setup, dim=2, phi=19.8, ppc=4, precision="fp32")
                if setup == "bui" or r["config"]["a"] == a]
        rows.sort(key=lambda r: r["config"]["dx"])
        if rows:
            L0 = rows[0]["L0"]
            axes[0].plot([r["config"]["dx"] * 1e3 for r in rows], [r["L_f"] / L0 for r in rows], "o-", label=lab)
            axes[1].plot([r["config"]["dx"] * 1e3 for r in rows], [r["H_wall_over_H0"] for r in rows], "o-", label=lab)
        pr = sorted([r for r in _rows(res, setup=setup, dim=2, phi=19.8, dx=0.005, precision="fp32")
                     if setup == "bui" or r["config"]["a"] == a], key=lambda r: r["config"]["ppc"])
        if pr:
            axes[2].plot([r["config"]["ppc"] for r in pr], [r["L_f"] / pr[0]["L0"] for r in pr], "o-", label=lab)
    axes[0].set(xlabel="dx [mm] (4 particles per cell)", ylabel="L_f / L0", title="run-out vs dx")
    axes[1].set(xlabel="dx [mm] (4 particles per cell)", ylabel="H_wall / H0", title="height at the wall vs dx")
    axes[2].set(xlabel="particles per cell (dx 5 mm)", ylabel="L_f / L0", title="run-out vs particles per cell")
    for setup, a, ls in (("bui", None, "-"), ("column", 2.0, "--")):
        rows = [r for r in _rows(res, setup=setup, dim=2, phi=19.8, ppc=4, precision="fp32")
                if (setup == "bui" or r["config"]["a"] == a) and r["config"]["dx"] in (0.01, 0.005, 0.0025, 0.00125)]
        for i, r in enumerate(sorted(rows, key=lambda r: -r["config"]["dx"])):
            p = r["profile"]
            axes[3].plot(p["distance"], p["height"], ls, color=f"C{i}",
                         label=f"{'Sec. 4.1.2' if setup == 'bui' else 'a = 2'}, dx {r['config']['dx'] * 1e3:g} mm")
    axes[3].set(xlabel="distance from the wall [m]", ylabel="deposit height [m]", title="final deposit profiles")
    axes[3].set_aspect("equal", adjustable="datalim")
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(PLOTS / "granular_convergence.png", dpi=110)
    plt.close(fig)
    # aspect ratio
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    aa = np.array(sorted(PAPER_DN))
    axes[0].loglog(aa, [PAPER_DN[a] for a in aa], "ks--", label="JAX-MPM (paper, 3D)")
    by_dx: dict = {}
    for r in _rows(res, setup="column", dim=2, phi=19.8, ppc=4, precision="fp32"):
        by_dx.setdefault(r["config"]["dx"], []).append(r)
    for dx, rs in sorted(by_dx.items(), reverse=True):
        rs.sort(key=lambda r: r["config"]["a"])
        axes[0].loglog([r["config"]["a"] for r in rs], [r["d_n"] for r in rs], "o-", label=f"mpmlab 2D plane strain, dx {dx * 1e3:g} mm")
    r3 = {}
    for r in _rows(res, setup="column3d"):
        r3.setdefault(r["config"]["dx"], []).append(r)
    for dx, rs in sorted(r3.items(), reverse=True):
        rs.sort(key=lambda r: r["config"]["a"])
        axes[0].loglog([r["config"]["a"] for r in rs], [r["d_n"] for r in rs], "^:", label=f"mpmlab 3D, dx {dx * 1e3:g} mm (smoke)")
    axes[0].loglog(aa, 4.0 * aa, "k:", lw=0.8, label="slope 1")
    axes[0].loglog(aa, 5.0 * aa ** 0.7, "k-.", lw=0.8, label="slope 0.7")
    axes[0].set(xlabel="a = H0 / L0", ylabel="d_n = (L_f - L0) / L0", title="normalised run-out (Sec. 4.2.2)")
    axes[0].legend(fontsize=7)
    axes[0].grid(alpha=0.3, which="both")
    if by_dx:
        dx = min(by_dx)
        for r in sorted(by_dx[dx], key=lambda r: r["config"]["a"]):
            p = r["profile"]
            axes[1].plot(np.asarray(p["distance"]) / r["L0"], np.asarray(p["height"]) / r["L0"], label=f"a = {r['config']['a']:g}")
        axes[1].set(xlabel="x / L0", ylabel="deposit height / L0", title=f"final deposits (2D, dx {dx * 1e3:g} mm)")
        axes[1].set_aspect("equal", adjustable="datalim")
        axes[1].legend(fontsize=8)
        axes[1].grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(PLOTS / "granular_aspect.png", dpi=110)
    plt.close(fig)
    # friction
    fr = sorted(_rows(res, setup="column", dim=2, a=2.0, dx=0.005, ppc=4, precision="fp32"), key=lambda r: r["config"]["phi"])
    if len(fr) > 1:
        fig, axes = plt.subplots(1, 2, figsize=(11, 4))
        axes[0].plot([r["config"]["phi"] for r in fr], [r["d_n"] for r in fr], "o-")
        axes[0].set(xlabel="friction angle [deg]", ylabel="d_n", title="run-out vs friction angle (2D, a = 2)")
        for r in fr:
            p = r["profile"]
            axes[1].plot(p["distance"], p["height"], label=f"phi = {r['config']['phi']:g}")
        axes[1].set(xlabel="x [m]", ylabel="height [m]", title="final deposits")
        axes[1].set_aspect("equal", adjustable="datalim")
        axes[1].legend(fontsize=8)
        for ax in axes:
            ax.grid(alpha=0.3)
        fig.tight_layout()
        fig.savefig(PLOTS / "granular_friction.png", dpi=110)
        plt.close(fig)
    plot_bars(res)


def failure_angle(x0: np.ndarray, eps_p: np.ndarray, threshold: float = 0.03) -> float:
    """Angle from the horizontal [deg] of the failure line in the initial configuration: per row of
    initial positions (10 % to 90 % of the column height), the largest x of a particle that stays below
    ``threshold``; a least-squares line through those points."""
    y = np.round(x0[:, 1], 9)
    rows = np.unique(y)
    h = rows.max()
    px, py = [], []
    for yy in rows[(rows > 0.1 * h) & (rows < 0.9 * h)]:
        m = (y == yy) & (eps_p <= threshold)
        if m.any():
            px.append(x0[m, 0].max())
            py.append(yy)
    if len(px) < 3:
        return float("nan")
    return float(math.degrees(math.atan(abs(np.polyfit(px, py, 1)[0]))))


def bars_summary(res) -> str:
    """Sec. 4.1.2: run-out, height at the wall and failure-line angle of every saved Bui run."""
    lines = ["| dx [mm] | ppc | L_f [m] | L_f at 0.65 s [m] | H_wall [m] | failure line [deg] | settled |",
             "|---|---|---|---|---|---|---|"]
    for r in sorted(_rows(res, setup="bui", dim=2, phi=19.8, precision="fp32"), key=lambda r: (-r["config"]["dx"], r["config"]["ppc"])):
        f = FINAL / (hashlib.sha1(key(r["config"]).encode()).hexdigest()[:16] + ".npz")
        ang = None
        if f.exists():
            z = np.load(f)
            ang = failure_angle(z["x0"], z["eps_p"])
        st = f"yes, {r['settled_time']:.2f} s" if r["settled"] else "NO"
        lines.append(f"| {r['config']['dx'] * 1e3:g} | {r['config']['ppc']} | {fmt(r['L_f'])} | {fmt(at_time(r, 0.65))} | "
                     f"{fmt(r['H_wall'])} | {fmt(ang, '{:.1f}')} | {st} |")
    return "\n".join(lines)


def plot_bars(res) -> None:
    """Sec. 4.1.2: the finest Bui run's final deposit coloured by eps_p, the failure surface (eps_p > 0.03
    in the initial configuration, and its boundary in the final one), the initial column."""
    import matplotlib.pyplot as plt

    rows = sorted([r for r in _rows(res, setup="bui", dim=2, phi=19.8, ppc=4, precision="fp32")],
                  key=lambda r: r["config"]["dx"])
    rows = [r for r in rows if (FINAL / (hashlib.sha1(key(r["config"]).encode()).hexdigest()[:16] + ".npz")).exists()]
    if not rows:
        return
    r = rows[0]
    z = np.load(FINAL / (hashlib.sha1(key(r["config"]).encode()).hexdigest()[:16] + ".npz"))
    x, e, x0 = z["x"], z["eps_p"], z["x0"]
    fig, axes = plt.subplots(2, 1, figsize=(10, 6.5))
    sc = axes[0].scatter(x[:, 0], x[:, 1], c=np.clip(e, 0, 0.5), s=1.5, cmap="viridis")
    fail = e > 0.03
    axes[0].plot([0, 0.2, 0.2], [0.1, 0.1, 0.0], "k--", lw=0.8, label="initial column")
    p = r["profile"]
    axes[0].plot(p["distance"], p["height"], "r-", lw=1, label="free surface (deposit profile)")
    # failure surface: for each column of bins, the lowest particle with eps_p > 0.03 (final configuration)
    bins = np.arange(0, r["L_f"] + r["config"]["dx"], r["config"]["dx"])
    fx, fy = [], []
    for lo, hi in zip(bins[:-1], bins[1:]):
        m = fail & (x[:, 0] >= lo) & (x[:, 0] < hi)
        if m.any():
            fx.append(0.5 * (lo + hi))
            fy.append(x[m, 1].min())
    axes[0].plot(fx, fy, "w-", lw=1.2, label="failure surface (lowest eps_p > 0.03)")
    fig.colorbar(sc, ax=axes[0], label="eps_p (clipped at 0.5)")
    axes[0].set(xlabel="x [m]", ylabel="y [m]", title=f"final deposit, dx {r['config']['dx'] * 1e3:g} mm, "
                f"t = {r['t_end']:.2f} s: L_f = {r['L_f']:.4f} m, H_wall = {r['H_wall']:.4f} m")
    axes[0].set_aspect("equal")
    axes[0].legend(fontsize=7, loc="upper right")
    axes[1].scatter(x0[:, 0], x0[:, 1], c=np.where(fail, 1.0, 0.0), s=1.5, cmap="coolwarm")
    ang = failure_angle(x0, e)
    axes[1].set(xlabel="x [m]", ylabel="y [m]", title="initial positions: red = eps_p > 0.03 at the end (the sliding "
                f"wedge); the failure line fits {ang:.1f} deg from the horizontal")
    axes[1].set_aspect("equal")
    axes[1].set_xlim(axes[0].get_xlim())
    fig.tight_layout()
    fig.savefig(PLOTS / "granular_bars.png", dpi=110)
    plt.close(fig)


def write_md(res: dict) -> None:
    if not MD.exists():
        return
    text = MD.read_text()
    for name, fn in (("convergence", table_convergence), ("aspect", table_aspect), ("friction", table_friction),
                     ("aspect3d", table_aspect3d), ("boundary", table_boundary), ("bars", bars_summary),
                     ("sensitivity", table_sensitivity), ("cylinder3d", table_cylinder),
                     ("aspect_pure_flip", lambda r: table_aspect(r, flip_ratio=1.0)), ("flip_dt", table_flip_dt),
                     ("pic_time_tau", table_pic_time_tau), ("default_dx", table_default_dx),
                     ("base_friction", table_base_friction)):
        a, b = f"<!-- {name} -->", f"<!-- /{name} -->"
        if a in text and b in text:
            text = text[: text.index(a) + len(a)] + "\n" + fn(res) + "\n" + text[text.index(b):]
    MD.write_text(text)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--part", action="append", help="convergence|aspect|friction|bars|aspect3d|aspect3d_fine|scale|boundary|flow_rule|transfer|cylinder3d|aspect_pure_flip|flip_dt|pic_time_dx|pic_time_tau|default_dx|base_friction (repeatable; default all)")
    ap.add_argument("--full", action="store_true", help="add the finest grids")
    ap.add_argument("--report", action="store_true", help="tables and plots from saved results only")
    ap.add_argument("--only", default="", help="run only configurations whose key contains this")
    ap.add_argument("--aspect-dx", type=float, default=0.0025, help="dx of the aspect part (default 2.5 mm)")
    ap.add_argument("--checkpoint-s", type=float, default=120.0, help="wall seconds between checkpoints")
    ap.add_argument("--deadline", default=None, help="stop (checkpointed) at this epoch time or HH:MM UTC")
    args = ap.parse_args()
    deadline = None
    if args.deadline:
        if ":" in args.deadline:
            import datetime as _dt
            hh, mm = map(int, args.deadline.split(":"))
            now = _dt.datetime.now(_dt.timezone.utc)
            deadline = now.replace(hour=hh, minute=mm, second=0, microsecond=0).timestamp()
        else:
            deadline = float(args.deadline)
    res = load()
    if not args.report:
        parts = args.part or ["convergence", "aspect", "friction", "bars", "aspect3d"]
        for part in parts:
            for c in configs(part, args.full, args.aspect_dx):
                k = key(c)
                if k in res or args.only not in k:
                    continue
                print(f"{k}: running", flush=True)
                t0 = time.perf_counter()
                r = run_one(c, args.checkpoint_s, deadline, log=lambda s: print(s, flush=True))
                if r is None:
                    print("deadline reached; resume with the same command", flush=True)
                    break
                r["config"] = c
                res[k] = r
                save(res)
                print(f"{k}: L_f {r['L_f']:.4f} m d_n {r['d_n']:.3f} H_wall {r['H_wall']:.4f} settled {r['settled']} "
                      f"t {r['t_end']:.2f} s ({time.perf_counter() - t0:.0f} s)", flush=True)
            else:
                continue
            break
    print(table_convergence(res))
    print(table_aspect(res))
    print(table_friction(res))
    print(table_aspect3d(res))
    plot(res)
    write_md(res)


if __name__ == "__main__":
    main()
