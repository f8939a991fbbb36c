"""Stability stress suite (issue #5 items 3-4): measured CFL limits, stress cases, long runs, random scenes.

One command regenerates everything::

    python benchmarks/stress.py                    # default set, both backends (~15-25 min on 2 busy cores)
    python benchmarks/stress.py --quick            # a smoke-sized run (a few minutes)
    python benchmarks/stress.py --full             # + every registered law (solids and fluids) in the sweep, 1000-step horizon
    python benchmarks/stress.py --backends jax --parts sweep,cases
    python benchmarks/stress.py --full --parts sweep --laws drucker_prager_jaumann --no-readme   # one law's rows
    python benchmarks/stress.py --parts dpj_study --study-label NAME   # why drucker_prager_jaumann had C* = 0.2
    python benchmarks/stress.py --render-only      # rewrite stress.md (+ README section) from the results files

and writes ``benchmarks/results/stress.json``, ``benchmarks/stress.md`` (C* table + outcomes table) and
the ``stress`` section of ``benchmarks/README.md``.

**C\\* sweep.** dt = C dx / (c_p + |v|max) with |v|max of the initial state and c_p the law's P-wave
speed (verification note #7). A fixed C is **stable** when a fixed-dt rollout of ``horizon`` steps
(500 by default) from the initial state (a) raises no ``SimulationDiverged`` (guards every 10 steps:
non-finite x/v/law state, J <= 0, particle outside the domain) **and** (b) its kinetic energy never
exceeds 1.5 x the energy available to it (initial kinetic energy + the largest work gravity can do
over the domain height + for the bar nothing else). C\\* is the largest stable C found by bisection
in log C over [0.02, 3] (7 halvings: brackets within ~5 %); the table gives C\\* = the largest C found
stable (the lower bracket). Stability is assumed monotone in C between the brackets (each bracket was
run; the in-between values were not all run).

**Stress cases.** Each runs with the library defaults (``dt: auto`` recomputed every ``dt_every``
steps) on both backends in fp32 for a bounded number of steps; the outcome is ``ok`` (finite
trajectory, kinetic energy bounded as above), ``diverged`` (``SimulationDiverged`` naming step,
particle, field), ``config_error`` (the one-sentence ``ConfigError``), or ``BAD`` (a NaN in a
returned trajectory, an unbounded energy without an error, any other exception) -- BAD must never occur.

**Long run.** A spinning elastic disc (no gravity, no walls) for 100k steps per transfer: PIC and APIC
must never gain kinetic energy (no external work; verification note #5b). Kinetic and elastic
(fixed-corotated reference energy) energies are sampled every 100 steps.
"""
from __future__ import annotations

import json
import math
import sys
import time
import traceback
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _harness as H  # noqa: E402
from _harness import log, machine_info, write_readme_section  # noqa: E402

H.quiet_warp(threads=1)   # before Warp is imported
HERE = H.HERE

TRANSFERS = ("pic", "flip", "apic", "mls", "tpic")
C_LO, C_HI, HALVINGS = 0.02, 3.0, 7
#: kinetic energy allowed over the available energy before a run counts as blowing up
KE_FACTOR = 1.5


# ---- scenes --------------------------------------------------------------------------------------
ELASTIC_PARAMS = {
    "fixed_corotated": {},
    "hencky_von_mises": {"yield_stress": 1e9},             # elastic range only: the Hencky elastic part
    "hencky_drucker_prager": {"friction_angle": 30.0},
    "drucker_prager_jaumann": {"friction_angle": 30.0},
    # fluids (--full): the same bulk modulus K = E / (3 (1 - 2 nu)) as the solids
    "weakly_compressible": {},
    "newtonian_fluid": {},
}


def _law_params(law: str, E: float, nu: float) -> dict:
    p = dict(ELASTIC_PARAMS.get(law, {}))
    K = E / (3.0 * (1.0 - 2.0 * nu))
    if law == "drucker_prager_jaumann":
        p.update(bulk_modulus=K, nu=nu)
    elif law == "weakly_compressible":
        p.update(bulk_modulus=K)
    elif law == "newtonian_fluid":
        p.update(sound_speed=float(np.sqrt(K / 1000.0)))      # cube_scene's density 1000 kg/m^3
    else:
        p.update(E=E, nu=nu)
    return p


def bar_scene(law: str = "fixed_corotated", cells: int = 20):
    """Verification #1a/1c: fixed-free bar in its first mode (E 100, rho 1, nu 0, v0 0.1), 2D strip."""
    from mpmlab.scenes.validation import vibrating_bar

    sc = vibrating_bar(dim=2, cells=cells, cfl=0.3)
    b = sc.bodies[0]
    b.material, b.params = law, _law_params(law, 100.0, 0.0)
    sc.dt_every = 0
    return sc


def cube_scene(law: str = "fixed_corotated", E: float = 1e4, nu: float = 0.3, velocity=(1.0, -2.0), spin=2.0,
               walls: str = "slip", dx: float = 0.05, density: float = 1000.0, name="falling_cube", **kw):
    """A 0.3 m elastic square thrown at a slip floor in a 1 m box (2D, 4 particles per cell)."""
    import mpmlab

    body = mpmlab.Body(shape={"kind": "box", "lo": [0.35, 0.4], "hi": [0.65, 0.7]}, material=law,
                       params=_law_params(law, E, nu) if law in ELASTIC_PARAMS else kw.pop("params", {}),
                       density=density, particles_per_cell=4, velocity=list(velocity), angular_velocity=spin,
                       name="cube")
    bnd = kw.pop("boundaries", None)
    if bnd is None:
        bnd = [mpmlab.boundaries.Walls(default=walls, thickness=2)] if walls != "none" else []
    return mpmlab.Scene(dim=2, dx=dx, domain=([0.0, 0.0], [1.0, 1.0]), bodies=[body] + kw.pop("extra", []),
                        gravity=[0.0, -9.8], boundaries=bnd, name=name, **kw)


