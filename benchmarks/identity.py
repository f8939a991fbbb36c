"""Bit-identity of built-in trajectories and gradients between two trees (issue #13, "must not change").

Dumps, for every built-in law x transfer x dimension x precision on the conformance scene
(``tests/scenes.py all_laws_scene``) and both backends, the state after 50 steps, and the gradient
of a fixed observation loss with respect to x, v and the law parameters (fp64, 20 steps). Run it once
per tree, then compare::

    PYTHONPATH=/tmp/parent python benchmarks/identity.py dump /tmp/id_parent.npz
    python benchmarks/identity.py dump /tmp/id_new.npz
    python benchmarks/identity.py compare /tmp/id_parent.npz /tmp/id_new.npz

Trajectories must match with ``np.array_equal``; gradients to 1e-12 (relative to the largest entry).
Only API present in both trees is used (``build_stepper``, ``rollout``, ``controls``, ``observe``).
"""
from __future__ import annotations

import argparse
import os
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, ".."))     # tests/scenes.py

LAWS = ("fixed_corotated", "hencky_drucker_prager", "hencky_von_mises", "weakly_compressible",
        "newtonian_fluid", "drucker_prager_jaumann")
TRANSFERS = ("pic", "flip", "apic", "mls", "tpic")
FIELDS = ("F", "J", "sigma", "eps_p", "C")


def dump(path: str, quick: bool = False, grads_only: bool = False) -> None:
    import mpmlab
    from mpmlab.observations import Lagrangian
    from tests.scenes import all_laws_scene

    out = {}
    dims = (2,) if quick else (2, 3)
    for dim in dims:
        scene = all_laws_scene(dim, list(LAWS))
        for tr in TRANSFERS:
            for prec in () if grads_only else ("fp64", "fp32"):
                for be in ("jax", "warp"):
                    st = mpmlab.build_stepper(scene, be, tr, prec)
                    traj = st.rollout(steps=50, every=50, fields=FIELDS)
                    key = f"{be}/{tr}/{dim}d/{prec}"
                    out[key + "/x"] = traj.x[-1]
                    out[key + "/v"] = traj.v[-1]
                    for f, a in traj.fields.items():
                        out[f"{key}/{f}"] = a[-1]
                    print(key, flush=True)
            # gradients, fp64, 20 steps, a loss on positions and velocities
            for be in ("jax", "warp"):
                st = mpmlab.build_stepper(scene, be, tr, "fp64")
                obs = Lagrangian(quantity="x")
                steps = (5, 20)
                n = st.particles.count
                w = np.sin(np.arange(2 * n * dim, dtype=float)).reshape(2, n, dim)
                c = st.controls()
                key = f"grad/{be}/{tr}/{dim}d"
                if be == "jax":
                    import jax
                    import jax.numpy as jnp
                    sub = {k: c[k] for k in ("x", "v", "law")}

                    def loss(s):
                        cc = dict(c); cc.update(s)
                        return jnp.sum(st.observe(cc, obs, steps) * w)
                    val, g = jax.value_and_grad(loss)(sub)
                    grads = {"x": np.asarray(g["x"]), "v": np.asarray(g["v"])}
                    for i, a in enumerate(g["law"]):
                        grads[f"law{i}"] = np.asarray(a)
                else:
                    import torch
                    leaves = [c["x"], c["v"], *c["law"]]
                    for a in leaves:
                        a.requires_grad_(True)
                    val = (st.observe(c, obs, steps) * torch.tensor(w)).sum()
                    val.backward()
                    grads = {"x": c["x"].grad.numpy(), "v": c["v"].grad.numpy()}
                    for i, a in enumerate(c["law"]):
                        grads[f"law{i}"] = a.grad.numpy()
                    val = float(val.detach())
                out[key + "/loss"] = np.asarray(float(val))
                for k, a in grads.items():
                    out[f"{key}/{k}"] = a
                print(key, flush=True)
    np.savez(path, **out)
    print(f"wrote {len(out)} arrays to {path}")


def compare(a_path: str, b_path: str, common: bool = False) -> int:
    a, b = np.load(a_path), np.load(b_path)
    bad = 0
    missing = [] if common else sorted(set(a.files) ^ set(b.files))
    for k in missing:
        print(f"MISSING {k} (in {'first' if k in a.files else 'second'} only)")
        bad += 1
    same = ngrad = 0
    worst = 0.0
    for k in sorted(set(a.files) & set(b.files)):
        x, y = a[k], b[k]
        if k.startswith("grad/"):
            ngrad += 1
            r = float(np.max(np.abs(x - y)) / max(np.max(np.abs(x)), 1e-300)) if x.size else 0.0
            worst = max(worst, r)
            if not r <= 1e-12:
                print(f"GRADIENT {k}: relative difference {r:.3e} > 1e-12")
                bad += 1
        elif np.array_equal(x, y):
            same += 1
        else:
            print(f"DIFFERS {k}: max |a - b| = {np.max(np.abs(x - y)):.3e}")
            bad += 1
    print(f"{same} trajectory arrays bit-identical; {ngrad} gradient arrays, worst relative difference "
          f"{worst:.3e}; {bad} problem(s)")
    return 1 if bad else 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    d = sub.add_parser("dump"); d.add_argument("path"); d.add_argument("--quick", action="store_true")
    d.add_argument("--grads-only", action="store_true", help="only the gradients (a change to the gradient path)")
    c = sub.add_parser("compare"); c.add_argument("a"); c.add_argument("b")
    c.add_argument("--common", action="store_true", help="compare only the arrays both files hold")
    args = ap.parse_args(argv)
    if args.cmd == "dump":
        dump(args.path, args.quick, args.grads_only)
        return 0
    return compare(args.a, args.b, args.common)


if __name__ == "__main__":
    raise SystemExit(main())
