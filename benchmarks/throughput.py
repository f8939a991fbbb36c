#!/usr/bin/env python
"""Throughput of mpmlab's steppers in particle-steps per second, against Taichi's mpm3d in the same run.

What is measured
----------------
* ``throughput``: steady-state particle-steps/s of one compiled step loop (``stepper._advance`` of
  ``--steps`` steps, best of ``--reps`` timed runs after a warm-up) for every backend (jax, warp) x
  precision (fp32, fp64) x dimension (2D, 3D) on

  - ``mpm3d``: Taichi mpm3d's scene (``mpmlab.scenes.mpm3d.mpm3d_fluid``): J-fluid, MLS/APIC,
    n_grid^3/4 particles at the peer's own random positions, E = 400, 3-cell separate walls. 2D uses
    the same recipe with n_grid chosen for the same particle count (181 / 512 / 1448 for 8k / 65k / 524k);
  - ``cube``: a fixed-corotated elastic cube (``mpmlab.scenes.mpm3d.elastic_cube``), MLS.

  The first call (trace/compile/kernel load + the first steps) is reported separately.
* ``taichi``: ``peers/mpm_taichi.py N_GRID STEPS`` run as a subprocess with the Python of a separate
  virtual environment (``--taichi-python`` or ``$MPMLAB_TAICHI_PYTHON``; Taichi is never imported
  here). The 3D fp32 mpm3d comparison runs in ``--rounds`` interleaved rounds (Taichi, then each
  mpmlab variant) and keeps each one's best round: on a shared machine the best round is the least
  disturbed one, for both sides. Ratios mpmlab/Taichi are printed and stored for those rows.
* ``skips``: the measured effect of what mpmlab leaves out of a compiled step when a scene does not
  need it (elastic vs plastic law, PIC vs APIC, J-only vs F law, no extra boundaries vs some, rollout
  keeping every frame vs every 100th, Warp's grid update limited to reached nodes vs the whole grid).

Results go to ``benchmarks/out/throughput.json`` and the "Throughput" / "Skips" sections of
``benchmarks/README.md`` (regenerated between markers; the rest of the README is kept).

Usage::

    MPMLAB_TAICHI_PYTHON=/path/to/taichi-venv/bin/python python benchmarks/throughput.py
    python benchmarks/throughput.py --quick          # 8k particles only, no skips
    python benchmarks/throughput.py --big            # adds the 524k-particle case
"""
from __future__ import annotations

import json
import os
import re
import subprocess
import tempfile
import time
from pathlib import Path

import _harness as H
from _harness import CUBE_N_GRID, N_GRID_2D, N_GRID_3D

HERE = H.HERE


# ---- measurement -----------------------------------------------------------------------------------
def steps_for(n: int, scale: float = 1.0) -> int:
    """Steps per timed run: about 2e6 particle-steps (>= 10, <= 200)."""
    return int(max(10, min(200, round(2e6 * scale / n))))


def measure(scene, backend, precision, transfer="mls", steps=None, reps=3, configure=None, **options) -> dict:
    import mpmlab

    t0 = time.perf_counter()
    st = mpmlab.build_stepper(scene, backend, transfer, precision, **options)
    if configure is not None:
        configure(st)
    build_s = time.perf_counter() - t0
    n = st.particles.count
    steps = steps or steps_for(n)
    s = st.init()
    t0 = time.perf_counter()
    s = st._advance(s, steps)                 # compiles (JAX) / loads kernels (Warp), then runs
    st._block(s)
    first_s = time.perf_counter() - t0
    s = st._advance(s, steps)                 # warm-up
    st._block(s)
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        s = st._advance(s, steps)
        st._block(s)
        times.append(time.perf_counter() - t0)
    best = min(times)
    bad = st._is_bad(s)
    out = {"backend": backend, "precision": precision, "transfer": transfer, "dim": st.dim, "particles": n,
           "grid": list(st.scene.grid_shape), "laws": [g.law.name for g in st.groups], "steps": steps,
           "build_s": build_s, "first_call_s": first_s,
           "ms_per_step": best / steps * 1e3, "ms_per_step_all": [t / steps * 1e3 for t in times],
           "particle_steps_per_s": n * steps / best, "diverged": bool(bad)}
    if backend == "warp":
        out["threads"] = getattr(st, "threads", 1)
    del st
    return out