def available_energy(scene, P) -> float:
    """Initial kinetic energy + the largest work gravity can do over the domain height [J]."""
    k0 = 0.5 * float(np.sum(P.mass * np.sum(P.v ** 2, axis=1)))
    H = float(scene.domain[1][1] - scene.domain[0][1])
    return k0 + float(np.sum(P.mass)) * float(np.linalg.norm(scene.gravity)) * H


def kinetic(traj) -> np.ndarray:
    return 0.5 * np.einsum("n,tnd->t", traj.mass, traj.v ** 2)


# ---- one run, classified ---------------------------------------------------------------------------
def run_case(scene_fn, backend: str, transfer: str, steps: int, every: int = 10, dt_C: float | None = None,
             precision: str = "fp32", stepper_cache: dict | None = None, key=None) -> dict:
    """Build and run; never raises. ``dt_C``: fixed dt at this CFL number (runtime dt, no recompile)."""
    import mpmlab
    from mpmlab.core.errors import ConfigError, SimulationDiverged

    t0 = time.perf_counter()
    out = {"backend": backend, "transfer": transfer, "steps": steps}
    try:
        st = stepper_cache.get(key) if stepper_cache is not None else None
        if st is None:
            scene = scene_fn()
            st = mpmlab.build_stepper(scene, backend, transfer, precision, check_every=every)
            if stepper_cache is not None:
                stepper_cache[key] = st
        scene, P = st.scene, st.particles
        vmax = float(np.max(np.linalg.norm(P.v, axis=1), initial=0.0))
        if dt_C is not None:
            st._set_dt(dt_C * scene.dx / (scene.wave_speed() + vmax))   # runtime dt: one compile per stepper
        out["dt0"] = st.dt
        e_avail = available_energy(scene, P)
        try:
            traj = st.rollout(steps=steps, every=every)
        finally:
            if dt_C is not None:
                st._set_dt(None)
        ke = kinetic(traj)
        out["ke_ratio"] = float(np.max(ke) / e_avail) if e_avail > 0 else None
        out["t_end"] = float(traj.time[-1])
        if not (np.all(np.isfinite(traj.x)) and np.all(np.isfinite(traj.v))):
            out.update(outcome="BAD", message="NaN/Inf in a returned trajectory")
        elif out["ke_ratio"] is not None and out["ke_ratio"] > KE_FACTOR:
            out.update(outcome="energy_blowup", message=f"kinetic energy reached {out['ke_ratio']:.3g} x the available energy")
        else:
            out["outcome"] = "ok"
    except SimulationDiverged as e:
        tr = e.trajectory
        finite = tr is None or (np.all(np.isfinite(tr.x)) and np.all(np.isfinite(tr.v)))
        named = e.step >= 0 and bool(e.field) and f"step {e.step}" in str(e)
        out.update(outcome="diverged" if (finite and named) else "BAD", step=e.step, particle=e.particle,
                   field=e.field, message=str(e).split(";")[0])
    except ConfigError as e:
        out.update(outcome="config_error", message=str(e))
    except Exception as e:  # anything else is a bug the suite must show
        out.update(outcome="BAD", message=f"{type(e).__name__}: {e}", traceback=traceback.format_exc(limit=3))
    out["wall_s"] = round(time.perf_counter() - t0, 3)
    return out


# ---- (a) C* sweep ---------------------------------------------------------------------------------
def c_star(scene_fn, backend, transfer, horizon) -> dict:
    cache: dict = {}
    runs = {}

    def stable(C):
        r = run_case(scene_fn, backend, transfer, horizon, dt_C=C, stepper_cache=cache, key=0)
        runs[round(C, 5)] = r["outcome"] + (f"@{r.get('step')}:{r.get('field')}" if r["outcome"] == "diverged" else "")
        if r["outcome"] in ("BAD", "config_error"):
            raise RuntimeError(f"sweep run failed: {r.get('message')}")
        return r["outcome"] == "ok"

    t0 = time.perf_counter()
    if stable(C_HI):
        res = {"c_star": C_HI, "bracket": [C_HI, None], "note": f"stable at the top of the range ({C_HI})"}
    elif not stable(C_LO):
        res = {"c_star": None, "bracket": [None, C_LO], "note": f"unstable even at C = {C_LO}"}
    else:
        lo, hi = C_LO, C_HI
        for _ in range(HALVINGS):
            mid = math.sqrt(lo * hi)
            lo, hi = (mid, hi) if stable(mid) else (lo, mid)
        res = {"c_star": round(lo, 4), "bracket": [round(lo, 4), round(hi, 4)]}
    res["runs"] = runs
    res["wall_s"] = round(time.perf_counter() - t0, 2)
    return res


def sweep(backends, laws_by_scene, horizon) -> list[dict]:
    rows = []
    for scene_name, laws in laws_by_scene.items():
        for law in laws:
            fn = (lambda law=law: bar_scene(law)) if scene_name == "vibrating_bar" else (lambda law=law: cube_scene(law, dt_every=0))
            for backend in backends:
                for tr in TRANSFERS:
                    r = c_star(fn, backend, tr, horizon)
                    r.update(scene=scene_name, law=law, backend=backend, transfer=tr, horizon=horizon)
                    rows.append(r)
                    log(f"  C* {scene_name:14s} {law:22s} {backend:4s} {tr:4s}: {r['c_star']} "
                        f"(bracket {r['bracket']}, {r['wall_s']:.1f} s)")
    return rows


