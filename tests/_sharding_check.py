"""The sharded-stepper checks of ``tests/test_sharding.py``, in a process of its own: XLA reads
``XLA_FLAGS=--xla_force_host_platform_device_count=N`` once, when JAX starts, so the forced host devices
cannot be had inside the pytest process. Prints one JSON line: the largest differences against the
single-device stepper.

    XLA_FLAGS=--xla_force_host_platform_device_count=3 python tests/_sharding_check.py OUT_DIR
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from mpmlab.cli import main
from mpmlab.io.h5 import read_trajectory
from mpmlab.observations import Lagrangian
from mpmlab.simulator import build_stepper
from mpmlab.testing import law_scene

TRANSFERS = ("pic", "flip", "apic", "mls", "tpic")
LAWS = ("fixed_corotated", "hencky_drucker_prager", "hencky_von_mises", "weakly_compressible",
        "newtonian_fluid", "drucker_prager_jaumann")
#: long enough for every body to land on the 2-cell walls (y < 0.1 from step ~100) and deform there
STEPS, EVERY = 160, 40
GRAD_STEPS = [10, 20]


def max_abs(a, b) -> float:
    return float(np.max(np.abs(np.asarray(a, np.float64) - np.asarray(b, np.float64)), initial=0.0))


def max_rel(a, b) -> float:
    """max |a - b| / max |a|: fields with units (sigma in Pa) compared at their own scale."""
    scale = float(np.max(np.abs(np.asarray(a, np.float64)), initial=0.0))
    return max_abs(a, b) / scale if scale > 0 else max_abs(a, b)


def trajectories(runs) -> dict:
    """Per (transfer, devices): max |sharded - single| of x and v over every kept frame, max relative
    difference of each carried field, and the lowest particle height reached (the walls' inner face is
    at y = 0.1: every run has bodies pressed into the floor)."""
    scene = law_scene(list(LAWS), 2)    # one body per law: six material groups of 16 and 12 particles
    out = {}
    for tr, counts in runs.items():
        one = build_stepper(scene, "jax", tr, "fp64")
        fields = tuple(f for f in ("F", "C", "J", "sigma", "eps_p")
                       if f in one.state_field_names or (f == "C" and one.transfer.needs_affine))
        a = one.rollout(steps=STEPS, every=EVERY, fields=fields, progress=False)
        for n in counts:
            b = build_stepper(scene, "jax", tr, "fp64", devices=n).rollout(steps=STEPS, every=EVERY, fields=fields,
                                                                            progress=False)
            assert b.x.shape == a.x.shape, (b.x.shape, a.x.shape)       # no padding particle shows
            out[f"{tr}/{n}"] = {"x": max_abs(a.x, b.x), "v": max_abs(a.v, b.v),
                                "fields_rel": {f: max_rel(a.fields[f], b.fields[f]) for f in fields},
                                "min_y": float(a.x[..., 1].min())}
    return out


def shapes(devices: int) -> dict:
    """APIC with uGIMP, the one shape function with per-particle data (lp, laid out with the particles, the
    clones keeping their twins'; the B-splines change only the window, which the sharded stepper shares
    with the single-device one): max |sharded - single| of x, v and relative of C over the kept frames."""
    scene = law_scene(list(LAWS), 2)
    out = {}
    for shape in ("ugimp",):
        a, b = (build_stepper(scene, "jax", "apic", "fp64", devices=n, shape=shape).rollout(
            steps=STEPS, every=EVERY, fields=("C",), progress=False) for n in (None, devices))
        out[shape] = {"x": max_abs(a.x, b.x), "v": max_abs(a.v, b.v), "C_rel": max_rel(a.fields["C"], b.fields["C"])}
    return out


def gradients(devices: int, transfer: str) -> dict:
    """jax.grad of a loss of observed velocities w.r.t. the controls (initial x, v, C and law state, law
    parameters, mass, volume, gravity): max |sharded - single| / max |single| per control, on an elastic
    body and a fluid body (two material groups; on 3 devices the 16 elastic particles are padded to 18)."""
    scene = law_scene(["fixed_corotated", "weakly_compressible"], 2, dt=2e-3)
    obs = Lagrangian(quantity="v")
    grads = []
    for n in (None, devices):
        st = build_stepper(scene, "jax", transfer, "fp64", devices=n)
        c = st.controls()
        w = jnp.asarray(np.random.default_rng(0).standard_normal((len(GRAD_STEPS), st.particles.count, 2)))
        loss = lambda c_: jnp.sum(w * st.observe(c_, obs, GRAD_STEPS, segment=5))  # noqa: E731
        grads.append(jax.jit(jax.value_and_grad(loss))(c))
    (l1, g1), (ln, gn) = grads
    res = {"loss_rel": abs(float(ln) - float(l1)) / abs(float(l1))}
    other = {jax.tree_util.keystr(p): a for p, a in jax.tree_util.tree_leaves_with_path(gn)}
    for path, a in jax.tree_util.tree_leaves_with_path(g1):
        key = jax.tree_util.keystr(path)
        if np.any(np.asarray(a)):        # the walls' parameters get no gradient here
            res[key] = max_rel(a, other[key])
    return res


def cli(out_dir: Path, devices: int) -> dict:
    """`mpmlab backend.devices=N` against one device through the CLI (dt: auto, two materials, walls)."""
    common = ["scene=jelly_pool_drop", "scene.resolution=tiny", "precision=fp64", "steps=20", "frame_every=10",
              "output.recording=false", "output.plots=false"]
    runs = {}
    for n in (1, devices):
        d = out_dir / f"devices_{n}"
        code = main(common + [f"backend.devices={n}", f"hydra.run.dir={d}"])
        assert code == 0, code
        runs[n] = (read_trajectory(d / "trajectory.h5"), json.loads((d / "summary.json").read_text()))
    (a, _), (b, sb) = runs[1], runs[devices]
    return {"x": max_abs(a.x, b.x), "v": max_abs(a.v, b.v), "summary_devices": sb.get("devices"),
            "status": sb["status"], "containment": sb["containment"] == runs[1][1]["containment"]}


if __name__ == "__main__":
    out = Path(sys.argv[1])
    n = len(jax.devices())
    # n = 3: the groups of 16 particles do not split evenly, so padding clones are in those runs
    runs = {tr: (n, 2) if tr == "mls" and n > 2 else (n,) for tr in TRANSFERS}
    report = {"devices": n, "trajectories": trajectories(runs), "gradients": {"apic": gradients(n, "apic")},
              "cli": cli(out, n), "shapes": shapes(n)}
    print(json.dumps(report))
