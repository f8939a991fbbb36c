"""Warp gradient path: per-kernel forward / adjoint time, and fwd+bwd / forward, generated vs
hand-written adjoints (issue 17, item 1, Warp half).

Scene: the 2D Ritter dam break of ``benchmarks/gradients.py`` (``ritter_dam_break(dx=0.0125)``:
2560 particles, apic, fp32, newtonian fluid, slip walls). Everything runs in one process, the two
adjoint kinds alternating, so the machine's load hits both alike (it is reported, ``os.getloadavg``,
before and after).

* **Per kernel** (:func:`kernel_split`): ``steps`` steps are recorded, one ``wp.Tape`` per step (the
  gradient path's own recording, ``GradPath.step``); every launch of those tapes is then replayed
  alone, forward then adjoint, each followed by ``wp.synchronize_device`` and timed with
  ``time.perf_counter``; ms per step, median over ``reps`` replays of all tapes. A launch recorded
  with its hand-written adjoint (``Tape.record_func``: ``adjoints.RecordedP2G``) is timed with its
  ``forward()`` and its adjoint call. B/F = sum of adjoint times / sum of forward times.
* **fwd+bwd / forward** (:func:`ratio`): ``loss = sum(observe(c, Lagrangian('x'), steps=[N],
  segment=n)**2)`` and ``loss.backward()`` w.r.t. the initial velocity and the law parameters (as
  ``gradients.py``'s ``warp_fns``), against the forward alone (the same observe, segment = N, under
  ``torch.no_grad``); medians of ``reps`` alternating repeats after a warm-up. ``n = "auto"`` keeps
  the recorded forward (``mpmlab.core.budget.resolve_segment``) when it fits: 1 + B/F instead of
  2 + B/F. ``steps_run`` counts the steps the path ran for one gradient (N: nothing recomputed).

Run::

    python benchmarks/_adjoint_split_warp.py              # table + benchmarks/results/adjoint_split_warp.json
    python benchmarks/_adjoint_split_warp.py --quick      # N = 40, dx 0.025, 2 reps (smoke)

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


def build(dx, transfer, precision):
    from mpmlab.scenes.validation import ritter_dam_break
    from mpmlab.simulator import build_stepper

    return build_stepper(ritter_dam_break(dx=dx), "warp", transfer, precision)


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


def kernel_split(st, kind: str, steps: int = 20, reps: int = 5) -> dict:
    """{group: {"fwd_ms", "adj_ms", "ratio"}} per step, plus "all", for adjoint ``kind``."""
    import warp as wp
    from mpmlab.backends.warp import grad as wgrad

    path = wgrad.path_of(st)
    path.adjoints = kind
    names, flat = path.flatten(st.controls())
    ctl = path.to_warp(names, flat, grad=True)
    pool = path.grad_buffers(steps)
    s = path.initial(ctl, grad=True)
    tapes = []
    t = 0.0
    for k in range(steps):
        tape = wp.Tape()
        with tape:
            s = path.step(s, ctl, t, grad=True, buf=pool[k])
        t += st.dt
        tapes.append(tape)
    dev = path.dev
    fw, bw = {}, {}
    for rep in range(reps + 1):                        # the first replay warms caches, not kept
        f1, b1 = {}, {}
        for tape in tapes:
            for launch in tape.launches:
                name = _label(path, launch)
                if callable(launch):
                    t0 = time.perf_counter()
                    launch.forward()
                    wp.synchronize_device(dev)
                    t1 = time.perf_counter()
                    launch()
                    wp.synchronize_device(dev)
                else:
                    kernel, dim, _, inputs, outputs, device = launch[:6]
                    t0 = time.perf_counter()
                    wp.launch(kernel, dim=dim, inputs=inputs, outputs=outputs, device=device, record_tape=False)
                    wp.synchronize_device(device)
                    t1 = time.perf_counter()
                    wp.launch(kernel, dim=dim, inputs=inputs, outputs=outputs, device=device, adjoint=True,
                              adj_inputs=[tape.get_adjoint(a) for a in inputs],
                              adj_outputs=[tape.get_adjoint(a) for a in outputs], record_tape=False)
                    wp.synchronize_device(device)
                f1[name] = f1.get(name, 0.0) + (t1 - t0)
                b1[name] = b1.get(name, 0.0) + (time.perf_counter() - t1)
        if rep == 0:
            continue
        for k in f1:
            fw.setdefault(k, []).append(f1[k])
            bw.setdefault(k, []).append(b1[k])
    out = {}
    for k in fw:
        f, b = float(np.median(fw[k])) / steps * 1e3, float(np.median(bw[k])) / steps * 1e3
        out[k] = {"fwd_ms": f, "adj_ms": b, "ratio": b / f}
    F = sum(v["fwd_ms"] for v in out.values())
    B = sum(v["adj_ms"] for v in out.values())
    out["all"] = {"fwd_ms": F, "adj_ms": B, "ratio": B / F}
    return out


def _fns(st, N, segment):
    import torch
    from mpmlab.observations import Lagrangian

    obs = Lagrangian(quantity="x")
    c = st.controls()

    def fwd():
        with torch.no_grad():
            y = st.observe(c, obs, steps=[N], segment=N)
            return float((y * y).sum())

    def grad():
        v = c["v"].detach().clone().requires_grad_(True)
        law = tuple(a.detach().clone().requires_grad_(True) for a in c["law"])
        y = st.observe({**c, "v": v, "law": law}, obs, steps=[N], segment=segment)
        loss = (y * y).sum()
        loss.backward()
        return float(loss), v.grad.numpy().copy(), [a.grad.numpy().copy() for a in law]

    return fwd, grad


def ratio(st, N: int, segments=(20, "auto"), kinds=KINDS, reps: int = 5) -> dict:
    """fwd+bwd / forward per (adjoint kind, segment), alternating repeats in one process."""
    from mpmlab.backends.warp import grad as wgrad

    path = wgrad.path_of(st)
    runs = {(kind, n): _fns(st, N, n) for kind in kinds for n in segments}
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
        r["grad_v_rel_diff_vs_first"] = float(np.abs(out[1] - ref[1]).max() / max(np.abs(ref[1]).max(), 1e-30))
        r["loss"] = out[0]
    for _ in range(reps):
        for (kind, n), (_, g) in runs.items():
            path.adjoints = kind
            t0 = time.perf_counter()
            fwd()
            t1 = time.perf_counter()
            g()
            t2 = time.perf_counter()
            r = res[f"{kind}/{n}"]
            r["fwd_s"].append(t1 - t0)
            r["grad_s"].append(t2 - t1)
    for r in res.values():
        r["fwd_median_s"] = float(np.median(r["fwd_s"]))
        r["grad_median_s"] = float(np.median(r["grad_s"]))
        r["ratio"] = r["grad_median_s"] / r["fwd_median_s"]
    return res


def warp_split(dx: float = 0.0125, transfer: str = "apic", precision: str = "fp32", N: int = 400,
               split_steps: int = 20, segments=(20, "auto"), kinds=KINDS, reps: int = 5) -> dict:
    """The whole measurement as one dict (what ``__main__`` writes to ``RESULT``)."""
    import warp as wp

    load0 = os.getloadavg()
    st = build(dx, transfer, precision)
    out = {"scene": {"name": "ritter_dam_break", "dx": dx, "transfer": transfer, "precision": precision,
                     "particles": int(st.particles.count), "grid": [int(g) for g in st.scene.grid_shape]},
           "N": N, "split_steps": split_steps, "reps": reps, "warp": wp.config.version,
           "cpus": len(os.sched_getaffinity(0)), "load_before": list(load0),
           "date": time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime())}
    for kind in kinds:                                   # compile both kinds first (not timed)
        kernel_split(st, kind, 2, 1)
    out["kernels"] = {}
    for _ in range(2):                                   # two alternating rounds; keep the lower per kernel
        for kind in kinds:
            r = kernel_split(st, kind, split_steps, reps)
            prev = out["kernels"].get(kind)
            if prev is not None:
                for k in r:
                    for f in ("fwd_ms", "adj_ms"):
                        r[k][f] = min(r[k][f], prev[k][f])
                    r[k]["ratio"] = r[k]["adj_ms"] / r[k]["fwd_ms"]
            out["kernels"][kind] = r
    out["ratio"] = ratio(st, N, segments, kinds, reps)
    out["load_after"] = list(os.getloadavg())
    return out


def table(res) -> str:
    L = [f"Ritter dam break dx={res['scene']['dx']} ({res['scene']['particles']} particles, "
         f"{res['scene']['transfer']}, {res['scene']['precision']}), Warp {res['warp']} CPU, {res['cpus']} cores; "
         f"load {res['load_before'][0]:.2f} before, {res['load_after'][0]:.2f} after; {res['date']}", "",
         f"Per kernel (ms per step, {res['split_steps']}-step tapes replayed launch by launch, medians of "
         f"{res['reps']}):", "",
         "| kernel | forward (ms) | generated adjoint (ms) | B/F | hand adjoint (ms) | B/F |",
         "|---|---|---|---|---|---|"]
    K = res["kernels"]
    gen, hand = K.get("generated", {}), K.get("hand", {})
    for k in list(gen) + [k for k in hand if k not in gen]:
        g, h = gen.get(k), hand.get(k)
        f = (g or h)["fwd_ms"]
        L.append(f"| {k} | {f:.3f} | " + (f"{g['adj_ms']:.3f} | {g['ratio']:.2f}" if g else "- | -") + " | "
                 + (f"{h['adj_ms']:.3f} | {h['ratio']:.2f}" if h else "- | -") + " |")
    L += ["", f"fwd+bwd / forward (N = {res['N']}, medians of {res['reps']} alternating repeats):", "",
          "| adjoints | segment | forward (s) | fwd+bwd (s) | ratio | steps run per gradient | |dL/dv| diff |",
          "|---|---|---|---|---|---|---|"]
    for key, r in res["ratio"].items():
        kind, n = key.split("/")
        L.append(f"| {kind} | {n} | {r['fwd_median_s']:.3f} | {r['grad_median_s']:.3f} | **{r['ratio']:.2f}x** | "
                 f"{r['steps_run']} | {r['grad_v_rel_diff_vs_first']:.1e} |")
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
    ap.add_argument("--out", default=str(RESULT))
    a = ap.parse_args(argv)
    if a.quick:
        a.N, a.dx, a.reps = 40, 0.025, 2
    segs = tuple(s if s == "auto" else int(s) for s in a.segments.split(","))
    res = warp_split(a.dx, a.transfer, a.precision, a.N, 20, segs, KINDS, a.reps)
    print(table(res))
    if not a.quick:
        Path(a.out).parent.mkdir(parents=True, exist_ok=True)
        Path(a.out).write_text(json.dumps(res, indent=1))
        print(f"wrote {a.out}")
    return res


if __name__ == "__main__":
    sys.path.insert(0, str(HERE.parent))
    main()