# ---- (a') why drucker_prager_jaumann had C* = 0.2 (issue 17 item 3) --------------------------------
DPJ_STUDY = HERE / "results" / "stress_dpj_study.json"
DPJ_C = (0.2, 0.3, 0.5, 1.0)


def _cone(sig, prm):
    """(sigma_m, tau, f_s, f_t) per particle (A.3-A.6; tr/D in 2D as the law)."""
    from mpmlab.laws.drucker_prager_jaumann import reference as R

    d = sig.shape[-1]
    sm = np.trace(sig, axis1=-2, axis2=-1) / d
    dev = sig - sm[..., None, None] * np.eye(d)
    tau = np.sqrt(0.5 * np.sum(dev * dev, axis=(-2, -1)))
    q, k, _ = R.cone_constants(prm["friction_angle"], prm["dilation_angle"], prm["cohesion"])
    return sm, tau, tau - k + q * sm, sm - prm["tensile_strength"]


def dpj_study(backend: str = "jax", transfer: str = "apic", steps: int = 1000) -> dict:
    """The thrown granular square (the sweep's falling_cube, drucker_prager_jaumann) at fixed C, fp64:
    outcome, the largest J reached, the diverging particle's J and its local CFL number C sqrt(J) (the
    wave speed of a hypo-elastic law integrated on the Cauchy stress at dilation J is sqrt(J) c_p), how
    many particles sit outside the cone in free flight (steps 1-40, before the impact), and the law's
    Kirchhoff stiffness |d(J sigma)| / |C:dd| for a particle held at J (1 for a law whose grid stiffness
    does not depend on J). Runs on whatever law the tree has: run it on two commits for before/after."""
    import mpmlab
    from mpmlab.core.errors import SimulationDiverged
    from mpmlab.laws.drucker_prager_jaumann import reference as R
    from mpmlab.core import registry

    law = registry.laws.get("drucker_prager_jaumann")
    rows = []
    for C in DPJ_C:
        sc = cube_scene("drucker_prager_jaumann", dt_every=0)
        prm = law.resolve_params(sc.bodies[0].params, "study", density=sc.bodies[0].density)
        st = mpmlab.build_stepper(sc, backend, transfer, "fp64", check_every=10)
        P = st.particles
        vmax = float(np.max(np.linalg.norm(P.v, axis=1)))
        st._set_dt(C * sc.dx / (sc.wave_speed() + vmax))
        r = {"C": C, "backend": backend, "transfer": transfer, "steps": steps}
        try:
            traj = st.rollout(steps=steps, every=1, fields=("J", "sigma"))
            r["outcome"] = "ok"
        except SimulationDiverged as e:
            traj = e.trajectory
            r.update(outcome="diverged", step=int(e.step), particle=int(e.particle), field=e.field)
        J, sig, x = traj.fields["J"], traj.fields["sigma"], traj.x
        T = len(J)
        pre = T if r["outcome"] == "ok" else max(1, T - 10)     # frames before the blow-up (J <= 0 is seen up to 10 steps late)
        r["J_max"], r["J_min"] = float(np.max(J[:pre])), float(np.min(J[:pre]))
        sm, tau, fs, ft = _cone(sig, prm)
        # free flight: the frames before the impact (the first frame with min J < 0.99)
        hit = np.nonzero(np.min(J, axis=1) < 0.99)[0]
        t_imp = int(hit[0]) if len(hit) else T
        r["impact_step"] = t_imp
        scale = max(float(np.max(np.abs(sig[:t_imp]))), 1.0)
        r["free_flight_outside_cone"] = float(np.mean(fs[1:t_imp] > 1e-9 * scale)) if t_imp > 1 else 0.0
        r["free_flight_max_fs"] = float(np.max(fs[1:t_imp])) if t_imp > 1 else 0.0
        # the largest local CFL C sqrt(J) of a particle in compression (sigma_m < 0): over the whole run, or
        # over the 10 frames before that window
        w0 = 0 if r["outcome"] == "ok" else max(0, pre - 10)
        loc = np.where(sm[w0:pre] < 0.0, J[w0:pre], 0.0)
        r["max_local_cfl_in_compression"] = float(C * math.sqrt(max(float(np.max(loc)), 0.0)))
        if r["outcome"] == "diverged" and r.get("particle", -1) >= 0:
            p = r["particle"]
            r["particle_J"] = float(np.max(J[w0:pre, p]))
            r["neighbours_within_dx"] = int(np.sum(np.linalg.norm(x[pre - 1] - x[pre - 1, p], axis=1) < sc.dx)) - 1
        rows.append(r)
        log(f"  [dpj study] C={C}: {r['outcome']}{'@' + str(r.get('step')) if r['outcome'] != 'ok' else ''} "
            f"J_max {r['J_max']:.3g} outside cone in free flight {100 * r['free_flight_outside_cone']:.0f} %")
    # law-level: Kirchhoff stiffness of a particle held at J (NumPy reference, uniaxial compression dd)
    prm = {"bulk_modulus": 1e6, "nu": 0.3, "friction_angle": 30.0, "dilation_angle": 0.0, "cohesion": 1e6,
           "tensile_strength": 0.0}
    G, lam = R.moduli(1e6, 0.3)
    L, dt = np.diag([-1.0, 0.0]), 1e-5
    want = lam * np.trace(L * dt) * np.eye(2) + 2 * G * L * dt
    stiff = {}
    for Jp in (1.0, 10.0, 100.0):
        n = R.update({"J": Jp, "sigma": np.zeros((2, 2)), "eps_p": 0.0}, L, dt, prm)
        stiff[str(Jp)] = float(np.linalg.norm(n["J"] * n["sigma"]) / np.linalg.norm(want))
    return {"rows": rows, "kirchhoff_stiffness_ratio": stiff}


