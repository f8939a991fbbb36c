"""The reduced step's time against the body's size (issue 16, "Speed"): the `rom_tower` scene scaled by
``--sizes`` (linear factors at the `cpu` resolution's fixed dx, so particles grow as size^3: 48k to 800k),
one Eulerian + linear reduced step at |M| = ``--samples`` on the compact node set and on the scene's grid
(JAX, and Warp with ``--backends`` naming it), and the full-order step on both backends, all in this one process -> ``benchmarks/rom.md`` (section
``rom-speed``) and ``benchmarks/results/rom_speed.json``.

    python benchmarks/rom_speed.py                       # sizes 1, 1.6, 2, 2.55; ~10 min on 2 cores
    python benchmarks/rom_speed.py --sizes 1,2 --report  # rewrite the section from the JSON only

The weights are an untrained g (Xavier, seed 0, latent 6, the normaliser of each size's reference body and
a displacement scale of 1 mm): the step's work does not depend on what g learned except through the inverse
map's Newton iterations (at most 8; near-identity maps converge in 1-2, a trained map in a few more), so the
measurement is of the architecture's scaling, not of a trained tower's accuracy (that needs the tower's
snapshots and training, not run yet). Each timing is the median of ``--repeats`` calls after two warm-up
calls; the reduced step is one compiled program.
"""
from __future__ import annotations

import statistics
import time
from pathlib import Path

import numpy as np
from _harness import RESULTS, csv, log, machine_info, md_table, parser, read_json, write_json, write_readme_section

MD = Path(__file__).resolve().parent / "rom.md"
JSON = RESULTS / "rom_speed.json"


def tower_overrides(size: float) -> list[str]:
    """rom_tower at ``size`` x its linear dimensions (the mesh, the domain, the caps' regions), dx unchanged."""
    s = float(size)
    lo, hi, top = -0.192 * s, 0.4224 * s, 0.7296 * s
    return ["scene=rom_tower", "scene.resolution=cpu", f"scene.bodies.tower.shape.scale={0.607 * s!r}",
            f"scene.bodies.tower.shape.translate=[0.0,0.0,{0.3635 * s!r}]",
            f"scene.domain.lo=[{lo!r},{lo!r},0.0]", f"scene.domain.hi=[{hi!r},{hi!r},{top!r}]",
            f"scene.boundaries.bottom.region.lo=[{lo!r},{lo!r},0.0]",
            f"scene.boundaries.bottom.region.hi=[{hi!r},{hi!r},{0.06 * s + 0.01!r}]",
            f"scene.boundaries.top.region.lo=[{lo!r},{lo!r},{0.667 * s - 0.01!r}]",
            f"scene.boundaries.top.region.hi=[{hi!r},{hi!r},{top!r}]"]


def timed(fn, repeats: int) -> float:
    """Median seconds of ``fn()`` (which blocks until its result is ready) after two warm-up calls."""
    fn(), fn()
    out = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
    return statistics.median(out)


def measure(size: float, samples: int, repeats: int, backends: list[str]) -> dict:
    import jax

    from mpmlab.build import build_scene
    from mpmlab.config import compose
    from mpmlab.rom import networks as N
    from mpmlab.rom.stepper import ReducedStepper
    from mpmlab.simulator import build_stepper

    scene = build_scene(compose(tower_overrides(size) + ["precision=fp32"]))
    row = {"size": size, "particles": int(scene.particles().count), "grid": list(scene.grid_shape),
           "samples": samples, "dt": float(scene.dt)}
    log(f"size {size}: {row['particles']} particles, grid {row['grid']}")
    fom, fom_w = {}, {}
    for b in backends:
        st = build_stepper(scene, b, "pic", "fp32")
        s = st.init()
        (fom if b == "jax" else fom_w)[b] = st
        step = lambda st=st, s=s: st._block(st._advance(s, 1))
        row[f"fom_{b}_s"] = timed(step, repeats)
        log(f"  full-order step, {b}: {row[f'fom_{b}_s'] * 1e3:.1f} ms")
    jfom = fom.get("jax") or build_stepper(scene, "jax", "pic", "fp32")
    X = np.asarray(jfom.particles.x)
    spec = N.RomSpec(dim=3, latent=6)
    norm = {"X_min": X.min(0), "X_max": X.max(0), "u_mean": np.zeros(3), "u_std": np.full(3, 1e-3)}
    w = N.RomWeights(N.init_params(spec, seed=0), norm, spec, 0)
    for nodes in ("compact", "scene"):
        rom = ReducedStepper(jfom, w, samples=samples, quadrature="eulerian", projection="linear", nodes=nodes)
        s0 = rom.init()
        row[f"rom_{nodes}_s"] = timed(lambda: jax.block_until_ready(rom.step(s0)), repeats)
        out = rom.step(s0)
        row[f"rom_{nodes}_unconverged"] = int(out.unconverged)
        log(f"  reduced step, {nodes} nodes: {row[f'rom_{nodes}_s'] * 1e3:.2f} ms")
        # the part the node set changes: the MPM step (P2G, grid update with its boundaries, G2P) of the
        # step's quadrature points and samples, alone
        M = rom._sample(s0.key)
        x, v, law, prm, rows, counts, windows = jax.jit(rom._eulerian_points)(s0, M)
        mpm = jax.jit(lambda st, p, w: jfom.step_fn(st, p, particle_bcs=False, update_law=False, nodes=w))
        st = {"x": x, "v": v, "law": law, "t": s0.t}
        row[f"mpm_{nodes}_s"] = timed(lambda: jax.block_until_ready(mpm(st, prm, windows)), repeats)
        row["quadrature_points"] = int(x.shape[0])
        log(f"  its MPM part, {nodes} nodes: {row[f'mpm_{nodes}_s'] * 1e3:.2f} ms ({x.shape[0]} points)")
    if "warp" in fom_w:
        # Warp's reduced model (torch networks, Warp MPM step of the quadrature's pseudo-particles) on both node
        # sets: the compact one (the samples' windows' nodes listed, node_list.py) and the scene grid (the box
        # of the reached nodes); then that Warp MPM step alone
        from rom_warp_phases import warp_node_sets

        row.update(warp_node_sets(fom_w["warp"], w, samples, repeats))
        for nodes in ("compact", "scene"):
            log(f"  reduced step, Warp ({nodes} nodes): {row[f'rom_warp_{nodes}_s'] * 1e3:.2f} ms; its MPM part "
                f"{row[f'mpm_warp_{nodes}_s'] * 1e3:.2f} ms")
    return row