def measure_pair(a: dict, b: dict, backend: str, precision: str = "fp32", reps: int = 3, rounds: int = 2):
    """Both steppers built and warmed first, then their timed runs alternate (a, b, a, b, ...):
    a burst of outside load hits both sides alike. ``a``/``b``: dict(scene=, transfer=, configure=,
    options=). Returns the two result dicts (best run each)."""
    import mpmlab

    sides = []
    for spec in (a, b):
        st = mpmlab.build_stepper(spec["scene"], backend, spec.get("transfer", "mls"), precision,
                                  **spec.get("options", {}))
        if spec.get("configure"):
            spec["configure"](st)
        n = st.particles.count
        steps = steps_for(n)
        s = st.init()
        t0 = time.perf_counter()
        s = st._advance(s, steps)
        st._block(s)
        first = time.perf_counter() - t0
        s = st._advance(s, steps)
        st._block(s)
        sides.append({"st": st, "s": s, "steps": steps, "n": n, "first": first, "times": []})
    for _ in range(reps * rounds):
        for side in sides:
            st = side["st"]
            t0 = time.perf_counter()
            side["s"] = st._advance(side["s"], side["steps"])
            st._block(side["s"])
            side["times"].append(time.perf_counter() - t0)
    out = []
    for side in sides:
        best = min(side["times"])
        out.append({"particles": side["n"], "steps": side["steps"], "first_call_s": side["first"],
                    "ms_per_step": best / side["steps"] * 1e3,
                    "ms_per_step_all": [t / side["steps"] * 1e3 for t in side["times"]],
                    "particle_steps_per_s": side["n"] * side["steps"] / best,
                    "laws": [g.law.name for g in side["st"].groups], "transfer": side["st"].transfer.name})
    return out


def measure_rollout(scene, backend, precision, steps, every, reps=2, **options) -> dict:
    import mpmlab

    st = mpmlab.build_stepper(scene, backend, "mls", precision, **options)
    st.rollout(steps=every, every=every, progress=False)           # compile the chunk size used
    if every != 1:
        st.rollout(steps=1, every=1, progress=False)
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        st.rollout(steps=steps, every=every, progress=False)
        times.append(time.perf_counter() - t0)
    n = st.particles.count
    return {"backend": backend, "precision": precision, "particles": n, "steps": steps, "every": every,
            "s": min(times), "particle_steps_per_s": n * steps / min(times)}


def run_taichi(python: str, peer_dir: Path, n_grid: int, steps: int, threads: int) -> dict:
    env = dict(os.environ, TI_THREADS=str(threads))
    with tempfile.TemporaryDirectory() as tmp:
        r = subprocess.run([python, str(peer_dir / "mpm_taichi.py"), str(n_grid), str(steps)], cwd=tmp, env=env,
                           capture_output=True, text=True, timeout=1800)
    line = next((l for l in r.stdout.splitlines() if l.startswith("taichi ")), None)
    if r.returncode != 0 or line is None:
        raise RuntimeError(f"mpm_taichi.py failed (exit {r.returncode}): {r.stderr.strip()[-800:]}")
    m = re.search(r"n=(\d+) first_call=([\d.]+)s steady=([\d.]+) ms/step\s+([\d.e+-]+) particle-steps/s", line)
    return {"n_grid": n_grid, "particles": int(m.group(1)), "first_call_s": float(m.group(2)),
            "ms_per_step": float(m.group(3)), "particle_steps_per_s": float(m.group(4)), "steps": steps,
            "threads": threads, "line": line}