def render_dpj(study: dict) -> str:
    if not study:
        return ""
    L = ["### Why `drucker_prager_jaumann` had C* = 0.2 (issue 17 item 3)\n",
         "`python benchmarks/stress.py --parts dpj_study [--study-label NAME]` (`results/stress_dpj_study.json`; "
         "run it on two commits for before/after). Thrown granular square (the sweep's `falling_cube`: "
         "cohesionless, phi 30 deg, c_p 3.67 m/s, spin 2 rad/s), APIC, JAX, fp64, fixed C, 1000 steps. "
         "*J max* and the diverging particle's J: more than 10 steps before the failure; *local CFL* = the largest "
         "C sqrt(J) of a particle in compression (sigma_m < 0) over the run, or over steps 20-10 before the "
         "failure (the wave speed of a hypo-elastic law integrated on the Cauchy stress at dilation J is "
         "sqrt(J) c_p, since the grid force uses J sigma); *outside cone* = share of particle-steps with "
         "f_s > 0 in free flight (before the impact, the first step with min J < 0.99; cohesionless: the stress "
         "must be 0 there); *K_tau(J)* = |d(J sigma)| / |C:dd| for a particle held at J (the grid stiffness per "
         "unit mass relative to J = 1).\n"]
    L += H.md_table(["code", "C", "outcome", "J max", "diverging particle: J max, neighbours < dx",
                     "local CFL C sqrt(J), sigma_m < 0", "outside cone (free flight)", "K_tau(J = 10, 100)"])
    for label, run in study.items():
        if label.startswith("_"):
            continue
        k = run.get("kirchhoff_stiffness_ratio", {})
        for r in run["rows"]:
            part = (f"{r['particle_J']:.3g}, {r['neighbours_within_dx']}" if "particle_J" in r else "")
            L.append(H.md_row([label, r["C"], r["outcome"] + (f"@{r['step']}" if r["outcome"] != "ok" else ""),
                               f"{r['J_max']:.3g}", part, f"{r['max_local_cfl_in_compression']:.2f}",
                               f"{100 * r['free_flight_outside_cone']:.0f} % (max f_s {r['free_flight_max_fs']:.3g} Pa)",
                               f"{k.get('10.0', float('nan')):.3g}, {k.get('100.0', float('nan')):.3g}"]))
    abl = study.get("_ablation")
    if abl:
        L.append("\n" + abl["note"] + "\n")
        L += H.md_table(["variant", *[f"C = {c}" for c in abl["C"]]])
        for name, outs in abl["rows"].items():
            L.append(H.md_row([name, *outs]))
    notes = study.get("_notes")
    if notes:
        L.append("\n" + notes + "\n")
    return "\n".join(L) + "\n"


# ---- (b) stress cases -----------------------------------------------------------------------------
def stress_cases():
    """(name, what, scene builder, transfer, steps). Built lazily so a ConfigError is an outcome."""
    import mpmlab
    from mpmlab.boundaries import BoxObstacle, Walls

    def water_pool():
        pool = mpmlab.Body(shape={"kind": "box", "lo": [0.1, 0.1], "hi": [0.9, 0.3]}, material="weakly_compressible",
                           params={"bulk_modulus": 2e4}, density=1000.0, particles_per_cell=4, name="pool")
        return cube_scene(velocity=(0.0, -8.0), spin=0.0, E=1e5, extra=[pool], name="cube_into_pool")

    def sand_on_jelly():
        sand = mpmlab.Body(shape={"kind": "box", "lo": [0.3, 0.1], "hi": [0.7, 0.25]}, material="hencky_drucker_prager",
                           params={"E": 2e4, "nu": 0.3, "friction_angle": 30.0}, density=1500.0,
                           particles_per_cell=4, velocity=[0.0, 0.0], name="sand")
        return cube_scene(velocity=(0.0, -15.0), spin=0.0, E=3e4, extra=[sand], name="cube_onto_sand")

    return [
        ("extreme_velocity_wall", "|v| = 200 m/s into a slip wall", lambda: cube_scene(velocity=(200.0, 0.0)), "apic", 400),
        ("extreme_velocity_sticky", "|v| = 100 m/s into sticky walls", lambda: cube_scene(velocity=(0.0, -100.0), walls="sticky"), "apic", 400),
        ("extreme_velocity_open", "|v| = 100 m/s, no walls (leaves the domain)", lambda: cube_scene(velocity=(100.0, 0.0), walls="none"), "apic", 400),
        ("wall_impact_separate", "50 m/s onto separating walls, PIC", lambda: cube_scene(velocity=(0.0, -50.0), walls="separate"), "pic", 400),
        ("wall_impact_flip", "50 m/s onto slip walls, FLIP", lambda: cube_scene(velocity=(0.0, -50.0)), "flip", 400),
        ("obstacle_impact", "20 m/s into a rigid box obstacle", lambda: cube_scene(
            velocity=(0.0, -20.0), boundaries=[Walls(default="slip", thickness=2), BoxObstacle(lo=[0.4, 0.15], hi=[0.6, 0.3])]),
         "apic", 400),
        ("nu_0.45", "nu = 0.45", lambda: cube_scene(nu=0.45), "apic", 400),
        ("nu_0.49", "nu = 0.49 (c_p 4.1x sqrt(E/rho))", lambda: cube_scene(nu=0.49), "apic", 400),
        ("nu_0.499", "nu = 0.499", lambda: cube_scene(nu=0.499), "apic", 400),
        ("nu_0.49_mls", "nu = 0.49, MLS", lambda: cube_scene(nu=0.49), "mls", 400),
        ("very_soft", "E = 10 Pa (collapses under gravity)", lambda: cube_scene(E=10.0, velocity=(0.0, 0.0), spin=0.0), "apic", 400),
        ("very_soft_hencky", "E = 10 Pa, Hencky", lambda: cube_scene(law="hencky_von_mises", E=10.0, velocity=(0.0, 0.0), spin=0.0), "apic", 400),
        ("very_stiff", "E = 1e10 Pa", lambda: cube_scene(E=1e10), "apic", 400),
        ("very_stiff_flip", "E = 1e10 Pa, FLIP", lambda: cube_scene(E=1e10), "flip", 400),
        ("multi_material_pool", "stiff cube at 8 m/s into a water pool", water_pool, "apic", 400),
        ("multi_material_sand", "cube at 15 m/s onto a sand layer", sand_on_jelly, "flip", 400),
        # no spin: the CFL number counts the largest particle speed, which a spin would raise above 50 m/s
        ("fixed_dt_at_cfl_limit", "fixed dt at C = cfl_limit (0.5), 50 m/s impact, dt_every n/a", lambda: cube_scene(
            velocity=(0.0, -50.0), spin=0.0, dt=0.5 * 0.05 / (cube_scene().wave_speed() + 50.0 * 1.0001)), "apic", 400),
        ("fixed_dt_above_limit", "fixed dt at C = 2 (refused)", lambda: cube_scene(dt=2.0 * 0.05 / 5.0), "apic", 10),
        ("invalid_nu", "nu = 0.5 (refused)", lambda: cube_scene(nu=0.5), "apic", 10),
        ("auto_once_speedup", "dt auto computed once (dt_every 0), body at rest then 100 m/s into the floor "
         "(gravity 2000 m/s^2)", lambda: _speedup(0), "apic", 400),
        ("auto_cadence_speedup", "as above with the default cadence", lambda: _speedup(None), "apic", 400),
    ]


