#!/usr/bin/env python
"""Gradients through rollouts: peak memory against segment length, and forward+backward time against
forward alone, on both backends (issue #4, item 3).

What is measured
----------------
A loss ``L = sum(y**2)`` of the Lagrangian positions ``y = stepper.observe(c, Lagrangian("x"),
steps=[N], segment=n)`` of every particle after N steps, differentiated w.r.t. the initial velocity
``c["v"]`` and the law parameters ``c["law"]`` (JAX: ``jax.value_and_grad``, jitted; Warp: torch
autograd, ``loss.backward()``). ``n`` is the segment length: the backward pass recomputes segments of
n steps from saved segment-start states, so memory should go as O(N/n + n) states instead of O(N).
Scene: the 2D Ritter dam break (``mpmlab.scenes.validation.ritter_dam_break``, ``--dx`` 0.0125 m:
2560 particles, 163 x 13 grid nodes, dt 1.07e-4 s), APIC, fp32.

* **Memory.** Every (backend, N, n) runs in a fresh subprocess. Compilation is kept out of it on both
  backends: JAX programs are compiled beforehand in a separate process into a persistent compilation
  cache (a temporary directory) and loaded from there; Warp kernels come from Warp's on-disk kernel
  cache, filled by a warm-up process. In the measured process: build the stepper, run one forward-only
  ``observe`` (segment = N, so nothing is saved; Warp also runs a 2-step gradient to load the backward
  kernels, JAX loads the compiled gradient program), ``gc.collect()``, then record the process's peak
  resident memory (``resource.getrusage(RUSAGE_SELF).ru_maxrss``) = *base*; run the gradient once,
  record ``ru_maxrss`` again = *grad*; the reported peak is *grad - base* (both raw numbers are in the
  JSON). A thread samples the current resident size (``/proc/self/statm``) every millisecond during
  the gradient call as a second estimate (peak during the call minus the size just before it); it
  also sees memory that the allocator reuses below the earlier peak. JAX also reports XLA's static
  buffer assignment of the compiled gradient program (``compiled.memory_analysis()``, temp bytes:
  exact for that program). *model* = (N/n + n) x the bytes of one simulation state (JAX state
  pytree: x, v, C, law state), the expected scaling with its smallest constant.
* **Time.** Same process, after the memory measurement: ``--reps`` rounds that each time the
  forward alone (``observe`` with segment = N under no gradient, the same call the gradient
  differentiates) and then the full forward + backward; medians are reported and the ratio is
  median(grad) / median(forward). Compilation (JAX, in the compile process) and the first call are
  reported apart. A breakdown process per backend (``--breakdown``) times, at N steps, the fast
  stepper (``stepper._advance``, the non-differentiable path), the gradient path without any
  recomputation (JAX: ``value_and_grad`` of a plain ``lax.scan`` of the step; Warp: one ``wp.Tape`` over
  all N steps) and with per-step rematerialisation only (JAX), to show where the time goes.
* **JAX variant.** The segment sweep and the breakdown are run once more for JAX with
  ``XLA_FLAGS=--xla_cpu_experimental_ynn_fusion_type=`` (XLA CPU's YNNPACK fusions off): on jaxlib
  0.10 they turn the small reductions of the step's transpose into slow library calls (README).
  ``--jax-variant-flags ''`` skips it.
* **JAX elastic step, SVD before / after** (issue 17; ``--elastic-only`` runs this part alone). The 3D
  fixed-corotated cube of ``stage_profile.py`` (``elastic_cube``, n_grid 32, 7600 particles, MLS, fp32),
  one process: the JAX step traced with the parent commit's SVD (``jnp.linalg.svd``, one LAPACK call per
  particle; ``mpmlab.backends.jax.linalg.svd_impl("lapack")``) and with the branch-free Jacobi SVD that
  replaced it, and Warp's step (default threads and one thread). ``--elastic-rounds`` interleaved rounds
  of ``stepper._advance(state, --elastic-steps)`` (best and median ms per step), then the gradient of
  sum(x^2) after ``--elastic-grad-steps`` steps w.r.t. (v0, E, nu) for each (JAX: ``value_and_grad``, no
  recomputation; Warp: torch autograd), medians of ``--reps`` alternating repeats. The positions after
  the timed steps of the two JAX variants are compared (they differ by fp32 round-off only). Output:
  ``benchmarks/results/elastic_step.json`` and the README section "JAX elastic step: the SVD".
* The parent process never imports JAX, Warp or torch: Linux carries a process's ``ru_maxrss``
  high-water mark into its children (fork/vfork + execve), so a heavy parent would raise every
  child's baseline above what the child itself reaches.

Output: ``benchmarks/out/gradients.json``, ``benchmarks/out/gradients.png`` and the "Gradients: memory
and time" section of ``benchmarks/README.md`` (regenerated between markers).

Usage::

    python benchmarks/gradients.py                     # the default sweep (~7 min on 2 cores)
    python benchmarks/gradients.py --quick             # small sizes, a smoke run
    python benchmarks/gradients.py --N 400 --segments 10,20,50,100,400 --scaling-N 100,200,400,800
    python benchmarks/gradients.py --render            # README table and plot from the JSON only
    python benchmarks/gradients.py --baseline f277f7d  # + the before/after table: that commit measured in the same run
    python benchmarks/gradients.py --elastic-only      # the JAX elastic step, SVD before / after (~2 min)
    python benchmarks/gradients.py --elastic-only --render
"""
from __future__ import annotations

import argparse
import gc
import json
import os
import resource
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

import _harness as H

HERE = H.HERE
MiB = 2.0**20


# ---- shared set-up ----------------------------------------------------------------------------------
def scene_of(spec):
    from mpmlab.scenes.validation import ritter_dam_break

    return ritter_dam_break(dx=spec["dx"])


def build(spec, backend):
    from mpmlab.simulator import build_stepper

    return build_stepper(scene_of(spec), backend, spec["transfer"], spec["precision"])


def jax_setup(cache_dir):
    import jax

    jax.config.update("jax_compilation_cache_dir", cache_dir)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)
    return jax


def jax_programs(st, N, n):
    """(loss, value_and_grad) of L = sum(observe(...)**2) w.r.t. p = (v, law): jitted, not compiled."""
    import jax
    import jax.numpy as jnp
    from mpmlab.observations import Lagrangian

    obs = Lagrangian(quantity="x")

    def loss(p, c, segment):
        y = st.observe({**c, "v": p[0], "law": p[1]}, obs, steps=[N], segment=segment)
        return jnp.sum(y * y)

    fwd = jax.jit(lambda p, c: loss(p, c, N))                       # forward alone: nothing to save
    grad = jax.jit(jax.value_and_grad(lambda p, c: loss(p, c, n)))
    return fwd, grad


