#!/usr/bin/env python
"""JAX gradients: where the backward time goes per stage, and fwd+bwd / forward (issue 17, item 1).

Scene: the Ritter dam break of ``gradients.py`` (``ritter_dam_break(dx=0.0125)``: 2560 particles,
163 x 13 nodes, APIC, fp32). For each XLA setting (``ynn``: "default" = XLA CPU's YNNPACK fusions on,
as jaxlib 0.10 ships; "off" = ``XLA_FLAGS=--xla_cpu_experimental_ynn_fusion_type=``; XLA reads the
flag once per process, so each setting runs in its own subprocess) and each adjoint implementation
(``adjoints``: "derived" = XLA's transposes of the P2G scatter / G2P gather, "custom" = the
hand-written ones of ``mpmlab/backends/jax/adjoints.py``; ``JaxStepper(..., adjoints=...)``):

* **Per-stage forward / backward** (``stages``): a ``stage_steps``-step ``lax.scan`` of the step,
  differentiated with every residual kept (``jax.vjp`` in one jitted program, the pullback in
  another: the backward program contains only adjoint work). Both programs run under
  ``jax.profiler``; every executed XLA thunk is attributed to a stage through the stack frames of the
  compiled HLO (``stage_profile.py``'s machinery: the comment-headed sections of ``step_fn``, and the
  functions of ``adjoints.py``: P2G, G2P), and the stage shares of the summed thunk time are scaled
  to the measured wall time of the program (best of ``reps``), per step (XLA runs independent thunks
  concurrently: the shares are of summed thunk time). Forward = the plain forward
  scan (no residuals); backward = the pullback. B/F per stage and for the step.
* **Whole gradient** (``ratios``): ``L = sum(observe(c, Lagrangian("x"), steps=[N], segment=s)**2)``
  differentiated w.r.t. (v0, law parameters) with ``jax.value_and_grad`` (jitted), against the forward
  ``observe`` with segment = N (as ``gradients.py``), for s = ``segment`` (recompute segments, the
  steps rematerialised: F + F + F + B), s = ``segment`` without the per-step remat (F + F + B, the
  segment's residuals kept while it is differentiated) and s = "auto" (every step kept when it fits
  the memory budget: F + B). All programs of both implementations are compiled first and then timed
  in interleaved rounds; min and median reported, ratio of the minima (the machine is shared: the
  minimum is the least disturbed run; ``load`` records the load average before and after).

``jax_split(...) -> dict`` runs it; ``python benchmarks/_adjoint_split_jax.py`` prints the table and
writes ``benchmarks/results/adjoint_split_jax.json``::

    python benchmarks/_adjoint_split_jax.py                       # N 400, segment 20, both settings
    python benchmarks/_adjoint_split_jax.py --N 100 --reps 3      # quicker
    python benchmarks/_adjoint_split_jax.py --render              # the table from the JSON
"""
from __future__ import annotations

import argparse
import gzip
import json
import os
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import _harness as H  # noqa: E402  (light: no JAX/Warp at import)
RESULT = HERE / "results" / "adjoint_split_jax.json"
YNN_OFF = "--xla_cpu_experimental_ynn_fusion_type="
STAGES = ("P2G", "law (stress)", "grid update", "G2P", "law (update)", "other")
#: adjoints.py functions -> stage (the innermost match along an op's stack wins)
_ADJ_STAGE = {"p2g": "P2G", "p2g_plain": "P2G", "_p2g_transpose": "P2G", "g2p": "G2P", "g2p_plain": "G2P",
              "_g2p_transpose": "G2P"}


# ---- worker (one XLA setting per process) ---------------------------------------------------------------
def _classifier(text):
    """HLO instruction name -> stage, from the compiled module's stack frames."""
    import inspect

    sys.path.insert(0, str(HERE))
    from stage_profile import _frame_chain, _hlo_tables, step_fn_sections

    from mpmlab.backends.jax.stepper import JaxStepper

    instr, roots, files, funcs, locs, frames = _hlo_tables(text)
    sections = step_fn_sections(JaxStepper)
    src, first = inspect.getsourcelines(JaxStepper.step_fn)
    last = first + len(src) - 1

    def of_frame(fid):
        for f, fn, line in _frame_chain(fid, files, funcs, locs, frames):
            if f.endswith("backends/jax/adjoints.py") and fn in _ADJ_STAGE:
                return _ADJ_STAGE[fn]
            if f.endswith("backends/jax/stepper.py"):
                if first <= line <= last:
                    stage = "P2G"
                    for start, name in sections:
                        if line >= start:
                            stage = name
                    return {"boundaries": "grid update"}.get(stage, stage)
                if fn == "bspline_weights":
                    return "P2G"
                if fn == "per_mass":
                    return "grid update"
            if "/boundaries" in f:
                return "grid update"
            if "/laws/" in f or f.endswith("backends/jax/linalg.py"):
                return "law (stress)" if "kirchhoff" in fn or "stress" in fn else "law (update)"
        return "other"

    def stage_of(name, depth=0):
        opcode, fid, called = instr.get(name, (None, None, []))
        if fid is None and called and depth < 4:
            root = roots.get(called[0])
            if root is not None:
                return stage_of(root, depth + 1)
        return of_frame(fid) if fid is not None else "other"

    containers = {n for n, (op, _, _) in instr.items() if op in ("while", "conditional", "call")}
    return stage_of, containers


