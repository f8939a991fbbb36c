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
  backend; and the Ritter dam break (fp32, 400 steps, positions every 25). ``check`` reruns them on
  the GPU and reports max |x_gpu - x_cpu| / dx per backend and between the backends on the GPU (the
  dam break frame by frame; a divergence is recorded, not fatal), the time of each Warp case's first
  call (the CUDA compile), and the gradient of L = sum(x_N^2) (``gradients.py``'s loss; N = 20 steps,
  segment 5) w.r.t. the initial velocities and every law parameter, fp64, on both GPU backends beside
  the CPU reference (relative L2 difference per leaf). ``gpu_check.json`` is rewritten after every
  case, so a run cut short by a time limit keeps what it measured.
* ``grad``: forward alone against forward+backward (N = 400 steps, segment n = 20) of the Ritter
  dam break at several particle counts, fp32, APIC, median of 5 after a warm-up, and the peak device
  memory of the gradient (JAX: XLA's buffer assignment of the compiled gradient program, temp bytes;
  Warp: the growth of Warp's memory-pool high-water mark during the gradient call).

Throughput (particle-steps/s) on the GPU comes from ``benchmarks/throughput.py`` run there with
``MPMLAB_WARP_DEVICE=cuda:0 --no-taichi --readme ''``; ``render`` tabulates it when its JSON is in
``--inputs`` (``throughput_gpu.json``).
"""
from __future__ import annotations

import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _harness as H  # noqa: E402

HERE = H.HERE
H.on_path(H.ROOT)                              # tests.scenes
TRANSFERS = ("pic", "flip", "apic", "mls", "tpic")
LAW_STEPS, LAW_DT = 40, 1e-3
LAW_DX = 0.05                                  # all_laws_scene's cell size
GRAD_N, GRAD_SEG = 20, 5
DAM_DX, DAM_STEPS, DAM_EVERY = 0.0125, 400, 25
DAM_CASE = "ritter/apic_fp32"


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
    """[x, v] after LAW_STEPS steps of the six-law scene, fp64."""
    from mpmlab.simulator import build_stepper
    from tests.scenes import all_laws_scene

    st = build_stepper(all_laws_scene(dim, dt=LAW_DT), backend, transfer, "fp64")
    traj = st.rollout(steps=LAW_STEPS, every=LAW_STEPS, progress=False)
    return np.stack([traj.x[-1], traj.v[-1]])


def run_dam(backend: str) -> np.ndarray:
    """Positions every DAM_EVERY steps of the fp32 Ritter dam break [frames, N, 2]; raises
    SimulationDiverged (with the frames so far) where it blows up."""
    from mpmlab.scenes.validation import ritter_dam_break
    from mpmlab.simulator import build_stepper

    st = build_stepper(ritter_dam_break(dx=DAM_DX), backend, "apic", "fp32")
    return st.rollout(steps=DAM_STEPS, every=DAM_EVERY, progress=False).x


def run_gradient(backend: str, dim: int) -> dict[str, np.ndarray]:
    """d sum(x_N^2) / d (v0, law parameters), fp64, APIC, segment GRAD_SEG (the loss of gradients.py)."""
    import gradients
    from mpmlab.simulator import build_stepper
    from tests.scenes import all_laws_scene

    st = build_stepper(all_laws_scene(dim, dt=LAW_DT), backend, "apic", "fp64")
    if backend == "jax":
        c = st.controls()
        _, grad = gradients.jax_programs(st, GRAD_N, GRAD_SEG)
        _, (gv, glaw) = grad((c["v"], c["law"]), c)
    else:
        _, grad = gradients.warp_fns(st, GRAD_N, GRAD_SEG)
        _, gv, glaw = grad()
    to_np = lambda a: np.asarray(a.detach().cpu().numpy() if hasattr(a, "detach") else a, dtype=float)
    return {"v": to_np(gv), **{f"law{k}": to_np(a) for k, a in enumerate(glaw)}}


def compute_all(backends, on_result=None) -> dict[str, np.ndarray]:
    """Every case on every backend: ``{"backend:case": array}``; ``on_result(key, array, seconds)``
    after each (the check writes its JSON there, so a run cut short keeps what it measured)."""
    from mpmlab.core.errors import SimulationDiverged

    res = {}

    def put(key, value, t0):
        res[key] = value
        dt = time.perf_counter() - t0
        print(f"[gpu] {key}: {dt:.1f} s", flush=True)
        if on_result is not None:
            on_result(key, value, dt)

    for b in backends:
        for name, dim, tr in law_cases():
            t0 = time.perf_counter()
            put(f"{b}:{name}", run_forward(b, dim, tr), t0)
        t0 = time.perf_counter()
        try:
            put(f"{b}:{DAM_CASE}", run_dam(b), t0)
        except SimulationDiverged as e:      # recorded, not fatal: the other cases still run
            put(f"{b}:{DAM_CASE}", str(e), t0)
        for dim in (2, 3):
            t0 = time.perf_counter()
            for k, a in run_gradient(b, dim).items():
                put(f"{b}:grad_{dim}d:{k}", a, t0)
    return res


def cmd_reference(args):
    os.environ.setdefault("JAX_PLATFORMS", "cpu")
    if os.environ.get("MPMLAB_WARP_DEVICE", "cpu") != "cpu":
        sys.exit("reference: run it on the CPU (unset MPMLAB_WARP_DEVICE).")
    res = compute_all(args.backends.split(","))
    bad = [k for k, v in res.items() if isinstance(v, str)]
    if bad:
        sys.exit(f"reference: {bad} diverged on the CPU: {[res[k] for k in bad]}")
    Path(args.reference).parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(args.reference, **res)
    print(f"[gpu] wrote {args.reference}")


def _rel(a, b):
    den = np.linalg.norm(b)
    return float(np.linalg.norm(a - b) / den) if den > 0 else float(np.linalg.norm(a - b))


def _row(key, a, seconds, ref, gpu) -> dict:
    """One row of gpu_check.json: the GPU result ``a`` against the CPU reference and the other backend."""
    b, case = key.split(":", 1)
    other = gpu.get(f"{'warp' if b == 'jax' else 'jax'}:{case}")
    r = ref.get(key)
    row = {"backend": b, "case": case, "seconds": seconds}
    if isinstance(a, str):
        return {**row, "error": a}
    row["finite"] = bool(np.all(np.isfinite(a)))
    if case.startswith("grad"):
        row["rel_l2_vs_cpu"] = _rel(a, r) if r is not None else None
        row["rel_l2_vs_other_gpu"] = _rel(a, other) if isinstance(other, np.ndarray) else None
    elif case == DAM_CASE:             # frames every DAM_EVERY steps; the reference keeps them too
        row["max_dx_vs_cpu"] = float(np.abs(a[-1] - r[-1]).max() / DAM_DX) if r is not None else None
        if isinstance(other, np.ndarray):
            row["dev_per_frame"] = [float(np.abs(p - q).max() / DAM_DX) for p, q in zip(a, other)]
    else:
        row["warp_first_call_s"] = seconds if b == "warp" else None     # CUDA compile + the steps
        row["max_dx_vs_cpu"] = float(np.abs(a[0] - r[0]).max() / LAW_DX) if r is not None else None
        row["max_dv_vs_cpu"] = float(np.abs(a[1] - r[1]).max()) if r is not None else None
        row["max_dx_vs_other_gpu"] = float(np.abs(a[0] - other[0]).max() / LAW_DX) \
            if isinstance(other, np.ndarray) else None
    return row


def cmd_check(args):
    ref = dict(np.load(args.reference))
    info, gpu, seconds = _device_info(), {}, {}
    path = Path(args.out) / "gpu_check.json"
    path.parent.mkdir(parents=True, exist_ok=True)

    def on_result(key, value, dt):      # rows rebuilt each time: a JAX row gains Warp's comparison
        gpu[key], seconds[key] = value, dt
        rows = [_row(k, gpu[k], seconds[k], ref, gpu) for k in gpu]
        H.write_json(path, {"info": info, "rows": rows})

    compute_all(args.backends.split(","), on_result)
    print(path.read_text())


# ---- gradient time and memory --------------------------------------------------------------------------
def _grad_case(backend: str, dx: float, N: int, n: int, reps: int) -> dict:
    """Forward alone and forward+backward of gradients.py's loss (sum(x_N^2) w.r.t. v0 and the law
    parameters) on the Ritter dam break; device memory of the gradient."""
    import gradients

    st = gradients.build({"dx": dx, "transfer": "apic", "precision": "fp32"}, backend)
    res = {"backend": backend, "particles": st.particles.count, "dx": dx, "N": N, "n": n}
    t0 = time.perf_counter()
    if backend == "jax":
        import jax

        c = st.controls()
        p = (c["v"], c["law"])
        fwd_j, grad_j = gradients.jax_programs(st, N, n)
        fwd_c, grad_c = fwd_j.lower(p, c).compile(), grad_j.lower(p, c).compile()
        res["compile_s"] = time.perf_counter() - t0
        for name, comp in (("grad", grad_c), ("fwd", fwd_c)):
            ma = comp.memory_analysis()
            res[f"{name}_temp_mib"] = getattr(ma, "temp_size_in_bytes", 0) / 2**20 if ma is not None else None
        fwd = lambda: jax.block_until_ready(fwd_c(p, c))
        grad = lambda: jax.block_until_ready(grad_c(p, c))
    else:
        import warp as wp

        fwd, grad_fn = gradients.warp_fns(st, N, n)

        def grad():
            grad_fn()
            wp.synchronize_device(st.device)

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
                H.write_json(out_dir / "gpu_grad.json", {"info": _device_info(), "rows": rows})


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
                  *H.md_table(["case", "JAX GPU vs JAX CPU", "Warp CUDA vs Warp CPU", "JAX GPU vs Warp CUDA", "finite",
                               "Warp first call s"])]
        for case in sorted({r["case"] for r in c["rows"] if r["case"].startswith("all_laws")}):
            j, w = rows.get(("jax", case), {}), rows.get(("warp", case), {})
            lines.append(H.md_row([case, _fmt(j.get("max_dx_vs_cpu")), _fmt(w.get("max_dx_vs_cpu")),
                                   _fmt(j.get("max_dx_vs_other_gpu")), f"{j.get('finite', '-')} / {w.get('finite', '-')}",
                                   _fmt(w.get("warp_first_call_s"), "{:.0f}")]))
        dam = rows.get(("warp", DAM_CASE), {})
        e = dam.get("dev_per_frame")
        if e:
            at = [k for k in (100, 200, DAM_STEPS) if k // DAM_EVERY < len(e)]
            lines += ["", f"The Ritter dam break (fp32, APIC, 2560 particles, {DAM_STEPS} steps): JAX GPU against Warp "
                      f"CUDA, max |dx| in cells after {' / '.join(map(str, at))} steps: "
                      + " / ".join(f"{e[k // DAM_EVERY]:.1e}" for k in at) + " (fp32 summation order only)."]
        for b in ("jax", "warp"):
            if rows.get((b, DAM_CASE), {}).get("error"):
                lines += ["", f"The Ritter dam break on {b}: {rows[(b, DAM_CASE)]['error']}"]
        lines += ["", "## Gradients: GPU against CPU", "",
                  f"d sum(x_N^2) / d(v0, law parameters) of the six-law scene, APIC, fp64, N = {GRAD_N}, segment "
                  f"{GRAD_SEG}: relative L2 difference per leaf (`law5` = drucker_prager_jaumann).", "",
                  *H.md_table(["leaf", "JAX GPU vs JAX CPU", "Warp CUDA vs Warp CPU"])]
        for case in sorted({r["case"] for r in c["rows"] if r["case"].startswith("grad")}):
            j, w = rows.get(("jax", case), {}), rows.get(("warp", case), {})
            lines.append(H.md_row([case, _fmt(j.get("rel_l2_vs_cpu")), _fmt(w.get("rel_l2_vs_cpu"))]))
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
                  *H.md_table(["backend", "particles", "N", "n", "forward s", "fwd+bwd s", "ratio", "fwd particle-steps/s",
                               "grad memory MiB"])]
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
                  "", *H.md_table(["dim", "particles", "precision", "JAX GPU", "Warp CUDA", "Warp / JAX"])]
        best = {}
        for r in t.get("throughput", []):
            if "particle_steps_per_s" not in r or r.get("scene") != "mpm3d":
                continue
            k = (r["dim"], r["particles"], r["precision"], r["backend"])
            best[k] = max(best.get(k, 0.0), r["particle_steps_per_s"])
        for dim, n, prec in sorted({k[:3] for k in best}, key=lambda k: (-k[0], k[1], k[2])):
            j, w = best.get((dim, n, prec, "jax")), best.get((dim, n, prec, "warp"))
            ratio = f"{w / j:.2f}" if j and w else "-"
            lines.append(H.md_row([f"{dim}D", n, prec, _fmt(j), _fmt(w), ratio]))
        lines.append("")
    Path(args.md).write_text("\n".join(lines) + "\n")
    print(f"[gpu] wrote {args.md}")


def main(argv=None):
    ap = H.parser(__doc__.split("\n")[0])
    ap.add_argument("mode", choices=["reference", "check", "grad", "render"])
    H.add_backends(ap)
    ap.add_argument("--reference", default=str(H.OUT / "gpu_reference.npz"))
    ap.add_argument("--out", default=str(H.OUT / "gpu"))
    ap.add_argument("--inputs", default=str(H.RESULTS / "gpu"))
    ap.add_argument("--md", default=str(HERE / "gpu.md"))
    ap.add_argument("--N", type=int, default=400)
    ap.add_argument("--segments", default="20")
    ap.add_argument("--dx", default="0.0125,0.003125", help="dam-break cell sizes (2560 / 41k particles)")
    ap.add_argument("--reps", type=int, default=5)
    args = ap.parse_args(argv)
    {"reference": cmd_reference, "check": cmd_check, "grad": cmd_grad, "render": cmd_render}[args.mode](args)


if __name__ == "__main__":
    main()