def jax_state_bytes(st):
    import jax
    from mpmlab.backends.jax import differentiable

    state, _ = differentiable.split_controls(st, st.controls())
    return int(sum(np.asarray(a).nbytes for a in jax.tree_util.tree_leaves(state)))


def mem_stats(ma) -> dict:
    if ma is None:
        return {}
    keys = ("temp_size_in_bytes", "argument_size_in_bytes", "output_size_in_bytes", "alias_size_in_bytes",
            "generated_code_size_in_bytes")
    return {k: int(getattr(ma, k)) for k in keys if hasattr(ma, k)}


def maxrss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0      # Linux: KiB


def rss_mib() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / MiB


class Sampler(threading.Thread):
    """Peak current resident size, sampled every ``period`` s while running."""

    def __init__(self, period=1e-3):
        super().__init__(daemon=True)
        # a private name: threading.Thread uses self._stop
        self.period, self.peak, self._stop_ev = period, rss_mib(), threading.Event()

    def run(self):
        while not self._stop_ev.is_set():
            self.peak = max(self.peak, rss_mib())
            time.sleep(self.period)

    def stop(self):
        self._stop_ev.set()
        self.join()
        self.peak = max(self.peak, rss_mib())
        return self.peak


# ---- workers (each runs in its own process) ----------------------------------------------------------
def worker_compile(spec):
    """JAX: compile every forward and gradient program into the persistent cache; compile times and
    XLA's memory analysis."""
    jax_setup(spec["cache"])
    st = build(spec, "jax")
    c = st.controls()
    p = (c["v"], c["law"])
    out = {"fwd": {}, "grad": {}}
    for N in sorted({N for N, _ in spec["configs"]}):
        fwd, _ = jax_programs(st, N, N)
        t0 = time.perf_counter()
        comp = fwd.lower(p, c).compile()
        out["fwd"][str(N)] = {"compile_s": time.perf_counter() - t0, "xla": mem_stats(comp.memory_analysis())}
    for N, n in spec["configs"]:
        _, grad = jax_programs(st, N, n)
        t0 = time.perf_counter()
        comp = grad.lower(p, c).compile()
        out["grad"][f"{N},{n}"] = {"compile_s": time.perf_counter() - t0, "xla": mem_stats(comp.memory_analysis())}
        print(f"  compiled jax N={N} n={n}: {out['grad'][f'{N},{n}']['compile_s']:.1f} s", file=sys.stderr, flush=True)
    out["state_bytes"] = jax_state_bytes(st)
    out["particles"] = st.particles.count
    out["grid"] = list(st.scene.grid_shape)
    out["dt"] = float(st.dt)
    return out


def warp_fns(st, N, n):
    import torch
    from mpmlab.observations import Lagrangian

    obs = Lagrangian(quantity="x")
    c = st.controls()

    def fwd():
        with torch.no_grad():
            y = st.observe(c, obs, steps=[N], segment=N)
            return float((y * y).sum())

    def grad(steps=N, segment=n):
        v = c["v"].detach().clone().requires_grad_(True)
        law = tuple(a.detach().clone().requires_grad_(True) for a in c["law"])
        y = st.observe({**c, "v": v, "law": law}, obs, steps=[steps], segment=segment)
        loss = (y * y).sum()
        loss.backward()
        return float(loss), v.grad, [a.grad for a in law]

    return fwd, grad


def worker_warm(spec):
    """Warp: fill the kernel cache (forward and backward kernels) with a short gradient."""
    st = build(spec, "warp")
    t0 = time.perf_counter()
    fwd, grad = warp_fns(st, 2, 1)
    fwd()
    grad()
    return {"first_call_s": time.perf_counter() - t0}


def worker_measure(spec):
    backend, N, n, reps = spec["backend"], spec["N"], spec["n"], spec["reps"]
    res = {"backend": backend, "N": N, "n": n, "stages": []}
    stage = lambda name: res["stages"].append((name, maxrss_mib(), rss_mib()))
    t0 = time.perf_counter()
    if backend == "jax":
        jax = jax_setup(spec["cache"])
        st = build(spec, "jax")
        c = st.controls()
        p = (c["v"], c["law"])
        stage("build")
        fwd_j, grad_j = jax_programs(st, N, n)
        fwd_c = fwd_j.lower(p, c).compile()                         # from the persistent cache
        stage("load forward")
        float(fwd_c(p, c))                                           # one forward-only observe
        stage("forward")
        t1 = time.perf_counter()
        grad_c = grad_j.lower(p, c).compile()                       # from the persistent cache
        res["grad_load_s"] = time.perf_counter() - t1
        stage("load gradient")

        def fwd():
            return float(fwd_c(p, c))

        def grad():
            out = grad_c(p, c)
            jax.block_until_ready(out)
            return out
    else:
        st = build(spec, "warp")
        stage("build")
        fwd, grad_full = warp_fns(st, N, n)
        fwd()                                                        # one forward-only observe
        stage("forward")
        t1 = time.perf_counter()
        grad_full(steps=2, segment=1)                                # loads the backward kernels
        res["grad_load_s"] = time.perf_counter() - t1
        stage("load gradient")
        grad = grad_full
    res["setup_s"] = time.perf_counter() - t0
    gc.collect()
    res["maxrss_base_mib"] = maxrss_mib()
    res["rss_before_mib"] = rss_mib()
    sampler = Sampler()
    sampler.start()
    t1 = time.perf_counter()
    out = grad()
    res["first_grad_s"] = time.perf_counter() - t1
    res["rss_peak_mib"] = sampler.stop()
    res["maxrss_grad_mib"] = maxrss_mib()
    res["peak_mib"] = res["maxrss_grad_mib"] - res["maxrss_base_mib"]
    res["peak_sampled_mib"] = res["rss_peak_mib"] - res["rss_before_mib"]
    leaves = list(_leaves(out[1:] if backend == "warp" else out[1]))
    res["grad_finite"] = bool(all(np.all(np.isfinite(np.asarray(a))) for a in leaves))
    res["loss"] = float(out[0])
    res["grad_v_norm"] = float(np.linalg.norm(np.asarray(leaves[0])))
    del out
    tf, tg = [], []
    for _ in range(reps):
        t1 = time.perf_counter()
        fwd()
        tf.append(time.perf_counter() - t1)
        t1 = time.perf_counter()
        grad()
        tg.append(time.perf_counter() - t1)
    res["fwd_s_all"], res["grad_s_all"] = tf, tg
    res["fwd_s"], res["grad_s"] = float(np.median(tf)), float(np.median(tg))
    res["ratio"] = res["grad_s"] / res["fwd_s"]
    res["particles"] = st.particles.count
    return res