def _shares(compiled, args, module_prefix):
    """{stage: share of the summed XLA thunk time} of one run of a compiled program under jax.profiler."""
    import jax

    stage_of, containers = _classifier(compiled.as_text())
    with tempfile.TemporaryDirectory() as d:
        with jax.profiler.trace(d):
            jax.block_until_ready(compiled(*args))
        trace = next(Path(d).rglob("*.trace.json.gz"))
        events = json.load(gzip.open(trace))["traceEvents"]
    thunk = defaultdict(float)
    for e in events:
        a = e.get("args") or {}
        if e.get("ph") == "X" and "hlo_op" in a and str(a.get("hlo_module", "")).startswith(module_prefix):
            if a["hlo_op"] in containers:
                continue
            thunk[stage_of(a["hlo_op"])] += e.get("dur", 0.0) * 1e-6
    total = sum(thunk.values()) or 1.0
    return {k: v / total for k, v in thunk.items()}


def _stage_programs(st, steps):
    """{name: (compiled, args, hlo module prefix)}: the forward scan and the pullback of the kept-residual VJP."""
    import jax
    import jax.numpy as jnp

    from mpmlab.backends.jax import differentiable as JD

    s0, p = JD.split_controls(st, st.controls())
    s0 = st._advance(s0, 20)

    def scan(s, prm):
        return jax.lax.scan(lambda c, _: (st.step_fn(c, prm), None), s, None, length=steps)[0]

    def stage_fwd(s, prm):
        return scan(s, prm)

    def stage_fwd_res(s, prm):
        return jax.vjp(scan, s, prm)

    def stage_bwd(pull, ct):
        return pull(ct)

    y, pull = jax.jit(stage_fwd_res)(s0, p)
    ct = jax.tree.map(lambda a: jnp.ones_like(a) if jnp.issubdtype(a.dtype, jnp.floating) else a, y)
    return {"stage fwd": (jax.jit(stage_fwd).lower(s0, p).compile(), (s0, p), "jit_stage_fwd"),
            "stage bwd": (jax.jit(stage_bwd).lower(pull, ct).compile(), (pull, ct), "jit_stage_bwd")}


def _ratio_programs(st, N, segment):
    import jax
    import jax.numpy as jnp

    from mpmlab.backends.jax import differentiable as JD
    from mpmlab.observations import Lagrangian

    obs = Lagrangian(quantity="x")
    c = st.controls()
    p0 = (c["v"], c["law"])

    def make(segment, remat_steps=True):
        f = JD.observe_fn(st, obs, [N], segment, remat_steps=remat_steps)

        def loss(p):
            y = f({**c, "v": p[0], "law": p[1]})
            return jnp.sum(y * y)
        return loss

    progs = {"forward": jax.jit(make(N))}
    variants = {f"segment {segment}": (segment, True), f"segment {segment}, no step remat": (segment, False),
                "segment auto": ("auto", True)}
    for name, (s, r) in variants.items():
        progs[name] = jax.jit(jax.value_and_grad(make(s, r)))
    return {k: (f.lower(p0).compile(), (p0,), None) for k, f in progs.items()}


