"""NCLaw speed on both backends against the analytic law it is trained to replace (fixed_corotated):
the 1000-step forward at 1,000 particles and the cost of a 100-step gradient (fwd+bwd / forward).

    python benchmarks/nclaw_warp.py                       # both backends, both laws; writes benchmarks/nclaw.md
    python benchmarks/nclaw_warp.py --backends warp --steps 200 --rounds 3 --md ''   # quick, no file
    python benchmarks/nclaw_warp.py --cold                # a fresh Warp kernel cache (compile times)

The scene: NCLaw's training cube (App. D.1) at 1 particle per cell, dx = 0.05: 10^3 = 1,000
particles on a 20^3 grid, MLS, fp32, dt = 5e-4, separate walls, thrown at (1, -1.5, -2) m/s.

Forward: ``stepper._advance(state, steps)`` (the compiled step loop, as ``throughput.py``), the two
laws' steppers of one backend built in this process and timed in alternation (``--rounds``
rounds, median; the ratio is the median of the per-round ratios, so load from other processes that
lasts a round cancels). Warp runs on 1 CPU thread unless ``MPMLAB_WARP_THREADS`` says otherwise (at 1,000
particles the stepper's own default is 1 thread too: one per 4,096 particles); each row records the count.
JAX runs on XLA's CPU threads. On the 2-core CPU the issue's 2.56 s bar is met with two Warp threads:

    MPMLAB_WARP_THREADS=2 python benchmarks/nclaw_warp.py

Gradient: the loss sum(w * observe(controls, Lagrangian(v), (grad_steps,))) w.r.t. the initial
velocities and the shared weights (the law's parameters for fixed_corotated). JAX:
``jax.jit(jax.value_and_grad(loss))`` against ``jax.jit(loss)``; Warp: ``observe`` with the leaves
requiring grad plus ``backward()`` against ``observe`` under ``torch.no_grad()`` (Warp's tape path,
``mpmlab/backends/warp/grad.py``, which is not the fused fast path). Both in fp32 as the forward.

Prints one JSON line per measurement and keeps them in ``benchmarks/results/nclaw_speed.json``
(a run of some backends keeps the other backends' rows from before, each row with its commit, date
and load); ``--md`` rewrites the ``## Speed`` section of ``benchmarks/nclaw.md`` from that file
(marked ``<!-- nclaw-speed:start/end -->``; the rest of the file is kept).
"""
from __future__ import annotations

import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _harness as H  # noqa: E402

H.on_path(H.ROOT)
H.quiet_warp(1)

LAWS = ("nclaw", "fixed_corotated")
#: the issue's targets: NCLaw Tab. 3 (RTX A6000, 1000 steps at 1k particles) and <= 3x the analytic law
PAPER_S = 2.56
MAX_RATIO = 3.0


def scene(law: str, dim: int = 3):
    import mpmlab
    from mpmlab.boundaries import Walls

    params = {"E": 1e5, "nu": 0.2} if law == "fixed_corotated" else {}
    body = mpmlab.Body(shape={"kind": "box", "lo": [0.25] * dim, "hi": [0.75] * dim}, material=law, params=params,
                       density=1000.0, particles_per_cell=1, velocity=[1.0, -1.5, -2.0][:dim])
    return mpmlab.Scene(dim=dim, dx=0.05, domain=([0.0] * dim, [1.0] * dim), bodies=[body],
                        gravity=[0.0, -9.8, 0.0][:dim], boundaries=[Walls(default="separate", thickness=3)],
                        dt=5e-4, name="nclaw_cube")


def forward(backend: str, steps: int, rounds: int, precision: str) -> list[dict]:
    """The ``steps``-step forward of each law, alternating laws within each round."""
    import mpmlab

    side = {}
    for law in LAWS:
        t0 = time.perf_counter()
        st = mpmlab.build_stepper(scene(law), backend, "mls", precision)
        s0 = st.init()
        s = st._advance(s0, steps)              # compiles (JAX: the whole loop) / loads the kernels (Warp)
        st._block(s)
        side[law] = {"st": st, "s0": s0, "first_s": time.perf_counter() - t0, "t": []}
        H.log(f"{backend} {law}: build + first {steps} steps {side[law]['first_s']:.1f} s", err=True)
    for _ in range(rounds):
        for law in LAWS:
            d = side[law]
            t = time.perf_counter()
            s = d["st"]._advance(d["s0"], steps)
            d["st"]._block(s)
            d["t"].append(time.perf_counter() - t)
    ratio = statistics.median(a / b for a, b in zip(side["nclaw"]["t"], side["fixed_corotated"]["t"]))
    out = []
    for law in LAWS:
        d = side[law]
        out.append({"what": "forward", "backend": backend, "law": law, "precision": precision, "steps": steps,
                    "particles": int(d["st"].particles.count), "rounds": rounds,
                    "build_and_first_run_s": round(d["first_s"], 2),
                    "run_s": round(statistics.median(d["t"]), 3), "run_s_min": round(min(d["t"]), 3),
                    "ms_per_step": round(1e3 * statistics.median(d["t"]) / steps, 3),
                    "nclaw_over_analytic": round(ratio, 2),
                    "warp_threads": int(os.environ["MPMLAB_WARP_THREADS"]) if backend == "warp" else None})
    return out


