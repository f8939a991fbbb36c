"""Where Warp's reduced Eulerian step spends its MPM time as the body grows (issue 16, "Speed"): the
`rom_tower` scene scaled as in ``rom_speed.py`` (fixed dx, 48k to 800k particles), one Eulerian + linear
``WarpReducedStepper`` at |M| = 50 per node set, and its Warp MPM step of the quadrature's pseudo-particles
timed whole (compact node set and scene grid) and, on the compact set, by phase: listing the windows'
nodes, P2G, grid update, grid boundaries, G2P, release. Prints one JSON line per size (no file written).

    python benchmarks/rom_warp_phases.py                 # sizes 1 and 2.55, about 5 min on 2 quiet cores

The weights are an untrained g at x_hat = 0 (``rom_speed.py`` says why that measures the scaling); the state is
set directly instead of by Eq. 19 (its Gauss-Newton over every material point is minutes at 800k in torch).
"""
from __future__ import annotations

import json
import statistics
import time

import numpy as np
from _harness import csv, parser, quiet_warp
from rom_speed import timed, tower_overrides


def measure(size: float, samples: int, repeats: int) -> dict:
    import torch
    import warp as wp

    from mpmlab.build import build_scene
    from mpmlab.config import compose
    from mpmlab.rom import networks as N
    from mpmlab.rom.stepper_warp import ReducedState, WarpReducedStepper
    from mpmlab.simulator import build_stepper

    scene = build_scene(compose(tower_overrides(size) + ["precision=fp32"]))
    st = build_stepper(scene, "warp", "pic", "fp32")
    X = np.asarray(st.particles.x)
    spec = N.RomSpec(dim=3, latent=6)
    norm = {"X_min": X.min(0), "X_max": X.max(0), "u_mean": np.zeros(3), "u_std": np.full(3, 1e-3)}
    w = N.RomWeights(N.init_params(spec, seed=0), norm, spec, 0)
    z = torch.zeros(spec.latent, dtype=torch.float32)
    s0 = ReducedState(z, z, z, 0.0, 0, 0, 0, 0)
    row = {"size": size, "particles": int(st.particles.count), "grid": list(scene.grid_shape), "samples": samples}
    for nodes in ("compact", "scene"):
        rom = WarpReducedStepper(st, w, samples=samples, quadrature="eulerian", projection="linear", nodes=nodes)
        rom.step(s0)                                   # fills the pseudo-particles and records the launches
        ps, a, o, q = rom._pseudo, rom._q_in, rom._q_out, rom._eu.q_size
        xM = a.x.numpy()[q:q + samples]                # the step's samples: their windows
        origin = (np.floor((xM - np.asarray(scene.origin)) / scene.dx - 0.5).astype(np.int32)
                  + getattr(rom, "_window_low", 0))
        nl = ps.node_list

        def mpm():
            if nl is not None:
                nl.claim_windows(origin)
            ps._step_into(a, o)
            if nl is not None:
                nl.release()
            ps._block(o)

        row[f"mpm_{nodes}_ms"] = round(1e3 * timed(mpm, repeats), 2)
        row[f"step_{nodes}_ms"] = round(1e3 * timed(lambda: rom.step(s0), 3), 1)
        if nl is None:
            continue
        cmds = ps._cmd_cache[(id(a), id(o), id(a.order))]
        phases = {"list": lambda: nl.claim_windows(origin), "p2g": lambda: ps._run_static(cmds.p2g),
                  "grid": lambda: ps._grid_update_listed(nl, len(cmds.p2g)),
                  "grid_boundaries": lambda: [bc.apply(ps.grid_v, a.t) for bc in ps.grid_bcs],
                  "g2p": lambda: ps._run_dynamic(cmds.g2p), "release": nl.release}
        t = {k: [] for k in phases}
        for _ in range(repeats):                       # in step order, so each phase sees a real step's data
            for k, f in phases.items():
                wp.synchronize()
                t0 = time.perf_counter()
                f()
                wp.synchronize()
                t[k].append(time.perf_counter() - t0)
        row["compact_phases_ms"] = {k: round(1e3 * statistics.median(v), 2) for k, v in t.items()}
    return row


def main() -> None:
    ap = parser(__doc__)
    ap.add_argument("--sizes", default="1,2.55")
    ap.add_argument("--samples", type=int, default=50)
    ap.add_argument("--repeats", type=int, default=7)
    a = ap.parse_args()
    quiet_warp()
    for s in csv(a.sizes):
        print(json.dumps(measure(float(s), a.samples, a.repeats)), flush=True)


if __name__ == "__main__":
    main()