# ---- scenes ------------------------------------------------------------------------------------------
def fluid(size: str, dim: int, law="weakly_compressible", boundaries=None):
    n_grid = (N_GRID_3D if dim == 3 else N_GRID_2D)[size]
    return H.throughput_scene("mpm3d", dim, n_grid, law=law, boundaries=boundaries), n_grid


def cube(dim: int, law="fixed_corotated", **kw):
    return H.throughput_scene("cube", dim, CUBE_N_GRID[dim], law=law, **kw)


def extra_boundaries(dim):
    """Grid boundaries that the fluid never reaches in the timed steps: cost only, same physics."""
    from mpmlab.boundaries import BoxObstacle, FrictionWalls, Plane

    lo, hi = [0.8] * dim, [0.9] * dim
    p = [0.0] * dim
    n = [0.0] * dim
    n[1] = 1.0
    return [FrictionWalls(face="x+", mu=(0.3,), along="y", thickness=2), Plane(point=p, normal=n, condition="slip"),
            BoxObstacle(lo=lo, hi=hi)]


# ---- report --------------------------------------------------------------------------------------------
def fmt(x):
    return f"{x:.2e}"


def tables(res: dict) -> tuple[str, str]:
    lines = []
    mach = res["machine"]
    lines.append(f"Measured {res['date']} on {mach['cpu']} ({mach['cores']} cores; load average "
                 f"{mach['load_before']} before the run), Python {mach['python']}, JAX {mach['jax']}, "
                 f"Warp {mach['warp']}, Taichi {mach.get('taichi', 'not run')}. Particle-steps/s of the "
                 f"steady state (best of {res['reps']} runs); `first` = first call in seconds (JAX: trace + XLA "
                 "compile; Warp: kernel load, from Warp's disk cache when warm) including its steps; "
                 f"3D fp32 mpm3d rows and Taichi: best of {res.get('rounds', 1)} interleaved rounds. "
                 "Regenerate with `python benchmarks/throughput.py` (see its docstring).\n")
    lines += H.md_table(["scene", "dim", "particles", "backend", "precision", "particle-steps/s", "ms/step",
                         "first (s)", "vs Taichi"])
    tai = {t["n_grid"]: t for t in res["taichi"]}
    for r in res["throughput"]:
        ratio = ""
        if r["scene"] == "mpm3d" and r["dim"] == 3 and r["precision"] == "fp32" and r["n_grid"] in tai:
            ratio = f"{r['particle_steps_per_s'] / tai[r['n_grid']]['particle_steps_per_s']:.2f}x"
        lines.append(H.md_row([r["scene"], f"{r['dim']}D", r["particles"],
                               r["backend"] + (f" ({r['threads']} thr)" if "threads" in r else ""), r["precision"],
                               fmt(r["particle_steps_per_s"]), f"{r['ms_per_step']:.2f}", f"{r['first_call_s']:.1f}",
                               ratio]))
    for t in res["taichi"]:
        lines.append(H.md_row(["mpm3d", "3D", t["particles"], f"taichi {mach.get('taichi', '')} ({t['threads']} thr, peer)",
                               "fp32", fmt(t["particle_steps_per_s"]), f"{t['ms_per_step']:.2f}",
                               f"{t['first_call_s']:.1f}", "1.00x"]))
    if res.get("taichi_note"):
        lines.append(f"\n{res['taichi_note']}")
    thr = "\n".join(lines) + "\n"
    sk = ["Each row: the same scene and backend with and without one thing the compiled step can leave out; "
          "fp32, 3D, 65k particles (cube: 55k), Warp on one thread. `gain` = throughput without / with.\n",
          *H.md_table(["skip", "backend", "without (particle-steps/s)", "with (particle-steps/s)", "gain", "note"],
                      ([s["skip"], s["backend"], fmt(s["without"]), fmt(s["with"]), f"{s['without'] / s['with']:.2f}x",
                        s.get("note", "")] for s in res["skips"]))]
    return thr, "\n".join(sk) + "\n"