def _leaves(x):
    if isinstance(x, (list, tuple)):
        for a in x:
            yield from _leaves(a)
    elif isinstance(x, dict):
        for a in x.values():
            yield from _leaves(a)
    elif x is not None:
        yield x.detach().cpu().numpy() if hasattr(x, "detach") else x


def _time(f, reps):
    f()                                                               # warm-up / compile
    ts = []
    for _ in range(reps):
        t0 = time.perf_counter()
        f()
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts)), ts


def worker_breakdown(spec):
    """Where the time goes at N steps: the fast stepper, the gradient path's forward, and its
    gradient without recomputation (O(N) memory)."""
    backend, N, reps = spec["backend"], spec["N"], spec["reps"]
    res = {"backend": backend, "N": N}
    if backend == "jax":
        jax = jax_setup(spec["cache"])
        import jax.numpy as jnp
        from mpmlab.backends.jax import differentiable

        st = build(spec, "jax")
        c = st.controls()
        s0 = st.init()
        res["fast_s"], _ = _time(lambda: st._block(st._advance(s0, N)), reps)
        state0, params = differentiable.split_controls(st, c)

        def make(step):
            def loss(v, law):
                prm = {**params, "law": law}
                s = jax.lax.scan(lambda s, _: (step(s, prm), None), {**state0, "v": v}, None, length=N)[0]
                return jnp.sum(s["x"] * s["x"])
            return loss

        plain = make(st.step_fn)
        remat = make(jax.checkpoint(st.step_fn))
        args = (c["v"], params["law"])
        for name, f in (("plain_fwd", jax.jit(plain)), ("plain_grad", jax.jit(jax.value_and_grad(plain, (0, 1)))),
                        ("remat_grad", jax.jit(jax.value_and_grad(remat, (0, 1))))):
            comp = f.lower(*args).compile()
            res[f"{name}_xla"] = mem_stats(comp.memory_analysis())
            res[f"{name}_s"], _ = _time(lambda: jax.block_until_ready(comp(*args)), reps)
        res["ratio_plain"] = res["plain_grad_s"] / res["plain_fwd_s"]
        res["ratio_remat"] = res["remat_grad_s"] / res["plain_fwd_s"]
    else:
        import warp as wp
        from mpmlab.backends.warp import grad as wgrad

        st = build(spec, "warp")
        s0 = st.init()
        res["fast_s"], _ = _time(lambda: st._block(st._advance(s0, N)), reps)
        path = wgrad.path_of(st)
        names, flat = path.flatten(st.controls())

        def run(grad):
            ctl = path.to_warp(names, flat, grad=grad)
            tape = wp.Tape() if grad else None
            t = 0.0
            with (tape if grad else _null()):
                s = path.initial(ctl, grad)
                for _ in range(N):
                    s = path.step(s, ctl, t, grad)
                    t += st.dt
            return s, tape

        def fwd():
            run(False)

        res["path_fwd_s"], _ = _time(fwd, reps)
        tf, tb = [], []
        for _ in range(reps + 1):
            t0 = time.perf_counter()
            s, tape = run(True)
            t1 = time.perf_counter()
            x = wp.to_torch(s.x)
            wp.to_torch(s.x.grad).copy_(2 * x)
            tape.backward()
            tb.append(time.perf_counter() - t1)
            tf.append(t1 - t0)
            del s, tape
        res["tape_fwd_s"], res["tape_bwd_s"] = float(np.median(tf[1:])), float(np.median(tb[1:]))
        res["plain_grad_s"] = res["tape_fwd_s"] + res["tape_bwd_s"]
        res["plain_fwd_s"] = res["path_fwd_s"]
        res["ratio_plain"] = res["plain_grad_s"] / res["path_fwd_s"]
        # per kernel, generated and hand-written adjoints (recorded functions timed by their own
        # forward and backward: benchmarks/_adjoint_split_warp.py)
        from _adjoint_split_warp import kernel_split

        res["kernels"] = kernel_split(st, steps=min(N, 20), reps=reps)
    return res


class _null:
    def __enter__(self):
        return self

    def __exit__(self, *a):
        return False


def worker_info(spec):
    """Versions, machine, and the scene's sizes (in a worker: the parent stays small, see main)."""
    st = build(spec, "jax")
    return {"machine": machine_info(), "state_bytes": jax_state_bytes(st), "particles": st.particles.count,
            "grid": list(st.scene.grid_shape), "dt": float(st.dt)}


# ---- the JAX elastic step: the SVD before / after (issue 17) -----------------------------------------------
ELASTIC_RESULT = H.RESULTS / "elastic_step.json"
#: (label, backend, JAX SVD implementation, Warp threads); None: mpmlab's default (one thread per 4096
#: particles, as in stage_profile.py's 5.4 ms)
ELASTIC_VARIANTS = (("jax, jnp.linalg.svd (parent commit)", "jax", "lapack", None),
                    ("jax, Jacobi SVD", "jax", "jacobi", None),
                    ("warp", "warp", None, None),
                    ("warp, all cores", "warp", None, len(os.sched_getaffinity(0))))