def _speedup(dt_every):
    """A body starting at rest in strong gravity: its speed grows from 0 to ~60 m/s, so a dt computed
    once from the initial speed is too large later; the cadence follows it."""
    kw = {} if dt_every is None else {"dt_every": dt_every}
    sc = cube_scene(E=1e4, velocity=(0.0, 0.0), spin=0.0, walls="slip", name="speedup", **kw)
    sc.gravity = np.array([0.0, -2000.0])
    sc.cfl = 0.5
    return sc


def cases(backends, steps_scale=1.0) -> list[dict]:
    rows = []
    for name, what, fn, tr, steps in stress_cases():
        for backend in backends:
            n = max(10, int(steps * steps_scale))
            r = run_case(fn, backend, tr, n)
            r.update(case=name, what=what)
            rows.append(r)
            detail = r.get("message", "")
            log(f"  case {name:26s} {backend:4s} {tr:4s}: {r['outcome']:12s} {detail[:110]}")
    return rows


# ---- (c) long run -----------------------------------------------------------------------------------
def long_run(backends, steps, transfers=("pic", "apic", "flip")) -> list[dict]:
    import mpmlab
    from mpmlab.io.metrics import compute_metrics

    rows = []
    for backend in backends:
        for tr in transfers:
            body = mpmlab.Body(shape={"kind": "sphere", "center": [0.5, 0.5], "radius": 0.12}, material="fixed_corotated",
                               params={"E": 1e5, "nu": 0.3}, density=1000.0, particles_per_cell=4, angular_velocity=2.0)
            sc = mpmlab.Scene(dim=2, dx=0.05, domain=([0.0, 0.0], [1.0, 1.0]), bodies=[body], gravity=[0.0, 0.0],
                              name="spinning_disc")
            st = mpmlab.build_stepper(sc, backend, tr, "fp32", check_every=1000)
            t0 = time.perf_counter()
            every = 100
            r = {"backend": backend, "transfer": tr, "steps": steps, "particles": int(st.particles.count)}
            try:
                traj = st.rollout(steps=steps, every=every, fields=("F",))
                m = compute_metrics(traj)
                ke = m["kinetic_energy"]
                el = m.get("elastic_energy", np.zeros_like(ke))
                tot = ke + el
                dke = np.diff(ke) / ke[0]
                dtot = np.diff(tot) / tot[0]
                r.update(outcome="ok", ke0=float(ke[0]), ke_end=float(ke[-1]), ke_max_over_ke0=float(ke.max() / ke[0]),
                         max_ke_rise_per_frame=float(dke.max()), max_total_rise_per_frame=float(dtot.max()),
                         frames_with_ke_rise_gt_1e_6_per_step=int(np.sum(dke > 1e-6 * every)),
                         total_max_over_total0=float(tot.max() / tot[0]), t_end=float(traj.time[-1]),
                         finite=bool(np.isfinite(traj.x).all()))
            except Exception as e:
                r.update(outcome=type(e).__name__, message=str(e)[:200])
            r["wall_s"] = round(time.perf_counter() - t0, 1)
            rows.append(r)
            log(f"  long {backend:4s} {tr:4s} {steps} steps: {r['outcome']} KE_max/KE0 {r.get('ke_max_over_ke0', float('nan')):.6f} "
                f"max KE rise/frame {r.get('max_ke_rise_per_frame', float('nan')):.2e} "
                f"max (KE+elastic) rise/frame {r.get('max_total_rise_per_frame', float('nan')):.2e} ({r['wall_s']} s)")
    return rows