def write_readme(path: Path, throughput_md: str, skips_md: str) -> None:
    H.write_readme_section(path, "throughput", "Throughput", throughput_md)
    H.write_readme_section(path, "skips", "Skips", skips_md)


# ---- main -------------------------------------------------------------------------------------------------
def machine_info() -> dict:
    return H.machine_info(("jax", "warp"), load=True)


def main(argv=None):
    ap = H.parser(__doc__.split("\n")[0])
    H.add_quick(ap, "8k particles only, no skips (a smoke run)")
    ap.add_argument("--big", action="store_true", help="also the 524k-particle mpm3d case (3D fp32 + 2D fp32)")
    H.add_backends(ap)
    ap.add_argument("--precisions", default="fp32,fp64")
    ap.add_argument("--dims", default="3,2")
    ap.add_argument("--reps", type=int, default=3, help="timed runs per measurement (best kept)")
    ap.add_argument("--rounds", type=int, default=3,
                    help="interleaved rounds of the 3D fp32 mpm3d comparison and of each skip pair (best kept)")
    ap.add_argument("--no-skips", action="store_true")
    ap.add_argument("--skips-only", action="store_true",
                    help="re-run only the skips table, keeping the throughput results already in --out")
    ap.add_argument("--no-taichi", action="store_true")
    ap.add_argument("--taichi-python", default=os.environ.get("MPMLAB_TAICHI_PYTHON"),
                    help="python of a venv with taichi==1.7.4 (default $MPMLAB_TAICHI_PYTHON)")
    ap.add_argument("--taichi-threads", type=int, default=2)
    ap.add_argument("--peer-dir", default=os.environ.get("MPMLAB_PEERS_DIR", "/work/shared/peers"))
    ap.add_argument("--out", default=str(H.OUT / "throughput.json"))
    H.add_readme(ap)
    args = ap.parse_args(argv)

    backends = args.backends.split(",")
    log = lambda *a: H.log(*a, err=True)
    if args.skips_only:
        out = Path(args.out)
        res = json.loads(out.read_text())
        res["skips"], res["rollout"] = [], []
        run_skips(res, backends, args.reps, log, max(1, args.rounds - 1))
        res["skips_date"] = time.strftime("%Y-%m-%d %H:%M")
        H.write_json(out, res)
        thr, sk = tables(res)
        print(sk)
        if args.readme:
            write_readme(Path(args.readme), thr, sk)
        return res
    precisions = args.precisions.split(",")
    dims = [int(d) for d in args.dims.split(",")]
    sizes = ["8k"] if args.quick else ["8k", "65k"] + (["524k"] if args.big else [])
    res = {"date": time.strftime("%Y-%m-%d %H:%M"), "machine": machine_info(), "reps": args.reps, "rounds": args.rounds,
           "throughput": [], "taichi": [], "skips": [], "rollout": []}

    # Warp runs on 1 thread and on all cores (on a busy shared machine one thread can be the
    # faster), JAX with XLA's own threading
    cores = len(os.sched_getaffinity(0))
    variants = []
    for b in backends:
        if b == "warp":
            variants += [("warp", {"threads": t}) for t in sorted({1, cores})]
        else:
            variants.append((b, {}))
    taichi_ok = False
    if args.no_taichi:
        res["taichi_note"] = "Taichi peer not run (--no-taichi)."
    elif not args.taichi_python or not Path(args.taichi_python).exists():
        res["taichi_note"] = ("Taichi peer skipped: no Taichi venv python given (set MPMLAB_TAICHI_PYTHON or pass "
                              "--taichi-python; create it with `python -m venv V && V/bin/pip install taichi==1.7.4 "
                              "numpy`).")
        log(res["taichi_note"])
    elif not (Path(args.peer_dir) / "mpm_taichi.py").exists():
        res["taichi_note"] = f"Taichi peer skipped: {args.peer_dir}/mpm_taichi.py not found (--peer-dir)."
        log(res["taichi_note"])
    else:
        taichi_ok = True
        v = subprocess.run([args.taichi_python, "-c", "import taichi; v = taichi.__version__; "
                            "print('.'.join(map(str, v)) if isinstance(v, tuple) else v)"],
                           capture_output=True, text=True)
        res["machine"]["taichi"] = v.stdout.strip().splitlines()[-1] if v.returncode == 0 else "?"

    def taichi(n_grid, n):
        try:
            return run_taichi(args.taichi_python, Path(args.peer_dir), n_grid, steps_for(n, 0.5), args.taichi_threads)
        except Exception as e:  # the peer is optional: report, keep going
            log(f"taichi n_grid={n_grid} failed: {e}")
            return None

    def best_of(runs):
        top = max(runs, key=lambda r: r["particle_steps_per_s"])
        top["rounds_particle_steps_per_s"] = [r["particle_steps_per_s"] for r in runs]
        return top

    for size in sizes:
        n_grid3 = N_GRID_3D[size]
        n = n_grid3**3 // 4
        # The headline comparison (3D, fp32, mpm3d) runs in interleaved rounds -- Taichi, then each mpmlab
        # variant, repeated -- and keeps each one's best round, so a burst of load from other jobs on
        # the shared machine does not decide the ratio.
        duel = 3 in dims and "fp32" in precisions
        sc3, _ = fluid(size, 3)
        t_runs, m_runs = [], {}
        for rnd in range(args.rounds if duel else 0):
            if taichi_ok:
                t = taichi(n_grid3, n)
                if t:
                    t_runs.append(t)
            for backend, opts in variants:
                m_runs.setdefault((backend, tuple(opts.items())), []).append(
                    measure(sc3, backend, "fp32", reps=args.reps, **opts))
        for dim in dims:
            sc, n_grid = fluid(size, dim)
            for backend, opts in variants:
                for prec in precisions:
                    if size == "524k" and prec == "fp64":
                        continue
                    if dim == 3 and prec == "fp32" and duel:
                        r = best_of(m_runs[(backend, tuple(opts.items()))])
                    else:
                        r = measure(sc, backend, prec, reps=args.reps, **opts)
                    r.update(scene="mpm3d", n_grid=n_grid)
                    res["throughput"].append(r)
                    log(f"mpm3d {dim}D n={r['particles']} {backend} {opts} {prec}: {fmt(r['particle_steps_per_s'])} "
                        f"particle-steps/s ({r['ms_per_step']:.2f} ms/step, first call {r['first_call_s']:.1f} s)")
        if t_runs:
            best = best_of(t_runs)
            res["taichi"].append(best)
            log(f"taichi n_grid={n_grid3}: {fmt(best['particle_steps_per_s'])} particle-steps/s "
                f"(rounds: {[fmt(x) for x in best['rounds_particle_steps_per_s']]})")
            for r in res["throughput"]:
                if r["scene"] == "mpm3d" and r["dim"] == 3 and r["n_grid"] == n_grid3 and r["precision"] == "fp32":
                    log(f"  ratio {r['backend']} {r.get('threads', '')}/taichi = "
                        f"{r['particle_steps_per_s'] / best['particle_steps_per_s']:.2f}")
    if not args.quick:
        for dim in dims:
            sc = cube(dim)
            for backend, opts in variants:
                for prec in precisions:
                    r = measure(sc, backend, prec, reps=args.reps, **opts)
                    r.update(scene="cube", n_grid=CUBE_N_GRID[dim])
                    res["throughput"].append(r)
                    log(f"cube {dim}D n={r['particles']} {backend} {prec}: {fmt(r['particle_steps_per_s'])}")

    out = H.write_json(args.out, res)        # partial results, in case the skips fail
    if not args.quick and not args.no_skips:
        run_skips(res, backends, args.reps, log, max(1, args.rounds - 1))

    res["ratios"] = [{"n_grid": t["n_grid"], "backend": r["backend"], "threads": r.get("threads"),
                      "ratio": r["particle_steps_per_s"] / t["particle_steps_per_s"]}
                     for t in res["taichi"] for r in res["throughput"]
                     if r["scene"] == "mpm3d" and r["dim"] == 3 and r["precision"] == "fp32" and r["n_grid"] == t["n_grid"]]
    res["machine"]["load_after"] = H.load_average()
    H.write_json(out, res)
    thr, sk = tables(res)
    print(thr)
    print(sk)
    if args.readme:
        write_readme(Path(args.readme), thr, sk)
    return res