def worker_elastic(spec):
    """Every variant of ELASTIC_VARIANTS in this one process: step time in interleaved rounds, then the
    gradient through ``grad_steps`` steps (module docstring)."""
    import contextlib

    import jax
    import jax.numpy as jnp
    import mpmlab
    from mpmlab.backends.jax import linalg
    from mpmlab.observations import Lagrangian

    H.quiet_warp(None)
    svd = lambda impl: linalg.svd_impl(impl) if impl else contextlib.nullcontext()
    steps, N = spec["steps"], spec["grad_steps"]
    obs = Lagrangian(quantity="x")
    runs = []
    for label, backend, impl, threads in ELASTIC_VARIANTS:
        # every call of a JAX variant runs under its SVD: the switch is read when a program is traced
        opts = {} if threads is None else {"threads": threads}
        with svd(impl):
            st = mpmlab.build_stepper(H.throughput_scene("cube", 3, spec["n_grid"]), backend, "mls",
                                      spec["precision"], **opts)
            t0 = time.perf_counter()
            s0 = st.init()
            st._block(st._advance(s0, steps))
            first = time.perf_counter() - t0
        runs.append({"label": label, "backend": backend, "svd": impl, "st": st, "s0": s0, "step_s": [],
                     "first_s": first, "threads": getattr(st, "threads", None) if backend == "warp" else None})
    for _ in range(spec["rounds"]):
        for r in runs:
            with svd(r["svd"]):
                t0 = time.perf_counter()
                out = r["st"]._advance(r["s0"], steps)
                r["st"]._block(out)
                r["step_s"].append((time.perf_counter() - t0) / steps)
            r["x"] = np.asarray(r["st"].to_numpy(out)["x"], float)
    for r in runs:
        with svd(r["svd"]):
            st = r["st"]
            if r["backend"] == "jax":
                c = st.controls()
                p = (c["v"], c["law"])

                def loss(p, c, st=st):
                    y = st.observe({**c, "v": p[0], "law": p[1]}, obs, steps=[N], segment=N)
                    return jnp.sum(y * y)

                fwd_c, grad_c = jax.jit(loss), jax.jit(jax.value_and_grad(loss))
                t0 = time.perf_counter()
                fwd_c, grad_c = fwd_c.lower(p, c).compile(), grad_c.lower(p, c).compile()
                r["grad_compile_s"] = time.perf_counter() - t0
                r["fwd"] = lambda f=fwd_c, p=p, c=c: float(f(p, c))
                r["grad"] = lambda g=grad_c, p=p, c=c: jax.block_until_ready(g(p, c))
            else:
                r["fwd"], r["grad"] = warp_fns(st, N, N)
            t0 = time.perf_counter()
            out = r["grad"]()
            r["grad_first_s"] = time.perf_counter() - t0
            leaves = list(_leaves(out[1:] if r["backend"] == "warp" else out[1]))
            r["grad_finite"] = bool(all(np.all(np.isfinite(np.asarray(a))) for a in leaves))
            r["fwd_s"], r["grad_s"] = [], []
    for _ in range(spec["reps"]):
        for r in runs:
            with svd(r["svd"]):
                for key in ("fwd", "grad"):
                    t0 = time.perf_counter()
                    r[key]()
                    r[f"{key}_s"].append(time.perf_counter() - t0)
    jx = [r for r in runs if r["backend"] == "jax"]
    extent = float(np.abs(jx[0]["x"]).max())
    rows = []
    for r in runs:
        rows.append({k: r[k] for k in ("label", "backend", "svd", "threads", "first_s", "step_s", "grad_compile_s",
                                       "grad_first_s", "grad_finite", "fwd_s", "grad_s") if k in r})
        rows[-1].update(step_ms_best=1e3 * min(r["step_s"]), step_ms_median=1e3 * float(np.median(r["step_s"])),
                        grad_fwd_s=float(np.median(r["fwd_s"])), grad_total_s=float(np.median(r["grad_s"])))
        rows[-1]["x_vs_first_jax"] = float(np.abs(r["x"] - jx[0]["x"]).max()) / extent
    return {"particles": int(runs[0]["st"].particles.count), "rows": rows,
            "machine": H.machine_info(("jax", "warp", "torch"))}


WORKERS = {"info": worker_info, "compile": worker_compile, "warm": worker_warm, "measure": worker_measure,
           "breakdown": worker_breakdown, "elastic": worker_elastic}


def run_worker(kind, spec, log, timeout=900):
    cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", kind, "--spec", json.dumps(spec)]
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    env.update(spec.get("env", {}))
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=env)
    line = next((l for l in reversed(r.stdout.splitlines()) if l.startswith("RESULT ")), None)
    for l in r.stderr.splitlines():
        if l.startswith("  compiled"):
            log(l)
    if r.returncode != 0 or line is None:
        raise RuntimeError(f"worker {kind} {spec.get('backend', '')} failed (exit {r.returncode}): "
                           f"{r.stderr.strip()[-1500:]}")
    return json.loads(line[len("RESULT "):])


# ---- report -----------------------------------------------------------------------------------------------
def machine_info() -> dict:
    return H.machine_info(("jax", "warp", "torch"), with_platform=True, load=True)


def _xla_temp(res, r):
    x = res.get("compile", {}).get(r["label"], {}).get("grad", {}).get(f"{r['N']},{r['n']}", {}).get("xla", {})
    return x.get("temp_size_in_bytes")


def n_steps(N, n) -> int:
    """The segment length a row ran with: ``"auto"`` keeps every step state when it fits (n = N)."""
    return N if isinstance(n, str) else n


def n_key(N, n) -> float:
    """Sort key: segments by length, ``"auto"`` after n = N."""
    return N + 0.5 if n == "auto" else float(n)


def model_mib(res, N, n):
    n = n_steps(N, n)
    return (np.ceil(N / n) + n) * res["state_bytes"] / MiB


def row_md(res, r):
    xt = _xla_temp(res, r) if r["backend"] == "jax" else None
    comp = res.get("compile", {}).get(r["label"], {}).get("grad", {}).get(f"{r['N']},{r['n']}", {}).get("compile_s")
    first = f"{comp:.1f} (compile)" if (r["backend"] == "jax" and comp is not None) else \
        f"{r['grad_load_s']:.2f} (load)"
    nn = n_steps(r["N"], r["n"])
    return (f"| {r['label']} | {r['N']} | {r['n']} | {np.ceil(r['N'] / nn) + nn:.0f} | "
            f"{r['peak_mib']:.1f} | {r['peak_sampled_mib']:.1f} | "
            f"{(f'{xt / MiB:.1f}' if xt is not None else '-')} | {model_mib(res, r['N'], r['n']):.1f} | "
            f"{r['maxrss_base_mib']:.0f} / {r['maxrss_grad_mib']:.0f} | "
            f"{r['fwd_s']:.3f} | {r['grad_s']:.3f} | **{r['ratio']:.1f}x** | {first} |")


HEADER = "\n".join(H.md_table(["backend", "N", "n", "N/n + n", "peak (MiB)", "peak, sampled (MiB)", "XLA temp (MiB)",
                               "model (MiB)", "ru_maxrss base / grad (MiB)", "forward (s)", "fwd+bwd (s)", "ratio",
                               "first (s)"]))


