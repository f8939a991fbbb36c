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


def warp_node_sets(fom, weights, samples: int, repeats: int, state=None, phases: bool = False) -> dict:
    """Warp's Eulerian + linear reduced model of ``fom`` at |M| = ``samples`` on each node set ("compact",
    "scene"): the whole reduced step (``rom_warp_<nodes>_s``) and its Warp MPM step of the pseudo-particles
    alone (``mpm_warp_<nodes>_s``: ``WarpReducedStepper._pseudo_step``, the listing and release included),
    medians of ``repeats`` after warm-up (``rom_speed.timed``); with ``phases``, the compact set's MPM step by
    phase (``compact_phases_s``). ``state``: the reduced state to step from (None: Eq. 19's, made once)."""
    import warp as wp

    from mpmlab.rom.stepper_warp import WarpReducedStepper

    out = {}
    for nodes in ("compact", "scene"):
        rom = WarpReducedStepper(fom, weights, samples=samples, quadrature="eulerian", projection="linear", nodes=nodes)
        if state is None:
            state = rom.init()                         # the same on both node sets
        rom.step(state)                                # fills the pseudo-particles and records the launches
        ps, a, q = rom._pseudo, rom._q_in, rom._eu.q_size
        scene = rom.scene
        xM = a.x.numpy()[q:q + samples]                # the step's samples: their base nodes
        base = np.floor((xM - np.asarray(scene.origin)) / scene.dx - 0.5).astype(np.int32)

        def mpm(rom=rom, base=base):
            rom._pseudo_step(base)
            rom._pseudo._block(rom._q_out)

        out[f"rom_warp_{nodes}_s"] = timed(lambda: rom.step(state), repeats)
        out[f"mpm_warp_{nodes}_s"] = timed(mpm, repeats)
        nl = ps.node_list
        if not phases or nl is None:
            continue
        o = rom._q_out
        cmds = ps._cmd_cache[(id(a), id(o), id(a.order))]
        steps = {"list": lambda: nl.claim_windows(base + rom._window_low), "p2g": lambda: ps._run_static(cmds.p2g),
                 "grid": lambda: ps._grid_update_listed(nl, len(cmds.p2g)),
                 "grid_boundaries": lambda: [bc.apply(ps.grid_v, a.t) for bc in ps.grid_bcs],
                 "g2p": lambda: ps._run_dynamic(cmds.g2p), "release": nl.release}
        t = {k: [] for k in steps}
        for _ in range(repeats):                       # in step order, so each phase sees a real step's data
            for k, f in steps.items():
                wp.synchronize()
                t0 = time.perf_counter()
                f()
                wp.synchronize()
                t[k].append(time.perf_counter() - t0)
        out["compact_phases_s"] = {k: statistics.median(v) for k, v in t.items()}
    return out


def measure(size: float, samples: int, repeats: int) -> dict:
    import torch

    from mpmlab.build import build_scene
    from mpmlab.config import compose
    from mpmlab.rom import networks as N
    from mpmlab.rom.stepper_warp import ReducedState
    from mpmlab.simulator import build_stepper

    scene = build_scene(compose(tower_overrides(size) + ["precision=fp32"]))
    st = build_stepper(scene, "warp", "pic", "fp32")
    X = np.asarray(st.particles.x)
    spec = N.RomSpec(dim=3, latent=6)
    norm = {"X_min": X.min(0), "X_max": X.max(0), "u_mean": np.zeros(3), "u_std": np.full(3, 1e-3)}
    w = N.RomWeights(N.init_params(spec, seed=0), norm, spec, 0)
    z = torch.zeros(spec.latent, dtype=torch.float32)
    row = {"size": size, "particles": int(st.particles.count), "grid": list(scene.grid_shape), "samples": samples}
    res = warp_node_sets(st, w, samples, repeats, state=ReducedState(z, z, z, 0.0, 0, 0, 0, 0), phases=True)
    for k, v in res.items():                       # every key ends in _s: printed in ms
        row[k[:-2] + "_ms"] = (
            {p: round(1e3 * x, 2) for p, x in v.items()} if isinstance(v, dict) else round(1e3 * v, 2))
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