# ---- (d) random scenes ------------------------------------------------------------------------------
def random_scene(rng):
    """A small random 2D scene: random registered law, parameters in range, boundary, velocity, transfer."""
    import mpmlab
    from mpmlab.core import registry

    law = str(rng.choice(registry.laws.names()))
    E = float(10 ** rng.uniform(1, 9))
    nu = float(rng.uniform(-0.5, 0.499))
    prm = {
        "fixed_corotated": {"E": E, "nu": nu},
        "hencky_von_mises": {"E": E, "nu": nu, "yield_stress": float(10 ** rng.uniform(0, 6))},
        "hencky_drucker_prager": {"E": E, "nu": nu, "friction_angle": float(rng.uniform(5, 45))},
        "drucker_prager_jaumann": {"bulk_modulus": E, "nu": max(nu, 0.0), "friction_angle": float(rng.uniform(5, 45))},
        "weakly_compressible": {"bulk_modulus": E},
        "newtonian_fluid": {"sound_speed": float(10 ** rng.uniform(0, 2.5)), "viscosity": float(10 ** rng.uniform(-4, 0))},
    }.get(law, {})
    v = (rng.uniform(-1, 1, 2) * 10 ** rng.uniform(-1, 2)).tolist()
    walls = str(rng.choice(["slip", "sticky", "separate", "none"]))
    dt = "auto" if rng.uniform() < 0.7 else float(rng.uniform(1e-5, 1e-3))
    body = mpmlab.Body(shape={"kind": "box", "lo": [0.35, 0.35], "hi": [0.65, 0.65]}, material=law, params=prm,
                       density=float(10 ** rng.uniform(2, 4)), particles_per_cell=4, velocity=v,
                       angular_velocity=float(rng.uniform(-5, 5)))
    bnd = [mpmlab.boundaries.Walls(default=walls, thickness=2)] if walls != "none" else []
    desc = f"{law} {prm} v={np.round(v, 2).tolist()} walls={walls} dt={dt}"
    sc = mpmlab.Scene(dim=2, dx=0.05, domain=([0.0, 0.0], [1.0, 1.0]), bodies=[body], gravity=[0.0, -9.8],
                      boundaries=bnd, dt=dt, name="random")
    return sc, desc


def random_scenes(backends, n, steps, seed=0) -> list[dict]:
    rng = np.random.default_rng(seed)
    rows = []
    for i in range(n):
        state = rng.bit_generator.state
        tr = str(rng.choice(TRANSFERS))
        for backend in backends:
            rng.bit_generator.state = state
            rng.choice(TRANSFERS)
            holder = {}

            def fn():
                sc, holder["desc"] = random_scene(rng)
                return sc
            r = run_case(fn, backend, tr, steps)
            r.update(case=f"random_{i}", what=holder.get("desc", ""))
            rows.append(r)
            log(f"  random {i:2d} {backend:4s} {tr:4s}: {r['outcome']:12s} {holder.get('desc', '')[:90]} {r.get('message', '')[:60]}")
    return rows