def tables(res) -> str:
    m = res["machine"]
    sp = res["spec"]
    L = []
    L.append(f"Measured {res['date']} on {m['cpu']} ({m['cores']} cores, shared; load average "
             f"{m['load_before']} before the run, {m.get('load_after', '?')} after), {m['platform']}, no GPU; "
             f"Python {m['python']}, JAX {m['jax']} (CPU, XLA's own threads), Warp {m['warp']} (CPU device; "
             f"the gradient path is single-threaded), torch {m['torch']}. Regenerate with "
             "`python benchmarks/gradients.py` (method in its docstring; raw numbers in "
             "`benchmarks/out/gradients.json`, plot `benchmarks/out/gradients.png`).\n")
    L.append(f"Scene: 2D Ritter dam break (`ritter_dam_break(dx={sp['dx']})`), {res['particles']} particles, "
             f"{res['grid'][0]} x {res['grid'][1]} grid nodes, dt = {res['dt']:.3g} s, {sp['transfer']}, "
             f"{sp['precision']}. Loss = sum of squares of all particle positions after N steps "
             "(`observe(c, Lagrangian('x'), steps=[N], segment=n)`), gradient w.r.t. the initial velocity "
             "and the law parameters. One simulation state (x, v, C, J, sigma) is "
             f"{res['state_bytes'] / 1024:.0f} KiB; *model* = (N/n + n) states.\n")
    L.append("How measured: each row is a fresh process with compilation kept out of it (JAX: compiled "
             "beforehand into a persistent compilation cache and loaded from it; Warp: kernels from its "
             "disk cache). *peak* = `ru_maxrss` after one gradient call minus `ru_maxrss` after building "
             "the stepper, one forward-only `observe` (segment = N) and loading the gradient program / "
             "backward kernels; *peak, sampled* = the highest resident size sampled every 1 ms during the "
             "call minus the size just before it; *XLA temp* = `jax.jit(grad).lower(c).compile()"
             ".memory_analysis()` temp bytes (exact for the compiled program). *forward* = the same "
             "observe with segment = N under no gradient, *fwd+bwd* = loss and gradient; medians of "
             f"{sp['reps']} alternating repeats after a warm-up; *ratio* = fwd+bwd / forward; *first* = "
             "JAX compile time of the gradient program (fresh, in the compile process); Warp: a 2-step "
             "gradient that loads the backward kernels from Warp's disk cache.\n")
    order = {lab: i for i, lab in enumerate(dict.fromkeys(r["label"] for r in res["rows"]))}
    seg = sorted([r for r in res["rows"] if r["N"] == sp["N"] and not r.get("baseline")],
                 key=lambda r: (order[r["label"]], n_key(r["N"], r["n"])))
    L.append(f"**Segment length** (N = {sp['N']} steps):\n")
    L.append(HEADER)
    L += [row_md(res, r) for r in seg]
    scal = sorted([r for r in res["rows"] if r["label"] == r["backend"] and
                   (r["N"] != sp["N"] or r["n"] in (sp["scaling_segment"], sp["N"]))],
                  key=lambda r: (order[r["label"]], r["n"] == r["N"], r["N"], n_key(r["N"], r["n"])))
    L.append(f"\n**Steps** (n = {sp['scaling_segment']} vs n = N, i.e. no recomputation):\n")
    L.append(HEADER)
    L += [row_md(res, r) for r in scal]
    if res.get("breakdown"):
        L.append(f"\n**Where the time goes** (N = {sp['N']}, medians of {sp['reps']}): *fast* = the "
                 "non-differentiable stepper (`_advance`); *grad path fwd* = the differentiable path's forward "
                 "(JAX: plain `lax.scan` of the step, the same program as the forward above; Warp: fresh "
                 "arrays per step, atomic P2G, no tape); *no recompute* = gradient with every intermediate "
                 "kept (O(N) memory: JAX `value_and_grad` of the plain scan, Warp one `wp.Tape` over all N "
                 "steps); *step remat* = JAX with `jax.checkpoint` on each step only.\n")
        L += H.md_table(["backend", "fast (s)", "grad path fwd (s)", "no recompute: fwd+bwd (s)", "ratio",
                         "step remat only (s)", "ratio", "XLA temp, no recompute (MiB)"])
        for b in res["breakdown"]:
            if b["backend"] == "jax":
                L.append(f"| {b.get('label', 'jax')} | {b['fast_s']:.3f} | {b['plain_fwd_s']:.3f} | {b['plain_grad_s']:.3f} | "
                         f"{b['ratio_plain']:.1f}x | {b['remat_grad_s']:.3f} | {b['ratio_remat']:.1f}x | "
                         f"{b['plain_grad_xla'].get('temp_size_in_bytes', 0) / MiB:.0f} |")
            else:
                L.append(f"| warp | {b['fast_s']:.3f} | {b['path_fwd_s']:.3f} | {b['plain_grad_s']:.3f} "
                         f"(tape fwd {b['tape_fwd_s']:.3f} + bwd {b['tape_bwd_s']:.3f}) | {b['ratio_plain']:.1f}x | "
                         f"- | - | - |")
        kern = next((b["kernels"] for b in res["breakdown"] if b.get("kernels")), None)
        if kern:
            if "fwd_ms" in next(iter(kern.values())):          # a JSON from before the hand-written adjoints
                kern = {"generated": dict(kern, all={"fwd_ms": sum(v["fwd_ms"] for v in kern.values()),
                                                     "adj_ms": sum(v["adj_ms"] for v in kern.values())})}
            L.append("\n**Warp, per kernel** (ms per step; each launch of a 20-step tape replayed alone, the "
                     "adjoint kinds alternating, minimum over the rounds; *generated*: Warp's generated adjoint, "
                     "which replays the forward body first; *hand*: `mpmlab/backends/warp/adjoints.py`):\n")
            L += H.md_table(["adjoint", "kernel", "forward (ms)", "adjoint (ms)", "adjoint / forward"])
            for kind, groups in kern.items():
                for k, v in groups.items():
                    L.append(f"| {kind} | {k} | {v['fwd_ms']:.3f} | {v['adj_ms']:.3f} | "
                             f"{v['adj_ms'] / v['fwd_ms']:.2f}x |")
    L += baseline_table(res)
    L.append("\n**Summary** (generated):\n")
    for lab in order:
        rows = [r for r in res["rows"] if r["label"] == lab]
        ratios = [r["ratio"] for r in rows]
        at = sorted([r for r in rows if r["N"] == sp["N"]], key=lambda r: n_key(r["N"], r["n"]))
        line = f"* {lab}: fwd+bwd / forward = {min(ratios):.1f}x - {max(ratios):.1f}x over {len(rows)} runs: " + \
               ("target <= 3x **met**" if max(ratios) <= 3 else "target <= 3x **not met**")
        if at:
            best = min(at, key=lambda r: r["peak_mib"])
            full = next((r for r in at if r["n"] == sp["N"]), None)
            line += (f". At N = {sp['N']} the smallest peak is at n = {best['n']} ({best['peak_mib']:.1f} MiB"
                     + (f", vs {full['peak_mib']:.1f} MiB without recomputation, n = N" if full else "") + ")")
        ok = all(r.get("grad_finite", True) for r in rows)
        L.append(line + ("" if ok else "; NON-FINITE gradients in some runs") + ".")
    if res.get("notes"):
        L.append("\n" + res["notes"])
    return "\n".join(L) + "\n"