def report(res: dict) -> None:
    rows = sorted(res["rows"], key=lambda r: r["particles"])
    if not rows:
        return
    first = rows[0]
    body = [f"`python benchmarks/rom_speed.py` ({res['machine'].get('cpu', '?')}; {res.get('when', '')}). "
            f"The `rom_tower` scene scaled at the `cpu` resolution's dx (19.2 mm, 27 particles per cell); one "
            f"Eulerian + linear reduced step at |M| = {first['samples']} (JAX, fp32, untrained g: the module doc "
            f"says why that measures the scaling) on the compact node set and on the scene's grid, and one "
            f"full-order PIC step per backend, all in the same run; medians of {res['repeats']} calls. Issue "
            f"16's target: the reduced step within 1.5x from 50k to 800k particles.", ""]
    fb = [b for b in ("jax", "warp") if f"fom_{b}_s" in first]
    wr = "rom_warp_compact_s" in first
    head = ["size", "particles", "grid", "reduced, compact nodes [ms]", "x the smallest", "reduced, scene grid [ms]",
            "x the smallest", "its MPM part, compact / scene [ms]"] + [f"full-order {b} [ms]" for b in fb] + \
        (["reduced, Warp, compact nodes [ms]", "x the smallest", "reduced, Warp, scene grid [ms]", "x the smallest",
          "its Warp MPM part, compact / scene [ms]"] if wr else [])

    def warp_cols(r):
        if not wr:
            return []
        if "rom_warp_compact_s" not in r:
            return ["–"] * 5
        return [f"{r['rom_warp_compact_s'] * 1e3:.1f}", f"{r['rom_warp_compact_s'] / first['rom_warp_compact_s']:.2f}",
                f"{r['rom_warp_scene_s'] * 1e3:.1f}", f"{r['rom_warp_scene_s'] / first['rom_warp_scene_s']:.2f}",
                f"{r['mpm_warp_compact_s'] * 1e3:.1f} / {r['mpm_warp_scene_s'] * 1e3:.1f}"]

    mpm = lambda r: (f"{r['mpm_compact_s'] * 1e3:.1f} / {r['mpm_scene_s'] * 1e3:.1f}" if "mpm_scene_s" in r else "–")
    body += md_table(head, [[f"{r['size']:g}", f"{r['particles']:,}", "x".join(map(str, r["grid"])),
                             f"{r['rom_compact_s'] * 1e3:.2f}", f"{r['rom_compact_s'] / first['rom_compact_s']:.2f}",
                             f"{r['rom_scene_s'] * 1e3:.2f}", f"{r['rom_scene_s'] / first['rom_scene_s']:.2f}", mpm(r)]
                            + [f"{r[f'fom_{b}_s'] * 1e3:.1f}" for b in fb] + warp_cols(r) for r in rows])
    if "quadrature_points" in first:
        body += ["", f"The reduced step's MPM part runs on {first['quadrature_points']:,} points (the quadrature's fixed "
                     f"budget, then the samples); the rest of the step is g, its Jacobians and the inverse map at those "
                     f"points, and the projection."]
    if wr:
        body += ["", "Warp's reduced model: torch networks and a Warp MPM step of the pseudo-particles, its grid update "
                     "over the samples' windows' nodes (compact, `backends/warp/node_list.py`) or over the box of the "
                     "reached nodes (scene grid); the last column times that Warp MPM step alone (one CPU thread)."]
    body.append("")
    write_readme_section(MD, "rom-speed", "The reduced step against the body's size (compact node set)", "\n".join(body))


def main() -> None:
    ap = parser(__doc__)
    ap.add_argument("--sizes", default="1,1.6,2,2.55")
    ap.add_argument("--samples", type=int, default=50)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--backends", default="jax,warp")
    ap.add_argument("--report", action="store_true", help="only rewrite the section from the JSON")
    a = ap.parse_args()
    res = read_json(JSON, {"rows": []})
    if not a.report:
        from _harness import quiet_warp
        quiet_warp()
        rows = [measure(float(s), a.samples, a.repeats, csv(a.backends)) for s in csv(a.sizes)]
        res = {"machine": machine_info(load=True), "when": time.strftime("%Y-%m-%d"), "repeats": a.repeats, "rows": rows}
        write_json(JSON, res)
    report(res)


if __name__ == "__main__":
    main()