# ---- report -------------------------------------------------------------------------------------------
def render(res: dict) -> str:
    L = []
    meta = res["meta"]
    L.append(f"Measured by `python benchmarks/stress.py{meta['argv']}` on {meta['machine']['cpu']} "
             f"({meta['machine']['cores']} cores), fp32, {meta['wall_s']:.0f} s in all. Raw numbers: "
             "`benchmarks/results/stress.json`.\n")
    kept = meta.get("kept_from_previous_run")
    if kept:
        L.append(f"Parts {', '.join(kept['parts'])} are from the previous run (`python benchmarks/stress.py"
                 f"{kept.get('argv') or ''}`, {kept.get('wall_s') or 0:.0f} s); this run redid the others.\n")
    rk = meta.get("sweep_rows_kept_from_previous_run")
    if rk:
        L.append(f"Sweep rows of {', '.join(f'`{l}`' for l in rk['laws'])} are from the previous run (`python "
                 f"benchmarks/stress.py{rk.get('argv') or ''}`, horizon {rk.get('horizon')}); this run redid the "
                 "other laws' rows (`--laws`).\n")
    if res.get("sweep"):
        L.append("### Largest stable CFL factor C*\n")
        L.append(f"dt = C dx / (c_p + |v|max(t=0)), fixed for the run. **Stable** = no `SimulationDiverged` "
                 f"(guards every 10 steps) over {res['sweep'][0]['horizon']} steps **and** kinetic energy "
                 f"<= {KE_FACTOR} x (initial kinetic + gravity's work over the domain height). C* = largest C "
                 f"found stable by bisection in log C over [{C_LO}, {C_HI}] ({HALVINGS} halvings); the first "
                 "unstable C above it is in the JSON (`bracket`). Scenes: `vibrating_bar` = verification #1a "
                 "as a 2D strip (20 cells, 4 particles/cell, nu 0), `falling_cube` = 0.3 m square, E 1e4, "
                 "nu 0.3, thrown at (1, -2) m/s with spin 2 rad/s onto slip walls (4 particles/cell).\n")
        backends = sorted({r["backend"] for r in res["sweep"]})
        L += H.md_table(["scene", "law", "backend", *TRANSFERS])
        keys = sorted({(r["scene"], r["law"]) for r in res["sweep"]})
        for sc, law in keys:
            for b in backends:
                cells = []
                for tr in TRANSFERS:
                    r = next((r for r in res["sweep"] if (r["scene"], r["law"], r["backend"], r["transfer"]) == (sc, law, b, tr)), None)
                    cells.append("–" if r is None else (f"<{C_LO}" if r["c_star"] is None else
                                 (f">={C_HI}" if r["bracket"][1] is None else f"{r['c_star']:.3g}")))
                L.append(H.md_row([sc, law, b, *cells]))
        from mpmlab.core import registry

        cfl = res["meta"]["default_cfl"]
        lines = []
        for law in sorted({r["law"] for r in res["sweep"]}):
            cs = [r["c_star"] for r in res["sweep"] if r["law"] == law and r["c_star"] is not None]
            declared = getattr(registry.laws.get(law), "stable_cfl", None)
            eff = min([cfl] + ([0.5 * declared] if declared is not None else []))
            ok = bool(cs) and eff <= 0.5 * min(cs) + 1e-9
            lines.append(f"`{law}` C*min {min(cs):.3g} -> dt: auto C = {eff:.3g}"
                         + (f" (declared stable_cfl {declared})" if declared is not None else "")
                         + ("" if ok else " **above C*min / 2**"))
        L.append("\nSafety factor of `dt: auto` (rule: C <= C*min / 2, `mpmlab/core/scene.py`; a law with a low "
                 "C* declares `stable_cfl`): " + "; ".join(lines) + ".\n")
    if res.get("cases"):
        L.append("### Stress cases\n")
        L.append("Library defaults (`dt: auto`, recomputed every `dt_every` steps) unless the case says otherwise; "
                 "fp32. `ok` = finite trajectory with bounded kinetic energy; `diverged` = `SimulationDiverged` "
                 "naming step, particle and field; `config_error` = refused before running. `BAD` would be a "
                 "NaN trajectory returned as fine, or any other exception.\n")
        L += H.md_table(["case", "what", "transfer", "backend", "outcome", "steps", "dt(0) [s]", "t_end [s]",
                         "max KE / available", "detail"])
        for r in res["cases"]:
            det = (f"step {r['step']}, particle {r['particle']}, field {r['field']}" if r["outcome"] == "diverged"
                   else r.get("message", "")).replace("|", "/")
            L.append(f"| {r['case']} | {r['what']} | {r['transfer']} | {r['backend']} | {r['outcome']} | {r['steps']} | "
                     f"{r.get('dt0', float('nan')):.3g} | {r.get('t_end', float('nan')):.3g} | "
                     f"{r.get('ke_ratio') if r.get('ke_ratio') is None else format(r['ke_ratio'], '.3g')} | {det[:160]} |")
        bad = [r for r in res["cases"] if r["outcome"] == "BAD"]
        L.append(f"\nBAD outcomes: **{len(bad)}**.\n")
    if res.get("random"):
        rr = res["random"]
        counts = {}
        for r in rr:
            counts[r["outcome"]] = counts.get(r["outcome"], 0) + 1
        L.append("### Random scenes\n")
        L.append(f"{len(rr)} runs ({len(rr) // max(1, len(res['meta']['backends']))} random 2D scenes x backends, "
                 f"{rr[0]['steps']} steps each; random law, parameters, density, velocity up to 100 m/s, spin, walls, "
                 f"transfer, dt auto or fixed): " + ", ".join(f"{k}: {v}" for k, v in sorted(counts.items())) + ".\n")
    if res.get("long"):
        L.append("### Long runs (energy)\n")
        L.append("Spinning elastic disc (r 0.12 m, E 1e5, omega 2 rad/s, no gravity, no walls), `dt: auto` "
                 "with the default cadence; energies every 100 steps. No external work is done, so kinetic "
                 "energy must not rise for PIC/APIC (verification #5b).\n")
        L += H.md_table(["backend", "transfer", "steps", "t_end [s]", "KE_end / KE0", "max KE / KE0",
                         "max KE rise per 100 steps (rel. KE0)", "max (KE+elastic) rise per 100 steps", "outcome"])
        for r in res["long"]:
            if r["outcome"] != "ok":
                L.append(f"| {r['backend']} | {r['transfer']} | {r['steps']} | | | | | | {r['outcome']}: {r.get('message', '')} |")
                continue
            L.append(f"| {r['backend']} | {r['transfer']} | {r['steps']} | {r['t_end']:.1f} | {r['ke_end'] / r['ke0']:.4g} | "
                     f"{r['ke_max_over_ke0']:.6f} | {r['max_ke_rise_per_frame']:.2e} | {r['max_total_rise_per_frame']:.2e} | ok |")
        L.append("")
    return "\n".join(L) + "\n"


def _head() -> str:
    import subprocess

    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=HERE, capture_output=True, text=True,
                              check=True).stdout.strip() or "unknown"
    except Exception:
        return "unknown"


