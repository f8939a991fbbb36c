"""Why a run diverged (issue 19, item 5): a classification from measured quantities of the states
just before the failure, and one line saying what grew, where, the number, and what to try.

``BaseStepper._diverged`` replays the failed chunk one step at a time; it keeps the chunk's start
state and the last few sound states (a bounded ring), and hands them with the failed state to
:func:`diagnose`. Everything here is NumPy on those host copies: nothing is recompiled or re-run.

Measured quantities (all reported in ``Diagnosis.measures``):

* ``cfl_wave`` = dt c / dx (c: the scene's largest elastic wave speed at rest), ``cfl_start`` =
  dt (c + |v|_99) / dx at the chunk start (|v|_99: the 99th percentile particle speed, the bulk of the
  body, not one runaway particle) and ``cfl_prev`` = dt (c + max |v|) / dx one step before the failure
  (the number the old message gave).
* ``move_cells``: the largest particle displacement in one step, in cells (the step before the
  failure, and the failing step among finite particles), and the particle's speed relative to the
  median speed.
* ``J``: the volume ratio (the law's J, or det F) of the failing particle and the smallest J one
  step before.
* ``ripple``: the grid-scale (cell-to-cell) oscillation of J: J averaged per grid cell minus the
  average of its occupied 3 x 3 neighbourhood, its largest magnitude and where, and how much of J's
  deviation from 1 it is (``ripple_share``: ripple / (ripple + smooth deviation)); and its value at
  the chunk start (growth).

* ``frames``: the J range and largest speed of the recent kept frames (``frame_note``, recorded by the
  rollout at every kept frame: O(N), no sort), so a collapse long before the failing chunk is seen.

Causes, checked in this order (the first that the numbers support):

``law``           a non-finite value one step after a sound, quiet state (CFL fine, nothing moving half
                  a cell per step, J of the particle in (0.1, 10), no J ripple): the law (or a body force)
                  produced it, e.g. an out-of-range parameter or an overflow in the precision used.
``cfl``           the time step: dt c / dx above the limit (min(scene.cfl_limit, 1, the law's measured
                  C*)), or dt (c + |v|_99) / dx at the chunk start above it with a smooth velocity field
                  (grid-scale share < 0.05: the speeds are the motion's, not noise): reduce dt / dt: auto.
``cell_crossing`` J ripples cell to cell (largest ripple >= 0.05, about a linear fit through the 3^D
                  neighbouring cells) and either dominates J's deviation (share >= 0.5), or J swings both
                  ways (J_min <= 0.8 and J_max >= 1.2), or the velocity field is noisy (share >= 0.05):
                  grid-aligned modes from particles crossing cells (the ringing/cell-crossing instability
                  of B-spline MPM); another shape function or transfer; dt does not help. With CPDI
                  already in use the advice is the measured one: a smaller dt (benchmarks/large_shear.md:
                  CPDI + APIC's late divergence on the finest grid is gone at 0.75 dt and dt/2, while
                  halving dt only delays the B-splines' ringing).
``velocity``      a particle moved more than 1 cell in one step (left its stencil neighbourhood) while
                  its J was not already collapsed: its velocity blew up locally.
``compression``   J of the failing particle (or the smallest J) collapsed (<= 0.1) or inverted, or a
                  recent kept frame had J_min <= 0.1 with no J above 1.2 at a fine CFL: large
                  compression/shear; another shape function/transfer, more particles per cell, finer grid.
``domain``        a particle reached the domain edge at a modest speed (or, with CPDI, a corner of its domain
                  did: the message gives the domain's stretch): enlarge the domain or add walls.
``unknown``       none of the above: the numbers are still reported.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from .interfaces import AbstractConstitutiveLaw

CAUSES = ("law", "cfl", "compression", "cell_crossing", "velocity", "domain", "unknown")

#: thresholds (see the module docstring); module constants so a study can change them
J_COLLAPSE = 0.1
J_BLOWUP = 10.0
RIPPLE_MIN = 0.05
RIPPLE_SHARE = 0.5
MOVE_CELLS = 1.0
V_NOISE = 0.05
TWO_SIDED = 0.2
QUIET_MOVE = 0.5


@dataclass
class Diagnosis:
    cause: str
    line: str                       # what grew, where, the number, what to try (one line)
    measures: dict[str, Any] = field(default_factory=dict)


def _det(F: np.ndarray) -> np.ndarray:
    """det of [N, D, D] by the explicit 2x2 / 3x3 formula (a batched LU is ~20x slower). A diverged
    state's F may overflow it: that is inf / nan for those particles, not a warning on the console."""
    F = np.asarray(F)
    with np.errstate(over="ignore", invalid="ignore"):
        if F.shape[-1] == 2:
            return F[:, 0, 0] * F[:, 1, 1] - F[:, 0, 1] * F[:, 1, 0]
        if F.shape[-1] == 3:
            a, b, c = F[:, 0, 0], F[:, 0, 1], F[:, 0, 2]
            return (a * (F[:, 1, 1] * F[:, 2, 2] - F[:, 1, 2] * F[:, 2, 1])
                    - b * (F[:, 1, 0] * F[:, 2, 2] - F[:, 1, 2] * F[:, 2, 0])
                    + c * (F[:, 1, 0] * F[:, 2, 1] - F[:, 1, 1] * F[:, 2, 0]))
        return np.linalg.det(F)


