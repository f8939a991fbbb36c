"""Throughput of two trees measured side by side in one run (issue #13's "within 5 % of the parent").

Each measurement runs in a fresh subprocess with ``PYTHONPATH`` set to one tree, A and B interleaved
for ``--rounds`` rounds; the best round of each is kept (on a shared machine the least disturbed one).
Cases: Taichi mpm3d's scene (J-fluid, MLS) and the fixed-corotated cube (MLS), 3D fp32, at 8k and 65k
particles, on JAX and Warp::

    git worktree add /tmp/parent <parent commit>
    python benchmarks/ab_throughput.py /tmp/parent . --rounds 3

Prints particle-steps/s per case and tree, and B / A. ``--gradients``: the time of one gradient of a
loss of the positions after N steps with respect to v and the law parameters (the setup of
``benchmarks/gradients.py``: the 2D Ritter dam break, 2560 particles, APIC, fp32, segment n), per
backend, best of 3 after a warm-up::

    python benchmarks/ab_throughput.py /tmp/parent . --gradients --rounds 2
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys

import numpy as np

CASE = r'''
import json, sys, time
import numpy as np
from mpmlab.scenes.mpm3d import mpm3d_fluid, elastic_cube
import mpmlab
scene_name, n_grid, backend, steps, transfer = sys.argv[1], int(sys.argv[2]), sys.argv[3], int(sys.argv[4]), sys.argv[5]
scene = (mpm3d_fluid if scene_name == "mpm3d" else elastic_cube)(n_grid=n_grid, dim=3)
st = mpmlab.build_stepper(scene, backend, transfer, "fp32")
s = st.init()
s = st._advance(s, steps); st._block(s)                # compile + warm-up
best = float("inf")
for _ in range(3):
    t = time.perf_counter(); s2 = st._advance(s, steps); st._block(s2); best = min(best, time.perf_counter() - t)
print(json.dumps({"particles": st.particles.count, "pps": st.particles.count * steps / best}))
'''


GRAD_CASE = r'''
import json, sys, time
import numpy as np
import mpmlab
from mpmlab.observations import Lagrangian
from mpmlab.scenes.validation import ritter_dam_break
backend, N, n = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
scene = ritter_dam_break(dx=0.0125)
st = mpmlab.build_stepper(scene, backend, "apic", "fp32")
obs = Lagrangian(quantity="x")
c = st.controls()
if backend == "jax":
    import jax, jax.numpy as jnp
    f = jax.jit(jax.value_and_grad(lambda v, law: jnp.sum(st.observe({**c, "v": v, "law": law}, obs, [N], segment=n) ** 2),
                                   argnums=(0, 1)))
    run = lambda: jax.block_until_ready(f(c["v"], c["law"]))
else:
    import torch
    def run():
        v = c["v"].clone().requires_grad_(True); law = tuple(a.clone().requires_grad_(True) for a in c["law"])
        (st.observe({**c, "v": v, "law": law}, obs, [N], segment=n) ** 2).sum().backward()
run()
best = float("inf")
for _ in range(3):
    t = time.perf_counter(); run(); best = min(best, time.perf_counter() - t)
print(json.dumps({"particles": st.particles.count, "seconds": best}))
'''


def measure(tree, case, code=None):
    env = dict(os.environ, PYTHONPATH=os.path.abspath(tree))
    out = subprocess.run([sys.executable, "-c", code or CASE, *map(str, case)], env=env, capture_output=True, text=True,
                         timeout=1800, cwd=os.path.abspath(tree))
    if out.returncode:
        raise SystemExit(f"{tree} {case}: {out.stderr[-1500:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("a"); ap.add_argument("b")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--grids", default="32,64", help="n_grid values (32: 8k particles, 64: 65k)")
    ap.add_argument("--backends", default="jax,warp")
    ap.add_argument("--scenes", default="mpm3d,cube")
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--transfers", default="mls", help="transfer schemes (comma-separated)")
    ap.add_argument("--gradients", action="store_true", help="time gradients (N steps, n = 50) instead")
    ap.add_argument("--gradient-steps", type=int, default=200, help="N of --gradients (longer: steadier timings)")
    args = ap.parse_args(argv)
    if args.gradients:
        return gradients(args)
    cases = [(sc, int(g), be, args.steps, t) for sc in args.scenes.split(",") for g in args.grids.split(",")
             for be in args.backends.split(",") for t in args.transfers.split(",")]
    best, ratios = {}, {}
    for r in range(args.rounds):
        for case in cases:
            for tree in (args.a, args.b):
                m = measure(tree, case)
                key = (case, tree)
                best[key] = max(best.get(key, (0, 0)), (m["pps"], m["particles"]))
                if tree == args.a:
                    pps_a = m["pps"]
                else:
                    ratios.setdefault(case, []).append(m["pps"] / pps_a)
                print(f"round {r + 1}: {case[0]} {case[1]}^3 {case[2]} {case[4]} {tree}: {m['pps']:.3e} particle-steps/s",
                      flush=True)
    # B / A of the best rounds, and the median of the paired (same-round, adjacent) ratios: on a noisy
    # machine the paired median is the steadier of the two
    print("\n| scene | particles | backend | transfer | A [particle-steps/s] | B | B / A (best) | B / A (median of rounds) |"
          "\n|---|---|---|---|---|---|---|---|")
    for case in cases:
        (pa, n), (pb, _) = best[(case, args.a)], best[(case, args.b)]
        med = float(np.median(ratios[case]))
        print(f"| {case[0]} | {n} | {case[2]} | {case[4]} | {pa:.3e} | {pb:.3e} | {pb / pa:.3f} | {med:.3f} |")


def gradients(args):
    cases = [(be, args.gradient_steps, 50) for be in args.backends.split(",")]
    best, ratios = {}, {}
    for r in range(args.rounds):
        for case in cases:
            for tree in (args.a, args.b):
                m = measure(tree, case, GRAD_CASE)
                best[(case, tree)] = min(best.get((case, tree), float("inf")), m["seconds"])
                if tree == args.a:
                    sec_a = m["seconds"]
                else:
                    ratios.setdefault(case, []).append(m["seconds"] / sec_a)
                print(f"round {r + 1}: gradient {case[0]} N={case[1]} n={case[2]} {tree}: {m['seconds']:.3f} s", flush=True)
    print("\n| backend | N | n | A [s] | B [s] | B / A (best) | B / A (median of rounds) |\n|---|---|---|---|---|---|---|")
    for case in cases:
        a, b = best[(case, args.a)], best[(case, args.b)]
        print(f"| {case[0]} | {case[1]} | {case[2]} | {a:.3f} | {b:.3f} | {b / a:.3f} | {float(np.median(ratios[case])):.3f} |")


if __name__ == "__main__":
    main()