def run_skips(res, backends, reps, log, rounds=2):
    """Each skip: same backend, fp32, 65k particles (3D) with and without the thing left out."""

    def pair(name, backend, without, with_, note=""):
        try:
            a, b = measure_pair(without, with_, backend, reps=reps, rounds=rounds)
        except Exception as e:   # one broken comparison must not lose the others
            log(f"skip {name} [{backend}] failed: {type(e).__name__}: {e}")
            return
        row = {"skip": name, "backend": backend, "without": a["particle_steps_per_s"], "with": b["particle_steps_per_s"],
               "note": note, "without_run": a, "with_run": b}
        res["skips"].append(row)
        log(f"skip {name} [{backend}]: {fmt(row['without'])} vs {fmt(row['with'])} ({row['without'] / row['with']:.2f}x)")

    fl, _ = fluid("65k", 3)
    fl_fc, _ = fluid("65k", 3, law="fixed_corotated")
    fl_bc, _ = fluid("65k", 3, boundaries=extra_boundaries(3))
    el, pl = cube(3), cube(3, law="hencky_von_mises", yield_stress=1e9)
    for be in backends:
        one = {"threads": 1} if be == "warp" else {}    # Warp on one thread: steadier on a shared machine
        m = lambda sc, **kw: dict(scene=sc, options=one, **kw)
        pair("plasticity (elastic law vs plastic law)", be, m(el), m(pl),
             "cube: fixed_corotated vs hencky_von_mises (never yields here): the return map + Hencky log/exp")
        pair("affine C (PIC vs APIC)", be, m(fl, transfer="pic"), m(fl, transfer="apic"),
             "mpm3d fluid: no C stored, no affine terms in P2G/G2P")
        pair("J-only law vs F law", be, m(fl), m(fl_fc),
             "mpm3d scene: weakly_compressible (J) vs fixed_corotated (F, SVD per particle)")
        pair("extra boundaries (none vs friction wall + plane + box)", be, m(fl), m(fl_bc),
             "mpm3d fluid: three extra grid boundaries, none reached")
        if be == "warp":
            def full_grid(st):
                st.limit_grid = False
            pair("grid update only where particles reach (vs whole grid)", be, m(fl), m(fl, configure=full_grid),
                 "Warp: grid update + clearing over the reached nodes' box")

            def unsorted(st):
                st.sort_every = None
            pair("scattered memory access (particles sorted by cell vs scene order)", be, m(fl), m(fl, configure=unsorted),
                 "Warp CPU: re-sort every 100 steps vs never (the peer's random order); an option, not a skip")
        steps = 200
        ab = [(measure_rollout(fl, be, "fp32", steps, 100, **one), measure_rollout(fl, be, "fp32", steps, 1, **one))
              for _ in range(rounds)]
        a = max((r[0] for r in ab), key=lambda r: r["particle_steps_per_s"])
        b = max((r[1] for r in ab), key=lambda r: r["particle_steps_per_s"])
        res["rollout"] += [a, b]
        res["skips"].append({"skip": "frames kept (every 100th vs every frame)", "backend": be,
                             "without": a["particle_steps_per_s"], "with": b["particle_steps_per_s"],
                             "note": f"rollout of {steps} steps (frames to NumPy + guard per kept frame)"})
        log(f"skip frames [{be}]: {fmt(a['particle_steps_per_s'])} vs {fmt(b['particle_steps_per_s'])}")


if __name__ == "__main__":
    main()