def volume_ratio(stepper, npstate: dict[str, np.ndarray]) -> np.ndarray:
    """Per-particle J (the law's scalar J, else det F; NaN for particles whose law keeps neither)."""
    n = len(npstate["x"])
    J = None
    for name, f in getattr(stepper, "state_fields", {}).items():
        if name not in npstate or f.check not in ("positive", "positive_det"):
            continue
        a = np.asarray(npstate[name])
        val = a.reshape(len(a)) if f.check == "positive" else _det(a)
        idx = npstate.get(name + "_particles")
        if J is None and (idx is None or len(val) == n):
            J = np.array(val, float)            # one field covers every particle (the common case)
            if idx is not None:
                J[np.asarray(idx)] = val
            continue
        if J is None:
            J = np.full(n, np.nan)
        idx = np.arange(len(val)) if idx is None else np.asarray(idx)
        fill = np.isnan(J[idx])
        J[idx[fill]] = val[fill]
    if J is None:
        J = np.asarray(_det(npstate["F"]), float) if "F" in npstate else np.full(n, np.nan)
    return J


def frame_note(stepper, npstate: dict, step: int) -> dict[str, float]:
    """What the rollout remembers of a kept frame for a later diagnosis (O(N), no sort): step, J range,
    largest speed."""
    J = volume_ratio(stepper, npstate)
    v = npstate["v"]
    sp2 = np.einsum("ij,ij->i", v, v)
    return {"step": int(step), "J_min": float(np.nanmin(J, initial=np.inf)) if len(J) else float("nan"),
            "J_max": float(np.nanmax(J, initial=-np.inf)) if len(J) else float("nan"),
            "speed_max": float(np.sqrt(np.max(sp2, initial=0.0)))}


def _cells(x: np.ndarray, origin: np.ndarray, dx: float) -> np.ndarray:
    return np.floor((x - origin) / dx).astype(np.int64)


#: the ripple measures work on a dense block of cells; above this many they use the block around ``center``
MAX_CELLS = 1 << 17


