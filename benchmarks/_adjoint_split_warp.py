"""Warp gradient path: per-kernel forward / adjoint time, and fwd+bwd / forward, generated vs
hand-written adjoints (issue 17, item 1, Warp half).

Scene: the 2D Ritter dam break of ``benchmarks/gradients.py`` (``ritter_dam_break(dx=0.0125)``:
2560 particles, apic, fp32, newtonian fluid, slip walls). Everything runs in one process, the two
adjoint kinds alternating, so the machine's load hits both alike (it is reported, ``os.getloadavg``,
before and after).

* **Per kernel** (:func:`kernel_split`): ``steps`` steps are recorded, one ``wp.Tape`` per step (the
  gradient path's own recording, ``GradPath.step``); every launch of those tapes is then replayed
  alone, forward then adjoint, each followed by ``wp.synchronize_device`` and timed with
  ``time.perf_counter``; ms per step, the two kinds' tapes replayed alternately, minimum over ``reps``
  rounds (the least-disturbed replay on a shared machine; medians in the JSON). A launch recorded
  with its hand-written adjoint (``Tape.record_func``: ``adjoints.RecordedP2G``) is timed with its
  ``forward()`` and its adjoint call. B/F = sum of adjoint times / sum of forward times.
* **fwd+bwd / forward, in the path** (:func:`path_ratio`): the same without the torch bridge, CPU time.
* **fwd+bwd / forward** (:func:`ratio`): ``loss = sum(observe(c, Lagrangian('x'), steps=[N],
  segment=n)**2)`` and ``loss.backward()`` w.r.t. the initial velocity and the law parameters (as
  ``gradients.py``'s ``warp_fns``), against the forward alone (the same observe, segment = N, under
  ``torch.no_grad``); medians (and the ratio of the minima) of ``reps`` alternating repeats after a
  warm-up. ``n = "auto"`` keeps
  the recorded forward (``mpmlab.core.budget.resolve_segment``) when it fits: 1 + B/F instead of
  2 + B/F. ``steps_run`` counts the steps the path ran for one gradient (N: nothing recomputed).

Run::

    python benchmarks/_adjoint_split_warp.py              # table + benchmarks/results/adjoint_split_warp.json
    python benchmarks/_adjoint_split_warp.py --quick      # N = 40, dx 0.025, 2 reps (smoke)
    python benchmarks/_adjoint_split_warp.py --scene box3d  # 3D per-kernel split (13.8k particles)

``benchmarks/gradients.py`` can call :func:`warp_split` and merge its dict.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
RESULT = HERE / "results" / "adjoint_split_warp.json"
KINDS = ("generated", "hand")


def build(dx, transfer, precision, scene="ritter"):
    """``ritter``: the 2D Ritter dam break of ``gradients.py``; ``box3d``: a 3D block of water (0.3 m
    cube, ``dx``, 8 particles per cell, slip walls), for the 3D per-kernel split."""
    from mpmlab.simulator import build_stepper

    if scene == "ritter":
        from mpmlab.scenes.validation import ritter_dam_break

        return build_stepper(ritter_dam_break(dx=dx), "warp", transfer, precision)
    import mpmlab
    from mpmlab.boundaries import Walls
    from mpmlab.testing import options_of, params_of

    law = "newtonian_fluid"
    body = mpmlab.Body(shape={"kind": "box", "lo": [0.3] * 3, "hi": [0.6] * 3}, material=law, params=params_of(law),
                       density=1000.0, particles_per_cell=8, options=options_of(law))
    sc = mpmlab.Scene(dim=3, dx=dx, domain=([0.0] * 3, [1.0] * 3), bodies=[body], gravity=[0.0, -9.8, 0.0],
                      boundaries=[Walls(default="slip", thickness=2)], dt=1e-4, name="water_box_3d")
    return build_stepper(sc, "warp", transfer, precision)


def _label(path, launch):
    """Kernel group of a tape entry."""
    if callable(launch):
        return getattr(launch, "name", "recorded function")
    k = launch[0]
    if k is path.k_p2g:
        return "p2g"
    if k is path.k_grid:
        return "grid_update"
    if any(k is g for g in path.k_g2p):
        return "g2p+law"
    return "other: " + k.key.split("__")[0]


def _record_tapes(st, kind: str, steps: int, pool):
    import warp as wp
    from mpmlab.backends.warp import grad as wgrad

    path = wgrad.path_of(st)
    path.adjoints = kind
    names, flat = path.flatten(st.controls())
    ctl = path.to_warp(names, flat, grad=True)
    s = path.initial(ctl, grad=True)
    tapes = []
    t = 0.0
    for k in range(steps):
        tape = wp.Tape()
        with tape:
            s = path.step(s, ctl, t, grad=True, buf=pool[k])
        t += st.dt
        tapes.append(tape)
    return tapes, ctl


def _replay(path, tapes, f1, b1, clock=time.perf_counter):
    """Every launch of ``tapes`` alone, forward then adjoint, timed into f1 / b1 by kernel group with
    ``clock`` (``time.perf_counter``: wall; ``time.thread_time``: this thread's CPU time, which a loaded
    machine disturbs far less -- Warp runs CPU kernels on the launching thread)."""
    import warp as wp

    dev = path.dev
    for tape in tapes:
        for launch in tape.launches:
            name = _label(path, launch)
            if callable(launch):
                t0 = clock()
                launch.forward()
                wp.synchronize_device(dev)
                t1 = clock()
                launch()
                wp.synchronize_device(dev)
            else:
                kernel, dim, _, inputs, outputs, device = launch[:6]
                t0 = clock()
                wp.launch(kernel, dim=dim, inputs=inputs, outputs=outputs, device=device, record_tape=False)
                wp.synchronize_device(device)
                t1 = clock()
                wp.launch(kernel, dim=dim, inputs=inputs, outputs=outputs, device=device, adjoint=True,
                          adj_inputs=[tape.get_adjoint(a) for a in inputs],
                          adj_outputs=[tape.get_adjoint(a) for a in outputs], record_tape=False)
                wp.synchronize_device(device)
            f1[name] = f1.get(name, 0.0) + (t1 - t0)
            b1[name] = b1.get(name, 0.0) + (clock() - t1)


def kernel_split(st, kinds=KINDS, steps: int = 20, reps: int = 5) -> dict:
    """{kind: {group: {...}}}, ms per step, plus "all": the two kinds' tapes (separate step buffers) are
    replayed alternately, ``reps`` rounds after a warm-up round, each round once timed by the wall clock
    and once by CPU time (``thread_time``). Per group: ``fwd_ms`` / ``adj_ms`` = minimum wall time over the
    rounds (the least-disturbed replay), ``*_med_ms`` the median wall time, ``*_cpu_ms`` the minimum CPU
    time; ``ratio`` = adj_ms / fwd_ms, ``ratio_cpu`` likewise."""
    from mpmlab.backends.warp import grad as wgrad

    path = wgrad.path_of(st)
    pool = path.grad_buffers(steps * len(kinds))
    rec = {kind: _record_tapes(st, kind, steps, pool[i * steps:(i + 1) * steps]) for i, kind in enumerate(kinds)}
    T = {(kind, c, fb): {} for kind in kinds for c in ("wall", "cpu") for fb in "fb"}
    for rep in range(reps + 1):
        for clock, c in ((time.perf_counter, "wall"), (time.thread_time, "cpu")):
            for kind in kinds:
                f1, b1 = {}, {}
                _replay(path, rec[kind][0], f1, b1, clock)
                if rep == 0:
                    continue
                for k in f1:
                    T[kind, c, "f"].setdefault(k, []).append(f1[k] / steps * 1e3)
                    T[kind, c, "b"].setdefault(k, []).append(b1[k] / steps * 1e3)
    out = {}
    for kind in kinds:
        r = {}
        for k in T[kind, "wall", "f"]:
            r[k] = {"fwd_ms": min(T[kind, "wall", "f"][k]), "adj_ms": min(T[kind, "wall", "b"][k]),
                    "fwd_med_ms": float(np.median(T[kind, "wall", "f"][k])),
                    "adj_med_ms": float(np.median(T[kind, "wall", "b"][k])),
                    "fwd_cpu_ms": min(T[kind, "cpu", "f"][k]), "adj_cpu_ms": min(T[kind, "cpu", "b"][k])}
        r["all"] = {f: sum(v[f] for v in r.values()) for f in next(iter(r.values()))}
        for v in r.values():
            v["ratio"] = v["adj_ms"] / v["fwd_ms"]
            v["ratio_cpu"] = v["adj_cpu_ms"] / v["fwd_cpu_ms"]
        out[kind] = r
    return out


def ratio(st, N: int, segments=(20, "auto"), kinds=KINDS, reps: int = 5) -> dict:
    """fwd+bwd / forward per (adjoint kind, segment), alternating repeats in one process."""
    from mpmlab.backends.warp import grad as wgrad

    path = wgrad.path_of(st)
    from gradients import warp_fns      # the loss and gradient benchmarks/gradients.py times

    runs = {(kind, n): warp_fns(st, N, n) for kind in kinds for n in segments}
    fwd = next(iter(runs.values()))[0]
    res = {f"{kind}/{n}": {"fwd_s": [], "grad_s": []} for kind, n in runs}
    ref = None
    for (kind, n), (_, g) in runs.items():                # warm-up: kernels, buffer pools; checks
        path.adjoints = kind
        fwd()
        before = path.steps_run
        out = g()
        r = res[f"{kind}/{n}"]
        r["steps_run"] = path.steps_run - before
        if ref is None:
            ref = out
        gv, gv0 = out[1].numpy(), ref[1].numpy()
        r["grad_v_rel_diff_vs_first"] = float(np.abs(gv - gv0).max() / max(np.abs(gv0).max(), 1e-30))
        r["loss"] = out[0]
    for _ in range(reps):
        for (kind, n), (_, g) in runs.items():
            path.adjoints = kind
            c0, t0 = time.process_time(), time.perf_counter()
            fwd()
            c1, t1 = time.process_time(), time.perf_counter()
            g()
            c2, t2 = time.process_time(), time.perf_counter()
            r = res[f"{kind}/{n}"]
            r["fwd_s"].append(t1 - t0)
            r["grad_s"].append(t2 - t1)
            r.setdefault("fwd_cpu_s", []).append(c1 - c0)
            r.setdefault("grad_cpu_s", []).append(c2 - c1)
    for r in res.values():
        r["fwd_median_s"] = float(np.median(r["fwd_s"]))
        r["grad_median_s"] = float(np.median(r["grad_s"]))
        r["ratio"] = r["grad_median_s"] / r["fwd_median_s"]
        r["ratio_min"] = min(r["grad_s"]) / min(r["fwd_s"])
        r["ratio_cpu"] = float(np.median(r["grad_cpu_s"])) / float(np.median(r["fwd_cpu_s"]))
    return res


def path_ratio(st, N: int, segments=(20, "auto"), kinds=KINDS, reps: int = 7) -> dict:
    """The same gradient as :func:`ratio` inside the gradient path alone (``GradPath.forward`` /
    ``backward``, no torch bridge, seed = ones), CPU time (``process_time``), alternating repeats:
    {"forward_cpu_s": [...], "<kind>/<segment>": {"cpu_s": [...], "ratio_min", "ratio_median"}}. The
    least load-sensitive form of fwd+bwd / forward on a shared machine."""
    import torch
    from mpmlab.backends.warp import grad as wgrad
    from mpmlab.observations import Lagrangian

    path = wgrad.path_of(st)
    names, flat = path.flatten(st.controls())
    obs = Lagrangian(quantity="x")
    steps = (N,)
    seed = torch.ones((1, path.N, st.dim), dtype=torch.float64 if st.precision == "fp64" else torch.float32)

    def fwd():
        path.forward(names, flat, obs, steps, N, keep=False)

    def grad(n):
        keep = n == "auto"
        seg = N if keep else int(n)
        _, saved = path.forward(names, flat, obs, steps, seg, keep=keep)
        path.backward(names, flat, obs, steps, seg, saved, seed)
        if keep:
            saved.record.busy = False

    cfg = [(k, n) for k in kinds for n in segments]
    for k, n in cfg:                                   # warm-up
        path.adjoints = k
        grad(n)
    out = {"forward_cpu_s": []}
    for _ in range(reps):
        c0 = time.process_time()
        fwd()
        out["forward_cpu_s"].append(time.process_time() - c0)
        for k, n in cfg:
            path.adjoints = k
            c0 = time.process_time()
            grad(n)
            out.setdefault(f"{k}/{n}", {"cpu_s": []})["cpu_s"].append(time.process_time() - c0)
    f, fm = min(out["forward_cpu_s"]), float(np.median(out["forward_cpu_s"]))
    for k, n in cfg:
        r = out[f"{k}/{n}"]
        r["ratio_min"], r["ratio_median"] = min(r["cpu_s"]) / f, float(np.median(r["cpu_s"])) / fm
    return out


def warp_split(dx: float = 0.0125, transfer: str = "apic", precision: str = "fp32", N: int = 400,
               split_steps: int = 20, segments=(20, "auto"), kinds=KINDS, reps: int = 5, scene: str = "ritter",
               ratio_too: bool = True) -> dict:
    """The whole measurement as one dict (what ``__main__`` writes to ``RESULT``); ``ratio_too=False``
    skips the fwd+bwd / forward part (the per-kernel split only)."""
    import warp as wp

    load0 = os.getloadavg()
    st = build(dx, transfer, precision, scene)
    out = {"scene": {"name": "ritter_dam_break" if scene == "ritter" else "water_box_3d", "dim": st.dim,
                     "dx": dx, "transfer": transfer, "precision": precision,
                     "particles": int(st.particles.count), "grid": [int(g) for g in st.scene.grid_shape]},
           "N": N, "split_steps": split_steps, "reps": reps, "warp": wp.config.version,
           "cpus": len(os.sched_getaffinity(0)), "load_before": list(load0),
           "date": time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime())}
    kernel_split(st, kinds, 2, 1)                         # compile both kinds first (not timed)
    out["kernels"] = kernel_split(st, kinds, split_steps, reps)
    out["ratio"] = ratio(st, N, segments, kinds, reps) if ratio_too else {}
    out["path_ratio"] = path_ratio(st, N, segments, kinds, max(reps, 5)) if ratio_too else {}
    out["load_after"] = list(os.getloadavg())
    return out


def table(res) -> str:
    L = [f"{res['scene']['name']} dx={res['scene']['dx']} ({res['scene']['particles']} particles, "
         f"{res['scene']['transfer']}, {res['scene']['precision']}), Warp {res['warp']} CPU, {res['cpus']} cores; "
         f"load {res['load_before'][0]:.2f} before, {res['load_after'][0]:.2f} after; {res['date']}", "",
         f"Per kernel (ms per step, {res['split_steps']}-step tapes replayed launch by launch, the two kinds "
         f"alternating; minimum over {res['reps']} rounds):", "",
         "| kernel | forward (ms) | generated adjoint (ms) | B/F | forward (ms) | hand adjoint (ms) | B/F |",
         "|---|---|---|---|---|---|---|"]
    K = res["kernels"]
    gen, hand = K.get("generated", {}), K.get("hand", {})
    for sfx, what in (("", "wall time"), ("_cpu", "CPU time")):
        cell = lambda r: (f"{r['fwd' + sfx + '_ms']:.3f} | {r['adj' + sfx + '_ms']:.3f} | {r['ratio' + sfx]:.2f}"
                          if r else "- | - | -")
        for k in list(gen) + [k for k in hand if k not in gen]:
            L.append(f"| {k} ({what}) | {cell(gen.get(k))} | {cell(hand.get(k))} |")
    if not res["ratio"]:
        return "\n".join(L)
    L += ["", f"fwd+bwd / forward (N = {res['N']}, medians of {res['reps']} alternating repeats):", "",
          "| adjoints | segment | forward (s) | fwd+bwd (s) | ratio | ratio of minima | CPU time ratio | "
          "steps run per gradient | |dL/dv| diff |", "|---|---|---|---|---|---|---|---|---|"]
    for key, r in res["ratio"].items():
        kind, n = key.split("/")
        L.append(f"| {kind} | {n} | {r['fwd_median_s']:.3f} | {r['grad_median_s']:.3f} | **{r['ratio']:.2f}x** | "
                 f"{r['ratio_min']:.2f}x | {r['ratio_cpu']:.2f}x | {r['steps_run']} | {r['grad_v_rel_diff_vs_first']:.1e} |")
    pr = res.get("path_ratio") or {}
    if pr:
        L += ["", f"Inside the gradient path (GradPath.forward / backward, no torch bridge), CPU time, forward "
                  f"{min(pr['forward_cpu_s']):.3f} s (minimum):", "",
              "| adjoints | segment | fwd+bwd CPU (s, min) | ratio of minima | ratio of medians |", "|---|---|---|---|---|"]
        for key, r in pr.items():
            if key == "forward_cpu_s":
                continue
            kind, n = key.split("/")
            L.append(f"| {kind} | {n} | {min(r['cpu_s']):.3f} | **{r['ratio_min']:.2f}x** | {r['ratio_median']:.2f}x |")
    return "\n".join(L)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--dx", type=float, default=0.0125)
    ap.add_argument("--transfer", default="apic")
    ap.add_argument("--precision", default="fp32")
    ap.add_argument("--N", type=int, default=400)
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--segments", default="20,auto")
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--scene", default="ritter", choices=("ritter", "box3d"),
                    help="box3d: the 3D per-kernel split only (dx default 0.025, 13.8k particles)")
    ap.add_argument("--out", default=str(RESULT))
    a = ap.parse_args(argv)
    if a.quick:
        a.N, a.dx, a.reps = 40, 0.025, 2
    segs = tuple(s if s == "auto" else int(s) for s in a.segments.split(","))
    if a.scene == "box3d":
        dx = a.dx if a.dx != 0.0125 else 0.025
        res = warp_split(dx, a.transfer, a.precision, a.N, 5, segs, KINDS, a.reps, "box3d", ratio_too=False)
    else:
        res = warp_split(a.dx, a.transfer, a.precision, a.N, 20, segs, KINDS, a.reps)
    print(table(res))
    if not a.quick:
        out = Path(a.out)
        old = json.loads(out.read_text()) if out.exists() else {}
        old = old if "runs" in old else {"runs": {}}
        old["runs"][res["scene"]["name"]] = res          # one entry per scene, the latest run of each
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(old, indent=1))
        print(f"wrote {out}")
    return res


if __name__ == "__main__":
    sys.path.insert(0, str(HERE.parent))
    main()