def worker(spec):
    """Both adjoint implementations in one process: every program compiled first, then timed in
    interleaved rounds (derived and custom alternate, so load changes hit both alike)."""
    import jax
    import numpy as np

    from mpmlab.backends.jax import differentiable as JD
    from mpmlab.scenes.validation import ritter_dam_break
    from mpmlab.simulator import build_stepper

    res = {"ynn": spec["ynn"], "xla_flags": os.environ.get("XLA_FLAGS", ""), "load_before": H.load_average(), "rows": []}
    progs, steppers = {}, {}
    for mode in spec["adjoints"]:
        st = build_stepper(ritter_dam_break(dx=spec["dx"]), "jax", spec["transfer"], spec["precision"], adjoints=mode)
        steppers[mode] = st
        for k, v in {**_stage_programs(st, spec["stage_steps"]), **_ratio_programs(st, spec["N"], spec["segment"])}.items():
            progs[(mode, k)] = v
    times = {k: [] for k in progs}
    cpu = {k: [] for k in progs}
    for k, (f, args, _) in progs.items():
        jax.block_until_ready(f(*args))
    for _ in range(spec["reps"]):
        for k, (f, args, _) in progs.items():
            t0, c0 = time.perf_counter(), time.process_time()
            jax.block_until_ready(f(*args))
            times[k].append(time.perf_counter() - t0)
            cpu[k].append(time.process_time() - c0)
    # the forward programs of the two implementations are the same program (bit-identical steps): the
    # ratios use the best forward of either, so that a disturbed forward does not skew one row
    Fbest = min(min(times[(m, "forward")]) for m in steppers)
    Fcpu = min(min(cpu[(m, "forward")]) for m in steppers)
    steps = spec["stage_steps"]
    for mode, st in steppers.items():
        row = {"adjoints": mode, "particles": int(st.particles.count), "grid": list(st.grid_shape)}
        F = min(min(times[(m, "stage fwd")]) for m in steppers)          # the same program for both
        B = min(times[(mode, "stage bwd")])
        fs = _shares(*progs[(mode, "stage fwd")])
        bs = _shares(*progs[(mode, "stage bwd")])
        Fc = min(min(cpu[(m, "stage fwd")]) for m in steppers)
        sg = {"steps": steps, "fwd_ms_per_step": 1e3 * F / steps, "bwd_ms_per_step": 1e3 * B / steps,
              "fwd_cpu_ms_per_step": 1e3 * Fc / steps, "bwd_cpu_ms_per_step": 1e3 * min(cpu[(mode, "stage bwd")]) / steps,
              "B_over_F_cpu": min(cpu[(mode, "stage bwd")]) / Fc,
              "fwd_median_ms_per_step": 1e3 * float(np.median(times[(mode, "stage fwd")])) / steps,
              "bwd_median_ms_per_step": 1e3 * float(np.median(times[(mode, "stage bwd")])) / steps,
              "B_over_F": B / F, "per_stage": {}}
        for k in STAGES:
            f, b = fs.get(k, 0.0) * F / steps, bs.get(k, 0.0) * B / steps
            sg["per_stage"][k] = {"fwd_ms": 1e3 * f, "bwd_ms": 1e3 * b, "B_over_F": (b / f) if f > 0 else None}
        row["stages"] = sg
        Ff = Fbest
        Fm = float(np.median([t for m in steppers for t in times[(m, "forward")]]))
        seg_auto, keep = JD.resolve(st, "auto", spec["N"])
        rat = {"N": spec["N"], "auto_keeps": bool(keep), "step_bytes": JD.step_bytes(st), "variants": {}}
        for (m, k), ts in times.items():
            if m != mode or k.startswith("stage"):
                continue
            rat["variants"][k] = {"min_s": min(ts), "median_s": float(np.median(ts)), "ratio": min(ts) / Ff,
                                  "ratio_median": float(np.median(ts)) / Fm,
                                  "cpu_s": min(cpu[(m, k)]), "ratio_cpu": min(cpu[(m, k)]) / Fcpu,
                                  "temp_mib": progs[(m, k)][0].memory_analysis().temp_size_in_bytes / 2**20}
        row["ratios"] = rat
        res["rows"].append(row)
        print(f"[adjoint split] ynn {spec['ynn']} {mode}: B/F {sg['B_over_F']:.2f}, ratios "
              + ", ".join(f"{k} {v['ratio']:.2f}" for k, v in rat["variants"].items() if k != "forward"),
              file=sys.stderr, flush=True)
    res["load_after"] = H.load_average()
    res["jax"] = jax.__version__
    return res


# ---- driver -----------------------------------------------------------------------------------------------
def jax_split(N: int = 400, segment: int = 20, dx: float = 0.0125, transfer: str = "apic", precision: str = "fp32",
              adjoints=("derived", "custom"), ynn=("default", "off"), stage_steps: int = 20, reps: int = 5,
              timeout: float = 1800) -> dict:
    """Per-stage forward / backward times and fwd+bwd / forward ratios (module docstring), one
    subprocess per YNNPACK setting. Returns ``{"spec", "date", "machine", "runs": [...]}``."""
    spec = {"N": N, "segment": segment, "dx": dx, "transfer": transfer, "precision": precision,
            "adjoints": list(adjoints), "stage_steps": stage_steps, "reps": reps}
    runs = []
    for y in ynn:
        env = dict(os.environ)
        flags = env.get("XLA_FLAGS", "").replace(YNN_OFF, "").strip()
        env["XLA_FLAGS"] = (flags + " " + YNN_OFF).strip() if y == "off" else flags
        env["PYTHONPATH"] = os.pathsep.join([str(HERE.parent), env.get("PYTHONPATH", "")]).strip(os.pathsep)
        out = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--worker", json.dumps({**spec, "ynn": y})],
                             env=env, capture_output=True, text=True, timeout=timeout)
        sys.stderr.write(out.stderr[-2000:] if out.returncode else "".join(
            l + "\n" for l in out.stderr.splitlines() if l.startswith("[adjoint split]")))
        if out.returncode:
            raise RuntimeError(f"worker (ynn {y}) failed with code {out.returncode}")
        runs.append(json.loads(out.stdout.strip().splitlines()[-1]))
    import platform

    cpu = platform.processor()
    try:
        cpu = next(l.split(":", 1)[1].strip() for l in open("/proc/cpuinfo") if l.startswith("model name"))
    except (OSError, StopIteration):
        pass
    return {"spec": spec, "date": time.strftime("%Y-%m-%d %H:%M"), "git": _git(),
            "machine": {"cpu": cpu, "cores": len(os.sched_getaffinity(0))}, "runs": runs}