def _ripple_fields(x: np.ndarray, vals: np.ndarray, origin: np.ndarray, dx: float, center=None):
    """Per occupied cell: the cell mean of each column of ``vals`` [N, K] and its least-squares linear fit
    a + b . o through the occupied cells o of the cell's 3^D neighbourhood (exact for a linear field, so a
    smooth gradient, a rotation or a uniform compression has no ripple). Returns (cell means [C, K],
    fits [C, K], cell centres [C, D]) or None. Memory is bounded: above ``MAX_CELLS`` cells only the block
    around ``center`` (default: the median particle) is used."""
    ok = np.all(np.isfinite(vals), axis=1) & np.all(np.isfinite(x), axis=1)
    if ok.sum() < 2:
        return None
    x, vals = x[ok], vals[ok]
    c = _cells(x, origin, dx)
    span = c.max(axis=0) - c.min(axis=0) + 3
    if float(np.prod(span.astype(float))) > MAX_CELLS:
        half = int(MAX_CELLS ** (1.0 / c.shape[1]) / 2) - 2
        mid = (_cells(np.asarray(center, float)[None], origin, dx)[0] if center is not None
               and np.all(np.isfinite(center)) else np.median(c, axis=0).astype(np.int64))
        keep = np.all(np.abs(c - mid) <= half, axis=1)
        if keep.sum() < 2:
            return None
        vals, c = vals[keep], c[keep]
    lo = c.min(axis=0) - 1
    c = c - lo
    shape = tuple(int(s) for s in c.max(axis=0) + 2)
    dim, K = len(shape), vals.shape[1]
    lin = np.ravel_multi_index(c.T, shape)
    size = int(np.prod(shape))
    cnt = np.bincount(lin, minlength=size).astype(float)
    occ = cnt > 0
    Vc = np.stack([np.bincount(lin, weights=vals[:, k], minlength=size) for k in range(K)], -1)
    Vc = (Vc / np.maximum(cnt, 1)[:, None]).reshape(shape + (K,))
    occ_g = occ.reshape(shape).astype(float)
    M = np.zeros(shape + (dim + 1, dim + 1))
    rhs = np.zeros(shape + (dim + 1, K))
    for off in np.ndindex(*(3,) * dim):
        o = np.array([1.0, *(np.asarray(off) - 1.0)])
        sl_dst = tuple(slice(max(0, 1 - q), s - max(0, q - 1)) for q, s in zip(off, shape))
        sl_src = tuple(slice(max(0, q - 1), s - max(0, 1 - q)) for q, s in zip(off, shape))
        wgt = occ_g[sl_src]
        M[sl_dst] += wgt[..., None, None] * np.outer(o, o)
        rhs[sl_dst] += (wgt[..., None] * Vc[sl_src])[..., None, :] * o[:, None]
    occ = occ.reshape(shape)
    Mo, ro = M[occ] + 1e-9 * np.eye(dim + 1), rhs[occ]
    n_nb = Mo[:, 0, 0]
    coef = np.linalg.solve(Mo, ro)                       # [C, D + 1, K]
    few = (n_nb < dim + 2)[:, None]                      # too few neighbours for a fit: their mean
    fit = np.where(few, ro[:, 0, :] / np.maximum(n_nb, 1e-300)[:, None], coef[:, 0, :])
    centres = (np.argwhere(occ) + lo + 0.5) * dx + origin
    return Vc[occ], fit, centres


def ripple(x: np.ndarray, J: np.ndarray, origin: np.ndarray, dx: float, ref: float = 1.0,
           center=None) -> dict[str, Any]:
    """Grid-scale oscillation of J: per-cell mean J minus its linear fit over the occupied 3^D
    neighbourhood (:func:`_ripple_fields`).

    Returns ``ripple`` (largest |.|), ``ripple_rms``, ``smooth_dev`` (largest |fit - ref|),
    ``ripple_share`` = ripple_rms / (ripple_rms + rms smooth deviation from ``ref``), and ``ripple_at`` (the
    cell centre of the largest ripple)."""
    f = _ripple_fields(x, np.asarray(J, float)[:, None], origin, dx, center)
    if f is None:
        return {"ripple": 0.0, "ripple_rms": 0.0, "smooth_dev": 0.0, "ripple_share": 0.0, "ripple_at": None}
    mean, fit, centres = f
    r, dev = (mean - fit)[:, 0], fit[:, 0] - ref
    k = int(np.argmax(np.abs(r)))
    rr, dd = float(np.sqrt(np.mean(r * r))), float(np.sqrt(np.mean(dev * dev)))
    return {"ripple": float(abs(r[k])), "ripple_rms": rr, "smooth_dev": float(np.max(np.abs(dev))),
            "ripple_share": rr / (rr + dd) if rr + dd > 0 else 0.0, "ripple_at": centres[k].tolist()}