def main(argv=None):
    ap = H.parser(__doc__.split("\n")[0])
    H.add_quick(ap, "smoke-sized: short horizons, fewer cases and scenes")
    ap.add_argument("--full", action="store_true", help="every registered law (solids and fluids) in the sweep, 1000-step horizon")
    H.add_backends(ap)
    ap.add_argument("--parts", default="sweep,cases,random,long")
    ap.add_argument("--long-steps", type=int, default=None, help="long-run steps (default 100000; --quick 5000)")
    ap.add_argument("--random", type=int, default=None, help="random scenes (default 12; --quick 4)")
    ap.add_argument("--no-write", action="store_true", help="print only; leave results and README alone")
    ap.add_argument("--laws", default=None,
                    help="comma list: sweep only these laws (of the chosen scene sets); the other laws' sweep rows "
                         "are kept from the previous results/stress.json")
    ap.add_argument("--no-readme", action="store_true", help="write results/stress.json and stress.md only")
    ap.add_argument("--render-only", action="store_true",
                    help="rewrite stress.md (and, without --no-readme, the README section) from results/stress.json and "
                         "results/stress_dpj_study.json; run nothing")
    ap.add_argument("--study-label", default=None,
                    help="dpj_study: the row label in results/stress_dpj_study.json (default: git HEAD's short hash)")
    a = ap.parse_args(argv)
    if a.render_only:
        res = H.read_json(H.RESULTS / "stress.json")
        md = render(res) + "\n" + render_dpj(H.read_json(DPJ_STUDY, {}) or {})
        (HERE / "stress.md").write_text("# Stability stress suite\n\n" + (__doc__.split("\n\n", 2)[2]) + "\n" + md)
        if not a.no_readme:
            write_readme_section(HERE / "README.md", "stress", "Stability stress suite (benchmarks/stress.py)",
                                 "`python benchmarks/stress.py` (`--quick`, `--full`, `--backends`, `--parts`); full "
                                 "tables in [stress.md](stress.md).\n\n" + render(res))
        log(f"[stress] rewrote {HERE / 'stress.md'}" + ("" if a.no_readme else " and the README section")
            + f" from {H.RESULTS / 'stress.json'} and {DPJ_STUDY}")
        return res
    backends = H.csv(a.backends)
    parts = set(a.parts.split(","))
    horizon = 150 if a.quick else (1000 if a.full else 500)
    laws = {"vibrating_bar": ["fixed_corotated"], "falling_cube": ["fixed_corotated", "hencky_von_mises"]}
    if a.full:
        laws = {"vibrating_bar": ["fixed_corotated", "hencky_von_mises"],
                "falling_cube": ["fixed_corotated", "hencky_von_mises", "hencky_drucker_prager", "drucker_prager_jaumann",
                                 "weakly_compressible", "newtonian_fluid"]}
    elif a.quick:
        laws = {"vibrating_bar": ["fixed_corotated"], "falling_cube": ["fixed_corotated"]}
    only = set(H.csv(a.laws)) if a.laws else None
    if only:
        laws = {sc: [l for l in ls if l in only] for sc, ls in laws.items()}
        laws = {sc: ls for sc, ls in laws.items() if ls}
        if not laws:
            ap.error(f"--laws {a.laws}: none of these is in the sweep's scene sets (use --full for every law)")
    import mpmlab
    from mpmlab.core.scene import Scene

    t0 = time.perf_counter()
    res = {"meta": {"argv": (" " + " ".join(argv if argv is not None else sys.argv[1:])).rstrip(),
                    "machine": machine_info(), "backends": backends, "horizon": horizon,
                    "default_cfl": Scene.__dataclass_fields__["cfl"].default,
                    "default_dt_every": Scene.__dataclass_fields__["dt_every"].default,
                    "ke_factor": KE_FACTOR, "c_range": [C_LO, C_HI], "halvings": HALVINGS}}
    if "sweep" in parts:
        log(f"[stress] C* sweep: horizon {horizon} steps, {sum(map(len, laws.values()))} scene/law pairs x "
            f"{len(backends)} backends x {len(TRANSFERS)} transfers")
        res["sweep"] = sweep(backends, laws, horizon)
    if "dpj_study" in parts:
        log("[stress] drucker_prager_jaumann study (issue 17 item 3)")
        label = a.study_label or _head()
        study = H.read_json(DPJ_STUDY, {}) or {}
        study[label] = dpj_study()
        if not a.no_write:
            H.write_json(DPJ_STUDY, study, default=float)
    if "cases" in parts:
        log("[stress] stress cases")
        res["cases"] = cases(backends, 0.25 if a.quick else 1.0)
    if "random" in parts:
        n = a.random if a.random is not None else (4 if a.quick else 12)
        log(f"[stress] {n} random scenes")
        res["random"] = random_scenes(backends, n, 60 if a.quick else 200)
    if "long" in parts:
        steps = a.long_steps or (5000 if a.quick else 100_000)
        log(f"[stress] long runs, {steps} steps")
        res["long"] = long_run(backends, steps)
    res["meta"]["wall_s"] = time.perf_counter() - t0
    prev_path = H.RESULTS / "stress.json"
    if not a.no_write and prev_path.exists():
        # a partial run (--parts) keeps the other parts of the last full run, and says which came from where
        prev = json.loads(prev_path.read_text())
        if only and "sweep" in res and prev.get("sweep"):
            res["sweep"] = H.keep_rows(prev["sweep"], res["sweep"], lambda r: r["law"] not in only)
            res["meta"]["sweep_rows_kept_from_previous_run"] = {
                "laws": sorted({r["law"] for r in prev["sweep"] if r["law"] not in only}),
                "argv": prev.get("meta", {}).get("argv"), "horizon": prev.get("meta", {}).get("horizon")}
        kept = H.keep_parts(res, prev, ("sweep", "cases", "random", "long"))
        if kept:
            src = prev.get("meta", {})
            pk = src.get("kept_from_previous_run")
            if pk and set(kept) <= set(pk.get("parts", ())):
                src = pk        # those parts were themselves kept from an earlier run: keep its provenance
            res["meta"]["kept_from_previous_run"] = {"parts": kept, "argv": src.get("argv"), "wall_s": src.get("wall_s")}
    md = render(res)
    if "dpj_study" in parts and not (parts - {"dpj_study"}):
        print(render_dpj(H.read_json(DPJ_STUDY, {}) or {}))
        return res                 # the study alone: results/stress_dpj_study.json; stress.md on the next write
    md_full = md + "\n" + render_dpj(H.read_json(DPJ_STUDY, {}) or {})
    print(md)
    if a.no_write:
        return res
    out = H.write_json(H.RESULTS / "stress.json", res, default=float)
    (HERE / "stress.md").write_text("# Stability stress suite\n\n" + (__doc__.split("\n\n", 2)[2]) + "\n" + md_full)
    if not a.no_readme:
        write_readme_section(HERE / "README.md", "stress", "Stability stress suite (benchmarks/stress.py)",
                             "`python benchmarks/stress.py` (`--quick`, `--full`, `--backends`, `--parts`); full "
                             "tables in [stress.md](stress.md).\n\n" + md)
    log(f"[stress] wrote {out}, {HERE / 'stress.md'}, README section ({res['meta']['wall_s']:.0f} s)")
    return res


if __name__ == "__main__":
    main()