def baseline_table(res) -> list[str]:
    """Before / after: the same workers on the baseline commit's mpmlab (a temporary worktree on
    PYTHONPATH) in the same run, beside this checkout's rows at the same (N, n), and its ``auto`` row."""
    base = [r for r in res["rows"] if r.get("baseline")]
    if not base:
        return []
    ref = res.get("baseline", {})
    L = [f"\n**Before / after** (the baseline `{ref.get('ref', '?')}` = {ref.get('commit', '?')} measured in the "
         "same run, same workers, its mpmlab from a temporary `git worktree` on `PYTHONPATH`; *after* = this "
         "checkout; n = auto: `segment='auto'`, every step state kept when it fits the memory budget):\n"]
    L += H.md_table(["backend", "N", "n", "before: forward (s)", "before: fwd+bwd (s)", "before: ratio",
                     "after: forward (s)", "after: fwd+bwd (s)", "after: ratio"])
    now = {(r["label"], r["N"], str(r["n"])): r for r in res["rows"] if not r.get("baseline")}
    for b in base:
        a = now.get((b["backend"], b["N"], str(b["n"])))
        cells = [b["backend"], b["N"], b["n"], f"{b['fwd_s']:.3f}", f"{b['grad_s']:.3f}", f"{b['ratio']:.1f}x"]
        cells += ([f"{a['fwd_s']:.3f}", f"{a['grad_s']:.3f}", f"**{a['ratio']:.1f}x**"] if a else ["-"] * 3)
        L.append(H.md_row(cells))
        auto = now.get((b["backend"], b["N"], "auto"))
        if auto and b["n"] == b["N"]:
            L.append(H.md_row([b["backend"], b["N"], "auto", "-", "-", "-", f"{auto['fwd_s']:.3f}",
                               f"{auto['grad_s']:.3f}", f"**{auto['ratio']:.1f}x**"]))
    return L


def worktree(ref: str):
    """A temporary detached worktree of ``ref`` (removed by the returned context manager)."""
    import contextlib

    @contextlib.contextmanager
    def cm():
        path = tempfile.mkdtemp(prefix="mpmlab-baseline-")
        git = lambda *a: subprocess.run(["git", "-C", str(H.ROOT), *a], capture_output=True, text=True, check=True)
        git("worktree", "add", "--detach", "--force", path, ref)
        try:
            yield path, git("rev-parse", "--short", ref).stdout.strip()
        finally:
            subprocess.run(["git", "-C", str(H.ROOT), "worktree", "remove", "--force", path], capture_output=True)
    return cm()


def git_commit() -> str:
    """HEAD's short hash, and the tracked files that differ from it (the measured code is HEAD + those)."""
    def git(*a):
        return subprocess.run(["git", "-C", str(H.ROOT), *a], capture_output=True, text=True).stdout
    edited = [l[3:] for l in git("status", "--porcelain", "--untracked-files=no").splitlines() if l.strip()]
    return git("rev-parse", "--short", "HEAD").strip() + (f" (+ edits to {', '.join(edited)})" if edited else "")


def run_elastic(args, log) -> dict:
    if args.quick:
        args.elastic_steps, args.elastic_rounds, args.elastic_grad_steps = 20, 2, 5
    spec = {"n_grid": args.elastic_n_grid, "precision": "fp32", "steps": args.elastic_steps,
            "rounds": args.elastic_rounds, "grad_steps": args.elastic_grad_steps, "reps": args.reps}
    load_before, t0 = H.load_average(), time.perf_counter()
    log(f"elastic step: {len(ELASTIC_VARIANTS)} variants, {spec['rounds']} rounds of {spec['steps']} steps, "
        f"gradients through {spec['grad_steps']} steps")
    res = run_worker("elastic", spec, log, timeout=1800)
    res["machine"].update(load_before=load_before, load_after=H.load_average())
    res.update(date=time.strftime("%Y-%m-%d %H:%M"), commit=git_commit(), spec=spec, total_s=time.perf_counter() - t0)
    for r in res["rows"]:
        log(f"  {r['label']}: {r['step_ms_best']:.2f} ms/step (median {r['step_ms_median']:.2f}), gradient "
            f"{r['grad_total_s']:.3f} s vs forward {r['grad_fwd_s']:.3f} s")
    return res


def elastic_tables(e) -> str:
    m, sp = e["machine"], e["spec"]
    rows = {r["label"]: r for r in e["rows"]}
    lapack, jacobi = (next(r for r in e["rows"] if r.get("svd") == k) for k in ("lapack", "jacobi"))
    warp = next(r for r in e["rows"] if r["backend"] == "warp" and r["label"] == "warp")
    L = [f"Measured {e['date']} at commit {e['commit']} on {m['cpu']} ({m['cores']} cores, shared; load average "
         f"{m['load_before']} before the run, {m['load_after']} after), JAX {m['jax']} (XLA's own threads), "
         f"Warp {m['warp']}. Regenerate with `python benchmarks/gradients.py --elastic-only` (method in its "
         "docstring; raw numbers in `benchmarks/results/elastic_step.json`).\n",
         f"Scene: the 3D fixed-corotated elastic cube of `stage_profile.py` (`elastic_cube`, n_grid "
         f"{sp['n_grid']}, {e['particles']} particles), MLS, {sp['precision']}. *step* = `stepper._advance(state, "
         f"{sp['steps']})` per step, best and median of {sp['rounds']} interleaved rounds in one process; "
         f"*gradient* = loss and gradient of sum(x^2) after {sp['grad_steps']} steps w.r.t. (v0, E, nu) (JAX: "
         "`value_and_grad` of `observe`, no recomputation; Warp: torch autograd), median of "
         f"{sp['reps']}, against the same forward alone; *x vs parent* = max |x - x_parent| / max |x| after "
         f"{sp['steps']} steps.\n"]
    L += H.md_table(["variant", "step best (ms)", "step median (ms)", "vs Warp (best)", "first call (s)",
                     f"gradient, {sp['grad_steps']} steps (s)", "forward (s)", "ratio", "x vs parent"])
    for lab, r in rows.items():
        thr = f" ({r['threads']} thr)" if r.get("threads") else ""
        L.append(H.md_row([lab + thr, f"{r['step_ms_best']:.2f}", f"{r['step_ms_median']:.2f}",
                           f"{r['step_ms_best'] / warp['step_ms_best']:.2f}x", f"{r['first_s']:.1f}",
                           f"{r['grad_total_s']:.3f}", f"{r['grad_fwd_s']:.3f}",
                           f"{r['grad_total_s'] / r['grad_fwd_s']:.1f}x", f"{r['x_vs_first_jax']:.1e}"]))
    ratio = jacobi["step_ms_best"] / warp["step_ms_best"]
    L.append(f"\n**Summary** (generated): the Jacobi SVD makes the JAX step "
             f"{lapack['step_ms_best'] / jacobi['step_ms_best']:.1f}x faster than with `jnp.linalg.svd` "
             f"({lapack['step_ms_best']:.2f} -> {jacobi['step_ms_best']:.2f} ms) and its gradient through "
             f"{sp['grad_steps']} steps {lapack['grad_total_s'] / jacobi['grad_total_s']:.1f}x "
             f"({lapack['grad_total_s']:.3f} -> {jacobi['grad_total_s']:.3f} s); JAX / Warp = {ratio:.2f} "
             f"(Warp {warp['step_ms_best']:.2f} ms, default threads): target JAX <= 1.5x Warp "
             + ("**met**." if ratio <= 1.5 else "**not met**."))
    return "\n".join(L) + "\n"