def velocity_noise(x: np.ndarray, v: np.ndarray, origin: np.ndarray, dx: float, center=None) -> float:
    """Share of the velocity field that is grid-scale (cell-to-cell) oscillation: rms ripple of the
    per-cell mean velocity / (rms ripple + rms of its smooth fit); 0 for a smooth field (a rigid motion,
    a rotation, a uniform compression), growing towards 0.5 and beyond for noise."""
    f = _ripple_fields(x, np.asarray(v, float), origin, dx, center)
    if f is None:
        return 0.0
    mean, fit, _ = f
    rr = float(np.sqrt(np.mean(np.sum((mean - fit) ** 2, axis=1))))
    dd = float(np.sqrt(np.mean(np.sum(fit**2, axis=1))))
    return rr / (rr + dd) if rr + dd > 0 else 0.0


def _fmt(p) -> str:
    return "[" + ", ".join(f"{float(a):.4g}" for a in np.ravel(p)) + "]"


def _nonfinite(value) -> bool:
    try:
        return not np.all(np.isfinite(np.asarray(value, float)))
    except (TypeError, ValueError):
        return True


def diagnose(stepper, start: dict, history: Sequence[dict], failed: dict, failure: tuple,
             frames: Sequence[dict] = ()) -> Diagnosis:
    """Classify a failure. ``start``: the replayed chunk's first state; ``history``: the last sound
    states, oldest first (the last is one step before the failure; it may be ``start``); ``failed``:
    the state where ``locate_failure`` found ``failure`` = (particle, field, value); ``frames``: the
    :func:`frame_note` of the recent kept frames (what happened before the chunk)."""
    scene = stepper.scene
    dt, dx = float(stepper.dt), float(scene.dx)
    origin = np.asarray(scene.origin, float)
    try:
        c = float(scene.wave_speed())
    except Exception:                  # a law without a wave speed: CFL from particle speeds only
        c = 0.0
    if not np.isfinite(c):
        c = 0.0
    caps = [getattr(law, "stable_cfl", None) for law in scene.body_laws()] if hasattr(scene, "body_laws") else []
    limit = min([float(scene.cfl_limit), 1.0] + [float(x) for x in caps if x])
    p, fname, value = failure
    prev = history[-1]
    before = history[-2] if len(history) > 1 else None

    def speeds(s):
        v = np.linalg.norm(np.asarray(s["v"], float), axis=1)
        return np.where(np.isfinite(v), v, np.inf)

    sp_prev, sp_start = speeds(prev), speeds(start)
    v99 = float(np.percentile(sp_start[np.isfinite(sp_start)], 99)) if np.isfinite(sp_start).any() else 0.0
    cfl_wave = dt * c / dx
    cfl_start = dt * (c + v99) / dx
    cfl_prev = dt * (c + float(np.max(sp_prev, initial=0.0))) / dx
    med = float(np.median(sp_prev)) if len(sp_prev) else 0.0

    xp_ = np.asarray(prev["x"], float)
    move_prev = (np.linalg.norm(xp_ - np.asarray(before["x"], float), axis=1) / dx if before is not None
                 else sp_prev * dt / dx)
    mv_fail = np.linalg.norm(np.asarray(failed["x"], float) - xp_, axis=1) / dx
    mv_fail = np.where(np.isfinite(mv_fail), mv_fail, -1.0)
    q_prev = int(np.argmax(move_prev)) if len(move_prev) else -1
    q_fail = int(np.argmax(mv_fail)) if len(mv_fail) else -1
    move_prev_max = float(move_prev[q_prev]) if q_prev >= 0 else 0.0
    move_fail_max = float(mv_fail[q_fail]) if q_fail >= 0 else 0.0

    J_prev = volume_ratio(stepper, prev)
    J_fail = volume_ratio(stepper, failed)
    have_J = not np.all(np.isnan(J_prev))
    Jp_prev = float(J_prev[p]) if 0 <= p < len(J_prev) else float("nan")
    Jp_fail = float(J_fail[p]) if 0 <= p < len(J_fail) else float("nan")
    k_min = int(np.nanargmin(J_prev)) if have_J else -1
    J_min = float(J_prev[k_min]) if have_J else float("nan")
    k_max = int(np.nanargmax(J_prev)) if have_J else -1
    J_max = float(J_prev[k_max]) if have_J else float("nan")
    ctr = xp_[p] if 0 <= p < len(xp_) else None
    rip = ripple(xp_, J_prev if have_J else np.full(len(xp_), np.nan), origin, dx, center=ctr)
    rip0 = (ripple(np.asarray(start["x"], float), volume_ratio(stepper, start), origin, dx, center=ctr)
            if have_J else rip)

    # the recent frames: did J collapse (smoothly: without J > 1 + TWO_SIDED elsewhere) before the failure?
    fr = [f for f in frames if np.isfinite(f["J_min"])]
    fr_collapse = next((f for f in fr if f["J_min"] <= J_COLLAPSE and f["J_max"] < 1.0 + TWO_SIDED
                        and dt * (c + f["speed_max"]) / dx <= limit), None)
    vn_start = velocity_noise(np.asarray(start["x"], float), np.asarray(start["v"], float), origin, dx, ctr)
    vn_prev = velocity_noise(xp_, np.asarray(prev["v"], float), origin, dx, ctr)
    two_sided = have_J and (1.0 - J_min) >= TWO_SIDED and (J_max - 1.0) >= TWO_SIDED
    pos = np.asarray(prev["x"][p], float) if 0 <= p < len(xp_) else np.full(scene.dim, np.nan)
    speed_p = float(sp_prev[p]) if 0 <= p < len(sp_prev) else float("nan")
    cfl_p = dt * (c + speed_p) / dx
    m = {"step_dt": dt, "dx": dx, "wave_speed": c, "cfl_limit_used": limit, "cfl_wave": cfl_wave,
         "cfl_start": cfl_start, "cfl_prev": cfl_prev, "speed_p99_start": v99, "speed_median": med,
         "move_cells_prev": move_prev_max, "move_particle_prev": q_prev, "move_cells_fail": move_fail_max,
         "move_particle_fail": q_fail, "J_particle_prev": Jp_prev, "J_particle_fail": Jp_fail, "J_min": J_min,
         "J_min_particle": k_min, "J_max": J_max, "J_max_particle": k_max, "particle": p,
         "position": pos.tolist(), "speed_particle": speed_p, "cfl_particle": cfl_p,
         "ripple": rip["ripple"], "ripple_rms": rip["ripple_rms"], "ripple_share": rip["ripple_share"],
         "ripple_at": rip["ripple_at"], "ripple_start": rip0["ripple"], "smooth_J_dev": rip["smooth_dev"],
         "velocity_noise_start": vn_start, "velocity_noise_prev": vn_prev, "J_two_sided": bool(two_sided),
         "frames_J_min": [f["J_min"] for f in fr], "frames_J_max": [f["J_max"] for f in fr],
         "frames_step": [f["step"] for f in fr], "frames_speed_max": [f["speed_max"] for f in fr]}
    where = f"particle {p} at {_fmt(pos)}"
    nums = (f"CFL number {cfl_prev:.3g} one step before (dt c/dx = {cfl_wave:.3g}, with the bulk speed at the chunk "
            f"start {cfl_start:.3g}; limit {limit:g})")
    nonfinite = _nonfinite(value)
    J_ok = not have_J or not np.isfinite(Jp_prev) or (J_COLLAPSE < Jp_prev < J_BLOWUP)
    quiet = (cfl_prev <= limit and move_prev_max <= QUIET_MOVE and J_ok and rip["ripple"] < RIPPLE_MIN)

    notes = law_notes(stepper, prev, p)
    if notes:
        m["law_notes"] = notes

    def out(cause, line):
        return Diagnosis(cause, "; ".join([line, *notes]), m)

    noise = have_J and rip["ripple"] >= RIPPLE_MIN and (rip["ripple_share"] >= RIPPLE_SHARE or two_sided
                                                         or max(vn_start, vn_prev) >= V_NOISE)
    # (e) the law: one step from a sound, quiet state to a non-finite value
    if nonfinite and quiet:
        law = _law_of(stepper, p)
        return out("law", f"cause: law -- {fname} became non-finite in one step from a sound state at {where} "
                          f"(J {Jp_prev:.4g}, speed {speed_p:.3g} m/s, {nums}): law '{law}' (or a body force) "
                          f"returned a non-finite value; check its parameters for values out of range or beyond "
                          f"what {stepper.precision} can represent; a smaller dt does not help")
    # (a) the time step
    if cfl_wave > limit or (cfl_start > limit and vn_start < V_NOISE):
        what = "wave speed" if cfl_wave > limit else "wave and particle speeds (a smooth velocity field)"
        return out("cfl", f"cause: CFL -- the time step is too large for the {what}: {nums}; "
                          f"reduce dt (or use dt: auto, a smaller cfl)")
    # (d) grid-scale noise in J
    if noise:
        if getattr(getattr(stepper, "shape", None), "kind", None) == "corners":
            # CPDI already: measured (benchmarks/large_shear.md, vortex3) -- its late divergence under
            # large shear on fine grids goes away with a smaller dt, unlike the B-splines' ringing
            advice = ("grid-scale modes in J under large deformation, with CPDI's domains (the twisted discs of "
                      "benchmarks/large_shear.md fail so just past their peak shear on the finest grid at the "
                      "CFL-0.3 step); try a smaller dt: 0.75 dt and dt/2 removed that divergence there, the stable "
                      "step under shear 6 shrinking faster than dx; with CPDI, APIC is the transfer that survives "
                      "there (MLS and PIC fail earlier)")
        else:
            advice = ("grid-aligned modes from particles crossing cells (the ringing instability of B-spline MPM "
                      "under large deformation); try another shape function: CPDI with APIC "
                      "(transfer.shape=cpdi: the twisted discs of benchmarks/large_shear.md then "
                      "survive their peak shear 6 on every grid at 2 particles per axis), or the "
                      "cubic B-spline (transfer.shape=cubic) with 4 particles per axis, or another "
                      "transfer; a smaller dt does not help")
        at = _fmt(rip["ripple_at"])
        return out("cell_crossing", f"cause: cell-crossing noise -- J ripples from cell to cell by up to "
                                    f"{rip['ripple']:.3g} (at {at}; {100 * rip['ripple_share']:.0f} % of J's "
                                    f"deviation, {rip0['ripple']:.3g} at the chunk start; J from {J_min:.3g} to "
                                    f"{J_max:.3g}; grid-scale share of the velocity field "
                                    f"{max(vn_start, vn_prev):.2g}) before {where} (J {Jp_prev:.4g}, speed "
                                    f"{speed_p:.3g} m/s = "
                                    f"{speed_p / max(med, 1e-300):.3g} x the median) failed; {nums}: " + advice)
    # (c) a runaway particle
    gradual = have_J and np.isfinite(Jp_prev) and Jp_prev <= J_COLLAPSE
    if (move_prev_max > MOVE_CELLS or move_fail_max > MOVE_CELLS) and not gradual:
        q, mv = (q_fail, move_fail_max) if move_fail_max >= move_prev_max else (q_prev, move_prev_max)
        qs = float(sp_prev[q]) if 0 <= q < len(sp_prev) else float("nan")
        return out("velocity", f"cause: velocity blow-up -- particle {q} at {_fmt(xp_[q])} moved {mv:.3g} cells in "
                               f"one step (speed {qs:.3g} m/s, {qs / max(med, 1e-300):.3g} x the median), leaving "
                               f"its stencil neighbourhood; {nums}: find what accelerates it (a contact, a load, "
                               f"a boundary, noise); reduce dt only if the CFL number with the bulk speed is above "
                               f"the limit")
    # (b) collapse / inversion of a smooth J field
    collapsed = (fname == "J" or (np.isfinite(Jp_fail) and Jp_fail <= J_COLLAPSE) or
                 (have_J and J_min <= J_COLLAPSE))
    if fr_collapse is not None and not collapsed:
        f = fr_collapse
        return out("compression", f"cause: J collapse -- J fell to {f['J_min']:.3g} at step {f['step']} (largest J "
                                  f"{f['J_max']:.3g}, CFL number {dt * (c + f['speed_max']) / dx:.3g} then), before "
                                  f"{where} failed with J {Jp_prev:.4g}, speed {speed_p:.3g} m/s ({nums}): large "
                                  f"compression, then the stiffened material outran the time step; try another shape "
                                  f"function or transfer, more particles per cell, a finer grid, or a law/parameters "
                                  f"that resist it; a smaller dt only delays it")
    if collapsed:
        k = p if fname == "J" or (np.isfinite(Jp_fail) and Jp_fail <= J_COLLAPSE) else k_min
        kpos = np.asarray(prev["x"][k], float)
        return out("compression", f"cause: J collapse -- particle {k} at {_fmt(kpos)} was compressed/sheared to "
                                  f"J = {float(J_prev[k]):.3g} one step before (J = {Jp_fail:.3g} at the failure; "
                                  f"smallest J {J_min:.3g}), with the J field smooth (cell-to-cell ripple "
                                  f"{rip['ripple']:.3g}) and the {nums}: large compression or shear, not the time "
                                  f"step; try another shape function or transfer, more particles per cell or a finer "
                                  f"grid, or a law that resists it; a smaller dt does not help")
    if fname.startswith("domain (a CPDI corner") and "domain" in prev:
        # CPDI: a corner of the particle's domain reached the grid edge; was it the domain's stretch?
        half = float(np.linalg.svd(np.asarray(prev["domain"][p], float), compute_uv=False)[0])
        try:
            half0 = float(np.linalg.svd(stepper.initial_domain()[p], compute_uv=False)[0])
        except Exception:              # a stepper without the initial domain: the chunk start's
            half0 = float(np.linalg.svd(np.asarray(start["domain"][p], float), compute_uv=False)[0])
        grow = half / max(half0, 1e-300)
        m["domain_half_length"], m["domain_growth"] = half, grow
        why = ("a domain stretched beyond a cell is CPDI's known limit (CPDI2 or particle splitting, not in "
               "mpmlab): another shape function avoids it, or enlarge the domain" if half > dx else
               "the particle itself reached the edge: enlarge the domain or add walls")
        return out("domain", f"cause: domain -- a corner of the CPDI domain of {where} left the grid at "
                             f"{_fmt(value)} (its longest half axis {half:.3g} m = {half / dx:.2g} cells, x{grow:.3g} "
                             f"its initial size; the particle moved at {speed_p:.3g} m/s, {nums}); {why}")
    if fname.startswith("x (outside"):
        return out("domain", f"cause: domain -- {where} reached the domain edge at {speed_p:.3g} m/s "
                             f"({move_prev_max:.3g} cells per step at most, {nums}); enlarge the domain or add walls")
    return out("unknown", f"cause: not classified -- {where}, J {Jp_prev:.4g}, speed {speed_p:.3g} m/s, largest "
                          f"move {move_prev_max:.3g} cells per step, J ripple {rip['ripple']:.3g}; {nums}; reduce dt "
                          f"if the CFL number is near the limit, else check the law, loads and boundaries")