def _jax_gradient(st, steps):
    import jax
    import jax.numpy as jnp
    import numpy as np

    from mpmlab.observations import Lagrangian

    c = st.controls()
    obs = Lagrangian(quantity="v")
    key = "law_weights" if any(len(w) for w in c["law_weights"]) else "law"
    w = jnp.asarray(np.random.default_rng(0).standard_normal((1, st.particles.count, st.dim)), st.dtype)

    def loss(v, p):
        return jnp.sum(w * st.observe({**c, "v": v, key: p}, obs, (steps,)))

    fwd = jax.jit(loss)
    both = jax.jit(jax.value_and_grad(loss, argnums=(0, 1)))
    return (lambda: jax.block_until_ready(fwd(c["v"], c[key])),
            lambda: jax.block_until_ready(both(c["v"], c[key])))


def _warp_gradient(st, steps):
    import numpy as np
    import torch

    from mpmlab.observations import Lagrangian

    c = st.controls()
    obs = Lagrangian(quantity="v")
    key = "law_weights" if any(len(w) for w in c["law_weights"]) else "law"
    w = torch.tensor(np.random.default_rng(0).standard_normal((1, st.particles.count, st.dim)), dtype=c["v"].dtype)

    def fwd():
        with torch.no_grad():
            return float((st.observe(c, obs, (steps,)) * w).sum())

    def both():
        v = c["v"].detach().clone().requires_grad_(True)
        if key == "law_weights":
            p = tuple({k: a.detach().clone().requires_grad_(True) for k, a in g.items()} for g in c[key])
        else:
            p = tuple(a.detach().clone().requires_grad_(True) for a in c[key])
        y = (st.observe({**c, "v": v, key: p}, obs, (steps,)) * w).sum()
        y.backward()
        return float(y.detach())

    return fwd, both


def gradient(backend: str, steps: int, rounds: int, precision: str) -> list[dict]:
    """fwd+bwd vs forward of a ``steps``-step observation loss, per law (laws alternating per round)."""
    import mpmlab

    side = {}
    for law in LAWS:
        st = mpmlab.build_stepper(scene(law), backend, "mls", precision)
        fwd, both = (_jax_gradient if backend == "jax" else _warp_gradient)(st, steps)
        t0 = time.perf_counter()
        fwd()
        both()
        side[law] = {"fwd": fwd, "both": both, "tf": [], "tb": [], "first_s": time.perf_counter() - t0}
        H.log(f"{backend} {law}: gradient path built + first runs {side[law]['first_s']:.1f} s", err=True)
    for _ in range(rounds):
        for law in LAWS:
            d = side[law]
            t = time.perf_counter()
            d["fwd"]()
            d["tf"].append(time.perf_counter() - t)
            t = time.perf_counter()
            d["both"]()
            d["tb"].append(time.perf_counter() - t)
    out = []
    for law in LAWS:
        d = side[law]
        out.append({"what": "gradient", "backend": backend, "law": law, "precision": precision, "steps": steps,
                    "rounds": rounds, "forward_s": round(statistics.median(d["tf"]), 3),
                    "fwd_bwd_s": round(statistics.median(d["tb"]), 3),
                    "fwd_bwd_over_forward": round(statistics.median(b / f for b, f in zip(d["tb"], d["tf"])), 2)})
    return out


RESULTS = H.RESULTS / "nclaw_speed.json"


