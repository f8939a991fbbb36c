"""NCLaw on both backends: Warp compile time and forward time per step of the two ways to evaluate the
networks inside the fused G2P kernel (``mpmlab.laws.nclaw.warp.FORM``), against fixed_corotated.

    python benchmarks/nclaw_warp.py --backend warp --form adjoint [--cold] [--dim 3] [--steps 50]
    python benchmarks/nclaw_warp.py --backend jax

One process per configuration (the form is read when the law's Warp functions are first built).
The scene: NCLaw's training cube (App. D.1) at 1 particle per cell, dx = 0.05: 10^3 = 1,000 particles
on a 20^3 grid, MLS, fp32, dt = 5e-4, separate walls. ``--cold``: a fresh Warp kernel cache, so the
first step includes the C++ compile. Prints one JSON line.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--backend", default="warp")
    ap.add_argument("--law", default="nclaw")
    ap.add_argument("--form", default="adjoint")
    ap.add_argument("--dim", type=int, default=3)
    ap.add_argument("--steps", type=int, default=50)
    ap.add_argument("--precision", default="fp32")
    ap.add_argument("--cold", action="store_true")
    a = ap.parse_args()
    os.environ.setdefault("MPMLAB_WARP_THREADS", "1")
    if a.backend == "warp":
        import warp as wp

        if a.cold:
            wp.config.kernel_cache_dir = tempfile.mkdtemp(prefix="nclaw_warp_cache_")
        import mpmlab.laws.nclaw.warp as NW

        NW.FORM = a.form
    import mpmlab
    from mpmlab.boundaries import Walls

    d = a.dim
    params = {"E": 1e5, "nu": 0.2} if a.law == "fixed_corotated" else {}
    body = mpmlab.Body(shape={"kind": "box", "lo": [0.25] * d, "hi": [0.75] * d}, material=a.law, params=params,
                       density=1000.0, particles_per_cell=1, velocity=[1.0, -1.5, -2.0][:d])
    scene = mpmlab.Scene(dim=d, dx=0.05, domain=([0.0] * d, [1.0] * d), bodies=[body], gravity=[0.0, -9.8, 0.0][:d],
                         boundaries=[Walls(default="separate", thickness=3)], dt=5e-4, name="nclaw_cube")
    t0 = time.perf_counter()
    st = mpmlab.build_stepper(scene, a.backend, "mls", a.precision)
    s = st.init()
    s = st.step(s)
    st.to_numpy(s)
    first = time.perf_counter() - t0
    best = float("inf")
    for _ in range(3):
        t = time.perf_counter()
        for _ in range(a.steps):
            s = st.step(s)
        st.to_numpy(s)
        best = min(best, (time.perf_counter() - t) / a.steps)
    print(json.dumps({"backend": a.backend, "law": a.law, "form": a.form if a.law == "nclaw" and a.backend == "warp" else None,
                      "dim": d, "particles": int(scene.particles().count), "precision": a.precision,
                      "cold": a.cold, "build_and_first_step_s": round(first, 2), "step_ms": round(1e3 * best, 3)}))


if __name__ == "__main__":
    main()