def law_notes(stepper, npstate: dict, p: int) -> list[str]:
    """Each material group's law's :meth:`~mpmlab.core.interfaces.AbstractConstitutiveLaw.divergence_note`
    on its particles' state in ``npstate`` (``p``: the failing particle, scene order); a law whose note
    fails to compute is left out (the diagnosis must not fail)."""
    out = []
    for g in getattr(stepper, "groups", ()):
        law = getattr(g, "law", None)
        if law is None or type(law).divergence_note is AbstractConstitutiveLaw.divergence_note:
            continue
        fields, local = {}, (p - g.start if g.start <= p < g.stop else -1)
        for name in getattr(law, "state_fields", ()):
            if name not in npstate:
                continue
            idx = np.asarray(npstate.get(name + "_particles", np.arange(len(npstate[name]))))
            sel = (idx >= g.start) & (idx < g.stop)
            fields[name] = np.asarray(npstate[name], float)[sel]
        try:
            note = law.divergence_note(fields, local)
        except Exception:      # a note is a courtesy: never let it hide the diagnosis
            note = None
        if note:
            out.append(note)
    return out


def _law_of(stepper, p: int) -> str:
    for g in getattr(stepper, "groups", ()):
        if g.start <= p < g.stop:
            return g.law.name
    return "?"