def _git() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=HERE, capture_output=True,
                              text=True).stdout.strip()
    except OSError:
        return "?"


def table(res: dict) -> str:
    sp = res["spec"]
    L = [f"JAX adjoint split, Ritter dam break dx {sp['dx']} ({sp['transfer']}, {sp['precision']}), "
         f"{res['date']}, {res['machine']['cpu']} ({res['machine']['cores']} cores), commit {res.get('git', '?')}"]
    L.append(f"\nPer stage, ms per step (scan of {sp['stage_steps']} steps; fwd = forward alone, bwd = pullback with "
             "every residual kept; best of the repeats):\n")
    L.append(f"| YNN | adjoints | {' | '.join(f'{s} fwd / bwd' for s in STAGES)} | step fwd / bwd | B/F | B/F (CPU time) |")
    L.append("|---|---|" + "---|" * (len(STAGES) + 3))
    for run in res["runs"]:
        for row in run["rows"]:
            s = row["stages"]
            cells = [f"{s['per_stage'][k]['fwd_ms']:.3f} / {s['per_stage'][k]['bwd_ms']:.3f}" for k in STAGES]
            L.append(f"| {run['ynn']} | {row['adjoints']} | {' | '.join(cells)} | {s['fwd_ms_per_step']:.3f} / "
                     f"{s['bwd_ms_per_step']:.3f} | {s['B_over_F']:.2f} | {s.get('B_over_F_cpu', float('nan')):.2f} |")
    L.append(f"\nWhole gradient, N = {sp['N']} steps: fwd+bwd / forward, wall (min over repeats; median in brackets) and "
             "CPU time (process, min), XLA temp MiB; forward = the best of both implementations' (same program):\n")
    names = [k for k in res["runs"][0]["rows"][0]["ratios"]["variants"] if k != "forward"]
    L.append(f"| YNN | adjoints | forward s | {' | '.join(names)} | load (before / after) |")
    L.append("|---|---|---|" + "---|" * len(names) + "---|")
    for run in res["runs"]:
        for row in run["rows"]:
            v = row["ratios"]["variants"]
            cells = [f"{v[k]['ratio']:.2f} ({v[k]['ratio_median']:.2f}), cpu {v[k].get('ratio_cpu', float('nan')):.2f}, "
                     f"{v[k]['temp_mib']:.0f} MiB" for k in names]
            L.append(f"| {run['ynn']} | {row['adjoints']} | {v['forward']['min_s']:.3f} | {' | '.join(cells)} | "
                     f"{run['load_before']} / {run['load_after']} |")
    return "\n".join(L)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--N", type=int, default=400)
    ap.add_argument("--segment", type=int, default=20)
    ap.add_argument("--dx", type=float, default=0.0125)
    ap.add_argument("--transfer", default="apic")
    ap.add_argument("--precision", default="fp32")
    ap.add_argument("--stage-steps", type=int, default=20)
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--ynn", default="default,off", help="XLA YNNPACK settings to run: default, off")
    ap.add_argument("--adjoints", default="derived,custom")
    ap.add_argument("--render", action="store_true", help="print the table of the saved JSON")
    ap.add_argument("--out", default=str(RESULT))
    a = ap.parse_args(argv)
    if a.worker is not None:
        print(json.dumps(worker(json.loads(a.worker))))
        return
    if a.render:
        print(table(json.loads(Path(a.out).read_text())))
        return
    res = jax_split(N=a.N, segment=a.segment, dx=a.dx, transfer=a.transfer, precision=a.precision,
                    adjoints=tuple(a.adjoints.split(",")), ynn=tuple(a.ynn.split(",")), stage_steps=a.stage_steps,
                    reps=a.reps)
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(res, indent=1))
    print(table(res))
    print(f"\nwrote {a.out}")


if __name__ == "__main__":
    main()