def write_readme(path: Path, body: str, title="Gradients: memory and time", name="gradients"):
    H.write_readme_section(path, name, title, body)


def plot(res, path: Path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sp = res["spec"]
    fig, ax = plt.subplots(1, 2, figsize=(11, 4.2))
    labels = list(dict.fromkeys(r["label"] for r in res["rows"]))
    palette = ["tab:blue", "tab:orange", "tab:cyan", "tab:red"]
    colors = {lab: palette[i % len(palette)] for i, lab in enumerate(labels)}
    a = ax[0]
    for b in labels:
        rows = sorted([r for r in res["rows"] if r["label"] == b and r["N"] == sp["N"] and r["n"] != "auto"
                       and not r.get("baseline")], key=lambda r: r["n"])
        if not rows:
            continue
        n = [r["n"] for r in rows]
        a.plot(n, [r["peak_mib"] for r in rows], "o-", color=colors[b], label=f"{b}: ru_maxrss peak")
        a.plot(n, [r["peak_sampled_mib"] for r in rows], "s:", color=colors[b], alpha=0.7, label=f"{b}: sampled RSS peak")
        if b == "jax":
            xt = [_xla_temp(res, r) for r in rows]
            if all(x is not None for x in xt):
                a.plot(n, [x / MiB for x in xt], "^--", color="tab:purple", label="jax: XLA temp bytes")
    nn = np.array(sorted({r["n"] for r in res["rows"] if r["N"] == sp["N"] and r["n"] != "auto"}))
    if nn.size:
        a.plot(nn, model_mib(res, sp["N"], nn), "k-", lw=0.8, alpha=0.6, label="(N/n + n) x state size")
    a.set_xscale("log")
    if nn.size:
        a.set_xticks(nn)
        a.set_xticklabels([str(v) for v in nn])
        a.minorticks_off()
    a.set_xlabel("segment length n (steps)")
    a.set_ylabel("peak memory of the gradient call (MiB)")
    a.set_title(f"N = {sp['N']} steps, {res['particles']} particles")
    a.legend(fontsize=7)
    a.grid(alpha=0.3)
    a = ax[1]
    for b in [lab for lab in labels if lab in ("jax", "warp")]:
        for kind, style in (("seg", "o-"), ("full", "x--")):
            rows = sorted([r for r in res["rows"] if r["label"] == b and
                           ((r["n"] == sp["scaling_segment"]) if kind == "seg" else (r["n"] == r["N"]))],
                          key=lambda r: r["N"])
            if rows:
                a.plot([r["N"] for r in rows], [max(r["peak_mib"], 0.1) for r in rows], style, color=colors[b],
                       label=f"{b}: n = {sp['scaling_segment']}" if kind == "seg" else f"{b}: n = N")
    NN = np.array(sorted({r["N"] for r in res["rows"]}))
    a.plot(NN, model_mib(res, NN, sp["scaling_segment"]), "k-", lw=0.8, alpha=0.6,
           label=f"model n = {sp['scaling_segment']}")
    a.plot(NN, model_mib(res, NN, NN), "k--", lw=0.8, alpha=0.6, label="model n = N")
    a.set_xscale("log")
    a.set_yscale("log")                   # (a zero peak is drawn at 0.1 MiB)
    a.set_xticks(NN)
    a.set_xticklabels([str(v) for v in NN])
    a.minorticks_off()
    a.set_xlabel("steps N")
    a.set_ylabel("peak memory (ru_maxrss delta, MiB)")
    a.set_title("memory vs steps")
    a.legend(fontsize=7)
    a.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ---- main ------------------------------------------------------------------------------------------------------
def main(argv=None):
    ap = H.parser(__doc__.split("\n")[0])
    H.add_backends(ap)
    ap.add_argument("--N", type=int, default=400, help="steps of the segment-length sweep")
    ap.add_argument("--segments", default="1,10,20,50,100,400,auto",
                    help="segment lengths n at --N (n > N dropped; 'auto': keep every step state when it fits)")
    ap.add_argument("--baseline", default="",
                    help="git ref measured in the same run for the before/after table (e.g. the commit before a change)")
    ap.add_argument("--baseline-segments", default="20,400", help="segment lengths (at --N) of the baseline rows")
    ap.add_argument("--scaling-N", default="100,200,400,800", help="steps of the N sweep")
    ap.add_argument("--scaling-segment", type=int, default=20, help="segment length of the N sweep (and n = N)")
    ap.add_argument("--reps", type=int, default=5, help="timed repeats (median)")
    ap.add_argument("--dx", type=float, default=0.0125, help="dam-break cell size (0.0125: 2560 particles)")
    ap.add_argument("--transfer", default="apic")
    ap.add_argument("--precision", default="fp32")
    ap.add_argument("--no-breakdown", action="store_true", help="skip the where-the-time-goes runs")
    ap.add_argument("--jax-variant-flags", default="--xla_cpu_experimental_ynn_fusion_type=",
                    help="XLA_FLAGS of an extra JAX run of the segment sweep ('' to skip)")
    ap.add_argument("--jax-variant-label", default="jax, YNN off")
    H.add_quick(ap, "N = 40, n in {5, 40, auto}, N sweep {20, 40}, dx 0.025")
    ap.add_argument("--merge", action="store_true",
                    help="keep the rows of variants not run now from the existing --out JSON (e.g. --backends warp)")
    ap.add_argument("--render", action="store_true", help="only rewrite the README section and plot from --out")
    ap.add_argument("--elastic-only", action="store_true",
                    help="only the JAX elastic step, SVD before / after (with --render: its README section from its JSON)")
    ap.add_argument("--no-elastic", action="store_true", help="skip the JAX elastic step")
    ap.add_argument("--elastic-n-grid", type=int, default=32)
    ap.add_argument("--elastic-steps", type=int, default=100, help="steps per timed round of the elastic step")
    ap.add_argument("--elastic-rounds", type=int, default=5)
    ap.add_argument("--elastic-grad-steps", type=int, default=20, help="steps of the elastic step's gradient")
    ap.add_argument("--out", default=str(H.OUT / "gradients.json"))
    ap.add_argument("--plot", default=str(H.OUT / "gradients.png"))
    H.add_readme(ap)
    ap.add_argument("--worker", choices=sorted(WORKERS), help=argparse.SUPPRESS)
    ap.add_argument("--spec", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)

    if args.worker:
        res = WORKERS[args.worker](json.loads(args.spec))
        print("RESULT " + json.dumps(res), flush=True)
        return res

    log = lambda *a: H.log(*a, err=True)
    out = Path(args.out)
    if args.elastic_only:
        e = H.read_json(ELASTIC_RESULT) if args.render else run_elastic(args, log)
        if not args.render:
            H.write_json(ELASTIC_RESULT, e)
        return report_elastic(e, args)
    if args.render:
        res = json.loads(out.read_text())
        return report(res, args)
    if args.quick:
        args.N, args.segments, args.scaling_N, args.scaling_segment, args.dx = 40, "5,40,auto", "20,40", 5, 0.025
        args.baseline_segments = "5,40"
    backends = args.backends.split(",")
    N = args.N
    # (label, backend, environment, configs): the JAX variant re-runs the segment sweep with XLA CPU's
    # YNNPACK fusions off (see the README: they make the small reductions of the step's transpose slow)
    variants = [(b, b, {}, "all") for b in backends]
    if "jax" in backends and args.jax_variant_flags:
        variants.append((args.jax_variant_label, "jax", {"XLA_FLAGS": args.jax_variant_flags}, "segments"))
    segs = [s if s == "auto" else int(s) for s in (t.strip() for t in args.segments.split(","))]
    segs = [n for n in segs if n == "auto" or n <= N]
    configs = [(N, n) for n in segs]
    for M in (int(s) for s in args.scaling_N.split(",")):
        for n in (args.scaling_segment, M):
            if n <= M and (M, n) not in configs:
                configs.append((M, n))
    spec = {"dx": args.dx, "transfer": args.transfer, "precision": args.precision, "N": N, "segments": segs,
            "scaling_N": [int(s) for s in args.scaling_N.split(",")], "scaling_segment": args.scaling_segment,
            "reps": args.reps}
    # This process never imports JAX, Warp or torch: a child's ru_maxrss starts at its parent's peak
    # (Linux carries the high-water mark through fork/vfork + execve), so the parent must stay below
    # what the measured processes reach before their baseline.
    t_start = time.perf_counter()
    res = {"date": time.strftime("%Y-%m-%d %H:%M"), "spec": spec, "rows": [], "breakdown": [], "configs": configs}
    with tempfile.TemporaryDirectory(prefix="mpmlab-gradbench-") as cache:
        base = dict(spec, cache=cache)
        res.update(run_worker("info", base, log))
        res["machine"]["parent_maxrss_mib"] = maxrss_mib()
        res["compile"] = {}
        for k, (label, b, env, which) in enumerate(variants):
            cfgs = configs if which == "all" else [(M, n) for M, n in configs if M == N]
            vbase = dict(base, env=env, cache=os.path.join(cache, str(k)), label=label)
            if b == "jax":
                log(f"{label}: compiling {len(cfgs)} gradient programs")
                res["compile"][label] = run_worker("compile", dict(vbase, configs=cfgs), log)
            else:
                res["warp_warm"] = run_worker("warm", dict(vbase, backend=b), log)
            for M, n in cfgs:
                r = run_worker("measure", dict(vbase, backend=b, N=M, n=n), log)
                r.update(label=label, env=env)
                res["rows"].append(r)
                log(f"{label} N={M} n={n}: peak {r['peak_mib']:.1f} MiB (sampled {r['peak_sampled_mib']:.1f}; "
                    f"maxrss {r['maxrss_base_mib']:.0f} -> {r['maxrss_grad_mib']:.0f}), fwd {r['fwd_s']:.3f} s, "
                    f"fwd+bwd {r['grad_s']:.3f} s, ratio {r['ratio']:.1f}x; loss {r['loss']:.6g}, "
                    f"|dL/dv| {r['grad_v_norm']:.6g}")
            if not args.no_breakdown:
                bd = run_worker("breakdown", dict(vbase, backend=b, N=N), log)
                bd.update(label=label, env=env)
                res["breakdown"].append(bd)
                log(f"{label} breakdown: {json.dumps({k: v for k, v in bd.items() if not k.endswith('xla')})}")
        if args.baseline:
            bsegs = [int(t) for t in args.baseline_segments.split(",") if int(t) <= N]
            with worktree(args.baseline) as (path, commit):
                res["baseline"] = {"ref": args.baseline, "commit": commit}
                for k, b in enumerate(backends):
                    label = f"{b} @ {commit}"
                    env = {"PYTHONPATH": path}
                    vbase = dict(base, env=env, cache=os.path.join(cache, f"baseline{k}"), label=label)
                    cfgs = [(N, n) for n in bsegs]
                    if b == "jax":
                        log(f"{label}: compiling {len(cfgs)} gradient programs")
                        res["compile"][label] = run_worker("compile", dict(vbase, configs=cfgs), log)
                    else:
                        run_worker("warm", dict(vbase, backend=b), log)
                    for M, n in cfgs:
                        r = run_worker("measure", dict(vbase, backend=b, N=M, n=n), log)
                        r.update(label=label, env=env, baseline=True)
                        res["rows"].append(r)
                        log(f"{label} N={M} n={n}: fwd {r['fwd_s']:.3f} s, fwd+bwd {r['grad_s']:.3f} s, "
                            f"ratio {r['ratio']:.1f}x; loss {r['loss']:.6g}, |dL/dv| {r['grad_v_norm']:.6g}")
    res["machine"]["parent_maxrss_mib_end"] = maxrss_mib()
    res["machine"]["load_after"] = H.load_average()
    res["total_s"] = time.perf_counter() - t_start
    if args.merge and out.exists():
        # keep the other variants' rows from the earlier run; say which rows were measured when
        old = json.loads(out.read_text())
        new_labels = {label for label, *_ in variants}
        label_of = lambda r: r.get("label", r["backend"])
        old_labels = sorted({label_of(r) for r in old["rows"]} - new_labels)
        res["rows"] = H.keep_rows(old["rows"], res["rows"], lambda r: label_of(r) in old_labels)
        res["breakdown"] = H.keep_rows(old.get("breakdown", []), res["breakdown"], lambda r: label_of(r) in old_labels)
        res["compile"] = {**{k: v for k, v in old.get("compile", {}).items() if k in old_labels}, **res["compile"]}
        res["date"] = f"{old['date']} ({', '.join(old_labels)} rows); {res['date']} ({', '.join(sorted(new_labels))} rows)"
    H.write_json(out, res)
    log(f"total {res['total_s']:.0f} s")
    if not args.no_elastic:
        e = run_elastic(args, log)
        H.write_json(ELASTIC_RESULT, e)
        report_elastic(e, args)
    return report(res, args)


def report_elastic(e, args):
    md = elastic_tables(e)
    print(md)
    if args.readme:
        write_readme(Path(args.readme), md, title="JAX elastic step: the SVD", name="elastic_step")
    return e


def report(res, args):
    for r in res["rows"] + res.get("breakdown", []):
        r.setdefault("label", r["backend"])
    md = tables(res)
    print(md)
    if args.plot:
        plot(res, Path(args.plot))
    if args.readme:
        write_readme(Path(args.readme), md)
    return res


if __name__ == "__main__":
    main()
