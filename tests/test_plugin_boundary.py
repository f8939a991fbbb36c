"""A plugin boundary differentiable on both backends (issue #13 item 5): the example plugin's conveyor
floor, registered from its source folder. JAX and Warp agree on the trajectory and on the gradient with
respect to the belt speed, and the gradient matches central differences."""
from __future__ import annotations

import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import torch

import mpmlab
from mpmlab.boundaries import Walls
from mpmlab.core import registry
from mpmlab.observations import Lagrangian

PLUGIN = Path(__file__).resolve().parents[1] / "examples" / "mpmlab-example-plugin"


def conveyor_scene():
    if "conveyor" not in registry.boundaries.names():
        sys.path.insert(0, str(PLUGIN))
        registry.boundaries.register("conveyor", "mpmlab_example_plugin.conveyor:Conveyor", provenance="tests")
    Conveyor = registry.boundaries.get("conveyor")
    body = mpmlab.Body(shape={"kind": "box", "lo": [0.3, 0.1], "hi": [0.5, 0.2]}, material="fixed_corotated",
                       params={"E": 2e4}, particles_per_cell=4, velocity=[0.0, -0.3])
    return mpmlab.Scene(dim=2, dx=0.05, domain=([0, 0], [1, 1]), gravity=[0, -9.8], dt=1e-3, bodies=[body],
                        boundaries=[Walls(default="slip", faces={"y-": "none"}, thickness=2),
                                    Conveyor(speed=0.4, thickness=2)], name="conveyor")


def test_conveyor_gradient_on_both_backends():
    scene = conveyor_scene()
    sj = mpmlab.build_stepper(scene, "jax", "apic", "fp64")
    sw = mpmlab.build_stepper(scene, "warp", "apic", "fp64")
    a, b = sj.rollout(steps=30, every=30), sw.rollout(steps=30, every=30)
    assert np.max(np.abs(a.x - b.x)) <= 1e-12
    assert np.mean(a.v[-1][:, 0]) > 0.05, "the belt must drag the body along x"
    obs, steps = Lagrangian(quantity="x"), (10, 20)
    c = sj.controls()
    n = sj.particles.count
    w = np.cos(np.arange(2 * n * 2)).reshape(2, n, 2)

    def loss(speed):
        bc = list(c["boundary"])
        bc[1] = {"speed": speed}
        return jnp.sum(sj.observe({**c, "boundary": tuple(bc)}, obs, steps) * w)

    s0 = c["boundary"][1]["speed"]
    gj = float(jax.grad(loss)(s0)[0])
    cw = sw.controls()
    cw["boundary"][1]["speed"].requires_grad_(True)
    (sw.observe(cw, obs, steps) * torch.tensor(w)).sum().backward()
    gw = float(cw["boundary"][1]["speed"].grad[0])
    assert abs(gj) > 1e-6
    assert abs(gj - gw) <= 1e-9 * abs(gj)
    h = 1e-4
    fd = (float(loss(s0 + h)) - float(loss(s0 - h))) / (2 * h)
    assert abs(fd - gj) <= 1e-6 * abs(gj), (fd, gj)
