#!/usr/bin/env python
"""GPU checks and numbers: the Warp CUDA path and the JAX GPU path against the CPU, and their speed.

Three steps, the first here on the CPU, the others on a machine with an NVIDIA GPU::

    python benchmarks/gpu.py reference                       # CPU: benchmarks/out/gpu_reference.npz
    MPMLAB_WARP_DEVICE=cuda:0 python benchmarks/gpu.py check --out DIR   # GPU: DIR/gpu_check.json
    MPMLAB_WARP_DEVICE=cuda:0 python benchmarks/gpu.py grad --out DIR    # GPU: DIR/gpu_grad.json
    python benchmarks/gpu.py render --inputs DIR             # benchmarks/gpu.md from the JSON files

``MPMLAB_WARP_DEVICE`` is the Warp stepper's default device (``backend.device`` on the CLI); JAX takes
the GPU by itself when its CUDA plugin is installed (``JAX_PLATFORMS=cpu`` forces the CPU).

* ``reference`` / ``check``: every built-in law in one scene (``tests/scenes.py::all_laws_scene``: six
  bodies spinning onto walls) in 2D and 3D under every transfer, fp64, 40 steps of 1 ms, on each
  backend; and the Ritter dam break (fp32, 400 steps). ``check`` reruns them on the GPU and reports
  max |x_gpu - x_cpu| / dx per backend and between the backends on the GPU; plus the gradient of
  L = sum(x_N^2) (N = 20 steps, segment 5) w.r.t. the initial velocities and every law parameter,
  fp64, on both GPU backends beside the CPU reference (relative L2 difference per leaf).
* ``grad``: forward alone against forward+backward (N = 400 steps, segment n = 20) of the Ritter
  dam break at several particle counts, fp32, APIC, median of 5 after a warm-up, and the peak device
  memory of the gradient (JAX: XLA's buffer assignment of the compiled gradient program, temp bytes;
  Warp: the growth of Warp's memory-pool high-water mark during the gradient call).

Throughput (particle-steps/s) on the GPU comes from ``benchmarks/throughput.py`` run there with
``MPMLAB_WARP_DEVICE=cuda:0 --no-taichi --readme ''``; ``render`` tabulates it when its JSON is in
``--inputs`` (``throughput_gpu.json``).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))          # tests.scenes
TRANSFERS = ("pic", "flip", "apic", "mls", "tpic")
LAW_STEPS, LAW_DT = 40, 1e-3
GRAD_N, GRAD_SEG = 20, 5


def _device_info() -> dict:
    info = {"python": platform.python_version(), "machine": platform.node()}
    try:
        import jax
        info["jax"] = jax.__version__
        info["jax_devices"] = [str(d) for d in jax.devices()]
    except Exception as e:       # pragma: no cover - reporting only
        info["jax_error"] = repr(e)
    try:
        import warp as wp
        wp.init()
        info["warp"] = wp.config.version
        info["warp_devices"] = [str(d) for d in wp.get_devices()]
        if wp.is_cuda_available():
            info["gpu"] = wp.get_device("cuda:0").name
    except Exception as e:       # pragma: no cover
        info["warp_error"] = repr(e)
    info["warp_device"] = os.environ.get("MPMLAB_WARP_DEVICE", "cpu")
    return info


# ---- forward and gradient cases ---------------------------------------------------------------------
def law_cases():
    for dim in (2, 3):
        for tr in TRANSFERS:
            yield f"all_laws_{dim}d/{tr}", dim, tr


def run_forward(backend: str, dim: int, transfer: str) -> np.ndarray:
    from mpmlab.simulator import build_stepper
    from tests.scenes import all_laws_scene

    st = build_stepper(all_laws_scene(dim, dt=LAW_DT), backend, transfer, "fp64")
    traj = st.rollout(steps=LAW_STEPS, every=LAW_STEPS, progress=False)
    return np.stack([traj.x[-1], traj.v[-1]])


def run_dam(backend: str) -> np.ndarray:
    from mpmlab.scenes.validation import ritter_dam_break
    from mpmlab.simulator import build_stepper

    st = build_stepper(ritter_dam_break(dx=0.0125), backend, "apic", "fp32")
    traj = st.rollout(steps=400, every=400, progress=False)
    return np.stack([traj.x[-1], traj.v[-1]])


def run_gradient(backend: str, dim: int) -> dict[str, np.ndarray]:
    """d sum(x_N^2) / d (v0, law parameters), fp64, APIC, segment GRAD_SEG."""
    from mpmlab.observations import Lagrangian
    from mpmlab.simulator import build_stepper
    from tests.scenes import all_laws_scene

    st = build_stepper(all_laws_scene(dim, dt=LAW_DT), backend, "apic", "fp64")
    obs = Lagrangian(quantity="x")
    c = st.controls()
    if backend == "jax":
        import jax
        import jax.numpy as jnp

        def loss(p):
            y = st.observe({**c, "v": p[0], "law": p[1]}, obs, steps=[GRAD_N], segment=GRAD_SEG)
            return jnp.sum(y * y)

        _, g = jax.jit(jax.value_and_grad(loss))((c["v"], c["law"]))
        gv, glaw = g
    else:
        v = c["v"].detach().clone().requires_grad_(True)
        law = tuple(a.detach().clone().requires_grad_(True) for a in c["law"])
        y = st.observe({**c, "v": v, "law": law}, obs, steps=[GRAD_N], segment=GRAD_SEG)
        (y * y).sum().backward()
        gv, glaw = v.grad, [a.grad for a in law]
    arr = lambda a: np.asarray(a.detach().cpu().numpy() if hasattr(a, "detach") else a, dtype=float)
    out = {"v": arr(gv)}
    for k, a in enumerate(glaw):
        out[f"law{k}"] = arr(a)
    return out


def compute_all(backends) -> dict[str, np.ndarray]:
    res = {}
    for b in backends:
        for name, dim, tr in law_cases():
            t0 = time.perf_counter()
            res[f"{b}:{name}"] = run_forward(b, dim, tr)
            print(f"[gpu] {b} {name}: {time.perf_counter() - t0:.1f} s", flush=True)
        res[f"{b}:ritter/apic_fp32"] = run_dam(b)
        for dim in (2, 3):
            for k, a in run_gradient(b, dim).items():
                res[f"{b}:grad_{dim}d:{k}"] = a
            print(f"[gpu] {b} gradient {dim}d done", flush=True)
    return res


def cmd_reference(args):
    os.environ.setdefault("JAX_PLATFORMS", "cpu")
    if os.environ.get("MPMLAB_WARP_DEVICE", "cpu") != "cpu":
        sys.exit("reference: run it on the CPU (unset MPMLAB_WARP_DEVICE).")
    res = compute_all(args.backends.split(","))
    Path(args.reference).parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(args.reference, **res)
    print(f"[gpu] wrote {args.reference}")


def _rel(a, b):
    den = np.linalg.norm(b)
    return float(np.linalg.norm(a - b) / den) if den > 0 else float(np.linalg.norm(a - b))


def cmd_check(args):
    ref = dict(np.load(args.reference))
    info = _device_info()
    backends = args.backends.split(",")
    t0 = time.perf_counter()
    gpu = compute_all(backends)
    rows = []
    for key, a in gpu.items():
        b, case = key.split(":", 1)
        r = ref.get(key)
        row = {"backend": b, "case": case, "finite": bool(np.all(np.isfinite(a)))}
        dx = 0.0125 if case.startswith("ritter") else 0.05
        if case.startswith("grad"):
            row["rel_l2_vs_cpu"] = _rel(a, r) if r is not None else None
            other = gpu.get(f"{'warp' if b == 'jax' else 'jax'}:{case}")
            row["rel_l2_vs_other_gpu"] = _rel(a, other) if other is not None else None
        else:
            row["max_dx_vs_cpu"] = float(np.abs(a[0] - r[0]).max() / dx) if r is not None else None
            row["max_dv_vs_cpu"] = float(np.abs(a[1] - r[1]).max()) if r is not None else None
            other = gpu.get(f"{'warp' if b == 'jax' else 'jax'}:{case}")
            row["max_dx_vs_other_gpu"] = float(np.abs(a[0] - other[0]).max() / dx) if other is not None else None
        rows.append(row)
    out = {"info": info, "rows": rows, "wall_s": time.perf_counter() - t0}
    Path(args.out).mkdir(parents=True, exist_ok=True)
    (Path(args.out) / "gpu_check.json").write_text(json.dumps(out, indent=1))
    for r in rows:
        print(r)


# ---- gradient time and memory --------------------------------------------------------------------------
def _grad_case(backend: str, dx: float, N: int, n: int, reps: int) -> dict:
    from mpmlab.observations import Lagrangian
    from mpmlab.scenes.validation import ritter_dam_break
    from mpmlab.simulator import build_stepper

    st = build_stepper(ritter_dam_break(dx=dx), backend, "apic", "fp32")
    obs = Lagrangian(quantity="x")
    c = st.controls()
    res = {"backend": backend, "particles": st.particles.count, "dx": dx, "N": N, "n": n}
    if backend == "jax":
        import jax
        import jax.numpy as jnp

        def loss(p, segment):
            y = st.observe({**c, "v": p[0], "law": p[1]}, obs, steps=[N], segment=segment)
            return jnp.sum(y * y)

        p = (c["v"], c["law"])
        t0 = time.perf_counter()
        fwd_c = jax.jit(lambda p: loss(p, N)).lower(p).compile()
        grad_c = jax.jit(jax.value_and_grad(lambda p: loss(p, n))).lower(p).compile()
        res["compile_s"] = time.perf_counter() - t0
        ma = grad_c.memory_analysis()
        res["grad_temp_mib"] = getattr(ma, "temp_size_in_bytes", 0) / 2**20 if ma is not None else None
        ma = fwd_c.memory_analysis()
        res["fwd_temp_mib"] = getattr(ma, "temp_size_in_bytes", 0) / 2**20 if ma is not None else None
        fwd = lambda: jax.block_until_ready(fwd_c(p))
        grad = lambda: jax.block_until_ready(grad_c(p))
    else:
        import torch
        import warp as wp

        def fwd():
            with torch.no_grad():
                y = st.observe(c, obs, steps=[N], segment=N)
                float((y * y).sum())

        def grad():
            v = c["v"].detach().clone().requires_grad_(True)
            law = tuple(a.detach().clone().requires_grad_(True) for a in c["law"])
            y = st.observe({**c, "v": v, "law": law}, obs, steps=[N], segment=n)
            (y * y).sum().backward()
            wp.synchronize_device(st.device)

        t0 = time.perf_counter()
        fwd()
        grad()
        res["compile_s"] = time.perf_counter() - t0
        if str(st.device).startswith("cuda"):
            before = wp.get_mempool_used_mem_current(st.device)
            grad()
            res["grad_pool_high_mib"] = (wp.get_mempool_used_mem_high(st.device) - before) / 2**20
    fwd(); grad()                                   # warm
    tf, tg = [], []
    for _ in range(reps):
        t = time.perf_counter(); fwd(); tf.append(time.perf_counter() - t)
        t = time.perf_counter(); grad(); tg.append(time.perf_counter() - t)
    res["fwd_s"], res["grad_s"] = float(np.median(tf)), float(np.median(tg))
    res["ratio"] = res["grad_s"] / res["fwd_s"]
    res["fwd_particle_steps_per_s"] = st.particles.count * N / res["fwd_s"]
    return res


def cmd_grad(args):
    rows = []
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    for backend in args.backends.split(","):
        for dx in [float(x) for x in args.dx.split(",")]:
            for n in [int(x) for x in args.segments.split(",")]:
                t0 = time.perf_counter()
                try:
                    r = _grad_case(backend, dx, args.N, n, args.reps)
                except Exception as e:     # keep the other cases; the error is reported
                    r = {"backend": backend, "dx": dx, "n": n, "error": f"{type(e).__name__}: {e}"[:400]}
                r["wall_s"] = time.perf_counter() - t0
                print(r, flush=True)
                rows.append(r)
                (out_dir / "gpu_grad.json").write_text(json.dumps({"info": _device_info(), "rows": rows}, indent=1))


# ---- report ---------------------------------------------------------------------------------------------
def _fmt(x, f="{:.2e}"):
    return "-" if x is None else f.format(x)


def cmd_render(args):
    d = Path(args.inputs)
    lines = ["# mpmlab on a GPU", "",
             "Generated by `python benchmarks/gpu.py render` from the JSON files in `benchmarks/results/gpu/`, "
             "which `benchmarks/gpu.py check`, `benchmarks/gpu.py grad` and `benchmarks/throughput.py` wrote on "
             "the GPU machine (commands in the docstring of `benchmarks/gpu.py`). CI has no GPU: these numbers "
             "are reproduced by hand on a machine with one.", "",
             "Not yet checked on a GPU (30 device-minutes went to the runs below): boundaries other than the "
             "domain walls (friction walls, planes, obstacles, particle velocity/load, body force), Eulerian "
             "observations, and the `task=inverse` fits. `MPMLAB_WARP_DEVICE=cuda:0 python -m pytest tests/` "
             "runs the whole suite's Warp side on a GPU.", ""]
    chk = d / "gpu_check.json"
    if chk.exists():
        c = json.loads(chk.read_text())
        i = c["info"]
        rows = {(r.get("backend"), r["case"]): r for r in c["rows"]}
        lines += [f"Machine: {i.get('gpu', '?')}; JAX {i.get('jax')} on {', '.join(i.get('jax_devices', []))}; "
                  f"Warp {i.get('warp')} on {i.get('warp_device')}. The CPU reference (`gpu.py reference`) ran "
                  "on the 2-core development machine.", "",
                  "## Forward: GPU against CPU", "",
                  f"`all_laws_{{2,3}}d`: the six built-in laws in one scene (`tests/scenes.py`), fp64, {LAW_STEPS} "
                  "steps. Max |x_gpu - x_cpu| in cells (dx), per backend, and between JAX and Warp on the GPU; "
                  "`Warp first call` is the CUDA compile (NVRTC) of that scene's kernels plus the steps.", "",
                  "| case | JAX GPU vs JAX CPU | Warp CUDA vs Warp CPU | JAX GPU vs Warp CUDA | finite | Warp first call s |",
                  "|---|---|---|---|---|---|"]
        for case in sorted({r["case"] for r in c["rows"] if r["case"].startswith("all_laws")}):
            j, w = rows.get(("jax", case), {}), rows.get(("warp", case), {})
            lines.append(f"| {case} | {_fmt(j.get('max_dx_vs_cpu'))} | {_fmt(w.get('max_dx_vs_cpu'))} | "
                         f"{_fmt(j.get('max_dx_vs_other_gpu'))} | {j.get('finite', '-')} / {w.get('finite', '-')} | "
                         f"{_fmt(w.get('warp_first_call_s'), '{:.0f}')} |")
        dev = rows.get((None, "ritter/apic_fp32/dev_per_25_steps"))
        if dev:
            e = dev["dev"]
            lines += ["", f"The Ritter dam break (fp32, APIC, 2560 particles, 400 steps): JAX GPU against Warp CUDA, "
                      f"max |dx| in cells after 100 / 200 / 400 steps: {e[4]:.1e} / {e[8]:.1e} / {e[-1]:.1e} "
                      "(fp32 summation order only)."]
        lines += ["", "## Gradients: GPU against CPU", "",
                  f"d sum(x_N^2) / d(v0, law parameters) of the six-law scene, APIC, fp64, N = {GRAD_N}, segment "
                  f"{GRAD_SEG}: relative L2 difference per leaf (`law5` = drucker_prager_jaumann).", "",
                  "| leaf | JAX GPU vs JAX CPU | Warp CUDA vs Warp CPU |", "|---|---|---|"]
        for case in sorted({r["case"] for r in c["rows"] if r["case"].startswith("grad")}):
            j, w = rows.get(("jax", case), {}), rows.get(("warp", case), {})
            lines.append(f"| {case} | {_fmt(j.get('rel_l2_vs_cpu'))} | {_fmt(w.get('rel_l2_vs_cpu'))} |")
        lines.append("")
    before = d / "gpu_check_before_p2g_fix.json"
    if before.exists():
        b = json.loads(before.read_text())
        worst = max((r.get("max_dx_vs_cpu") or 0.0) for r in b["rows"]
                    if r.get("backend") == "warp" and r["case"].startswith("all_laws"))
        lines += ["### Found on the GPU: a data race in Warp's P2G", "",
                  "The first GPU run (`gpu_check_before_p2g_fix.json`) had Warp CUDA off its own CPU result by up "
                  f"to {worst:.2f} cells after {LAW_STEPS} steps, while JAX GPU matched JAX CPU to 1e-14, and the "
                  "fp32 dam break diverged (J < 0) after about 240 steps. The CPU P2G kernel accumulates with a "
                  "plain read-add-write into a per-thread grid copy; on CUDA every particle runs at once into one "
                  "copy, so those updates raced. The P2G kernel now has an `atomic` specialisation "
                  "(`wp.atomic_add`, no bounding box) that the stepper picks for CUDA devices; "
                  "`tests/test_warp_cuda.py` runs that specialisation on the CPU against the default one (and, "
                  "where a GPU exists, CUDA against the CPU). The gradient path (`backends/warp/grad.py`) already "
                  "used atomics and matched from the start.", ""]
        re = d / "gpu_recheck.json"
        if re.exists():
            r = json.loads(re.read_text())
            lines += [f"The final form of the kernel (one generic `add()`, commit {r['commit']}) was rechecked on "
                      f"an {r['device']}: " + ", ".join(f"{x['case']} {x['max_dx_vs_cpu']:.1e} cells"
                                                     for x in r["rows"]) + " against the CPU.", ""]
    grd = d / "gpu_grad.json"
    if grd.exists():
        g = json.loads(grd.read_text())
        lines += ["## Gradients: time and memory", "",
                  "The Ritter dam break, APIC, fp32, N steps, segment n; L = sum(x_N^2) w.r.t. v0 and the law "
                  "parameters. Median of 5 timed runs after a warm-up. Memory: JAX = XLA temp buffers of the "
                  "compiled gradient program; Warp = growth of the memory pool's high-water mark in one gradient.", "",
                  "| backend | particles | N | n | forward s | fwd+bwd s | ratio | fwd particle-steps/s | grad memory MiB |",
                  "|---|---|---|---|---|---|---|---|---|"]
        for r in g["rows"]:
            if "error" in r:
                lines.append(f"| {r['backend']} | dx {r['dx']} | - | {r['n']} | error: {r['error'][:120]} | | | | |")
                continue
            mem = r.get("grad_temp_mib", r.get("grad_pool_high_mib"))
            lines.append(f"| {r['backend']} | {r['particles']} | {r['N']} | {r['n']} | {r['fwd_s']:.3f} | "
                         f"{r['grad_s']:.3f} | {r['ratio']:.1f}x | {r['fwd_particle_steps_per_s']:.2e} | "
                         f"{_fmt(mem, '{:.1f}')} |")
        lines.append("")
    thr = d / "throughput_gpu.json"
    if thr.exists():
        t = json.loads(thr.read_text())
        lines += ["## Throughput", "",
                  "`benchmarks/throughput.py --big --no-taichi --no-skips` on the GPU (Taichi is not installed "
                  "there, so no ratio): Taichi mpm3d's scene (J-fluid, MLS), steady-state particle-steps/s, best "
                  "of 3; first call = trace/compile/kernel load (from the warm kernel cache for Warp) + first steps.",
                  "", "| dim | particles | precision | JAX GPU | Warp CUDA | Warp / JAX |", "|---|---|---|---|---|---|"]
        best = {}
        for r in t.get("throughput", []):
            if "particle_steps_per_s" not in r or r.get("scene") != "mpm3d":
                continue
            k = (r["dim"], r["particles"], r["precision"], r["backend"])
            best[k] = max(best.get(k, 0.0), r["particle_steps_per_s"])
        for dim, n, prec in sorted({k[:3] for k in best}, key=lambda k: (-k[0], k[1], k[2])):
            j, w = best.get((dim, n, prec, "jax")), best.get((dim, n, prec, "warp"))
            ratio = f"{w / j:.2f}" if j and w else "-"
            lines.append(f"| {dim}D | {n} | {prec} | {_fmt(j)} | {_fmt(w)} | {ratio} |")
        lines.append("")
    Path(args.md).write_text("\n".join(lines) + "\n")
    print(f"[gpu] wrote {args.md}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("mode", choices=["reference", "check", "grad", "render"])
    ap.add_argument("--backends", default="jax,warp")
    ap.add_argument("--reference", default=str(HERE / "out" / "gpu_reference.npz"))
    ap.add_argument("--out", default=str(HERE / "out" / "gpu"))
    ap.add_argument("--inputs", default=str(HERE / "results" / "gpu"))
    ap.add_argument("--md", default=str(HERE / "gpu.md"))
    ap.add_argument("--N", type=int, default=400)
    ap.add_argument("--segments", default="20")
    ap.add_argument("--dx", default="0.0125,0.003125", help="dam-break cell sizes (2560 / 41k particles)")
    ap.add_argument("--reps", type=int, default=5)
    args = ap.parse_args(argv)
    {"reference": cmd_reference, "check": cmd_check, "grad": cmd_grad, "render": cmd_render}[args.mode](args)


if __name__ == "__main__":
    main()