def _commit() -> str:
    import subprocess

    try:
        return subprocess.run(["git", "-C", str(H.ROOT), "rev-parse", "--short", "HEAD"], capture_output=True,
                              text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "?"


def markdown(rows: list[dict], info: dict, a) -> str:
    fw = {(r["backend"], r["law"]): r for r in rows if r["what"] == "forward"}
    gr = {(r["backend"], r["law"]): r for r in rows if r["what"] == "gradient"}
    backends = sorted({b for b, _ in fw} | {b for b, _ in gr})
    runs = sorted({(r["backend"], r["commit"], r["date"], r["load"]) for r in rows})
    lines = [f"Generated by `python benchmarks/nclaw_warp.py` ({info['cpu']}, {info['cores']} cores, shared with "
             f"other processes; warp {info.get('warp', '-')}, jax {info.get('jax', '-')}). NCLaw's training cube: "
             f"1,000 particles, 3D, MLS, {rows[0]['precision'] if rows else a.precision}, dt = 5e-4; Warp's CPU threads in "
             f"the forward table. Absolute times move "
             f"with the machine's load (by 2x between runs here); the ratios are medians of per-round ratios of "
             f"the two laws timed in alternation in one process. Runs: "
             + "; ".join(f"{b} at commit {c}, {d}, load average before/after {l}" for b, c, d, l in runs) + ".", ""]
    if fw:
        steps, rounds = next(iter(fw.values()))["steps"], next(iter(fw.values()))["rounds"]
        lines += [f"**Forward, {steps} steps** (median of {rounds} rounds; target: nclaw < {PAPER_S} s for "
                  f"1,000 steps (NCLaw Tab. 3, RTX A6000) and <= {MAX_RATIO:g}x the analytic law):", ""]
        hdr = ["backend", "Warp threads", "nclaw s", "fixed_corotated s", "nclaw / fixed_corotated", "nclaw ms/step",
               "fixed_corotated ms/step", "build + first run s (nclaw / fc)"]
        body = []
        for b in backends:
            n, f = fw.get((b, "nclaw")), fw.get((b, "fixed_corotated"))
            if n and f:
                body.append([b, n.get("warp_threads") or "-", n["run_s"], f["run_s"], f"{n['nclaw_over_analytic']:.2f}", n["ms_per_step"],
                             f["ms_per_step"], f"{n['build_and_first_run_s']} / {f['build_and_first_run_s']}"])
        lines += H.md_table(hdr, body) + [""]
    if gr:
        steps, rounds = next(iter(gr.values()))["steps"], next(iter(gr.values()))["rounds"]
        lines += [f"**Gradient of a {steps}-step observation** (d loss / d (v0, shared weights); fixed_corotated: "
                  f"d (v0, E, nu); median of {rounds} rounds):", ""]
        hdr = ["backend", "law", "forward s", "fwd+bwd s", "fwd+bwd / forward"]
        body = [[b, law, gr[(b, law)]["forward_s"], gr[(b, law)]["fwd_bwd_s"], gr[(b, law)]["fwd_bwd_over_forward"]]
                for b in backends for law in LAWS if (b, law) in gr]
        lines += H.md_table(hdr, body) + [""]
    lines += ["The Warp forward rows are the fused fast path. The Warp gradient rows run the tape path "
              "(`backends/warp/grad.py`: plain launches on one thread, a tape per segment, the adjoint kernels); "
              "their forward column is that path's forward, not the fast path's. How the networks are "
              "evaluated on Warp and what else was measured: `benchmarks/README.md`, \"NCLaw on Warp\".", ""]
    return "\n".join(lines)


def main():
    ap = H.parser(__doc__, raw=True)
    H.add_backends(ap)
    ap.add_argument("--steps", type=int, default=1000, help="forward steps")
    ap.add_argument("--grad-steps", type=int, default=100, help="steps of the gradient (0: skip it)")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--precision", default="fp32")
    ap.add_argument("--cold", action="store_true", help="a fresh Warp kernel cache (times the compile)")
    ap.add_argument("--md", default=str(H.HERE / "nclaw.md"), help="'' to write no file")
    ap.add_argument("--report-only", action="store_true", help="rewrite the section from the results file, run nothing")
    a = ap.parse_args()
    backends = [] if a.report_only else H.csv(a.backends)
    if a.cold and "warp" in backends:
        import warp as wp

        wp.config.kernel_cache_dir = tempfile.mkdtemp(prefix="nclaw_warp_cache_")
    info = H.machine_info(["jax", "warp"])
    rows = []
    for b in backends:
        load, date = H.load_average(), time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
        new = forward(b, a.steps, a.rounds, a.precision)
        if a.grad_steps:
            new += gradient(b, a.grad_steps, a.rounds, a.precision)
        for r in new:
            r.update(commit=_commit(), date=date, load=f"{load} / {H.load_average()}")
            print(json.dumps(r), flush=True)
        rows += new
    rows = H.keep_rows(H.read_json(RESULTS, []), rows, lambda r: r["backend"] not in backends)
    H.write_json(RESULTS, rows, newline=True)
    if a.md:
        path = Path(a.md)
        if not path.exists():
            path.write_text("# NCLaw\n")
        H.write_readme_section(path, "nclaw-speed", "Speed", markdown(rows, info, a))
        H.log(f"wrote the Speed section of {path}", err=True)


if __name__ == "__main__":
    os.environ.setdefault("MPLBACKEND", "Agg")
    main()
