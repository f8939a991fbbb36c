"""The size pre-flight's memory model (mpmlab/core/budget.py) against the peak resident memory of a
real run, in a fresh process per case. A measurement, not a test: XLA's peak varies between runs
(217-313 MiB for the first case within one session, 850 MiB with YNNPACK fusions off), so no bound
is asserted; the table in budget.py's docstring came from runs like these.

    python benchmarks/budget_memory.py            # JAX, fp32, MLS: the default cube at 8 ppc, dx 0.02
"""
from __future__ import annotations

import json
import os
import subprocess
import sys

SCRIPT = r"""
import json, resource
import psutil
import mpmlab
from mpmlab.config import compose, build_scene
from mpmlab.core import budget
import jax.numpy as jnp
import mpmlab.backends.jax.stepper
jnp.zeros(3).block_until_ready()
# the cube sampled per cell (nclaw_jelly's own NCLaw lattice has 1000 points at any dx)
scene = build_scene(compose(["scene.dx=0.02", "scene.bodies.cube.sampling=regular", "scene.bodies.cube.lattice=null",
                             "scene.bodies.cube.particles_per_cell=8", "scene.dt=1e-4"]),
                    validate=False)
est = budget.estimate_memory(scene, "jax", "fp32", "mls", frames=3)
base = psutil.Process().memory_info().rss
mpmlab.simulate(scene, steps=2, every=1, backend="jax", transfer="mls", precision="fp32")
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
print(json.dumps({"estimate": est["total"], "estimate_without_runtime": est["total"] - est["runtime"],
                  "measured_peak": peak - base}))
"""


def main() -> int:
    # XLA_FLAGS left out: with YNNPACK fusions off (task=inverse) the forward peaks at ~3.7x
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    out = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, env={**env, "JAX_PLATFORMS": "cpu"})
    if out.returncode:
        print(out.stderr[-2000:], file=sys.stderr)
        return 1
    r = json.loads(out.stdout.strip().splitlines()[-1])
    mib = {k: v / 2**20 for k, v in r.items()}
    print(json.dumps({k: round(v, 1) for k, v in mib.items()}), f"ratio {r['estimate'] / r['measured_peak']:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
