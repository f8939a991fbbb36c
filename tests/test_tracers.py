"""Tracer bodies (``Body(tracer=True)``: massless points, the ROM paper's Tab. 4 baseline): they change
nothing in the run they observe, and a tracer where a material point sits moves exactly as that point
does, on both backends."""
from __future__ import annotations

import numpy as np
import pytest

import mpmlab
from mpmlab.core.errors import ConfigError


def scene(tracers: bool, transfer_dim=2):
    box = {"kind": "box", "lo": [0.3, 0.3], "hi": [0.5, 0.45]}
    bodies = [mpmlab.Body(shape=box, material="fixed_corotated", params={"E": 2e4, "nu": 0.3}, density=1000.0,
                          particles_per_cell=4, velocity=[0.5, 0.2], name="block")]
    if tracers:
        bodies.append(mpmlab.Body(shape=box, material="fixed_corotated", params={"E": 2e4, "nu": 0.3},
                                  density=1000.0, particles_per_cell=4, velocity=[0.5, 0.2], tracer=True, name="tracers"))
        bodies.append(mpmlab.Body(shape={"kind": "box", "lo": [0.7, 0.7], "hi": [0.8, 0.8]}, material="fixed_corotated",
                                  params={"E": 2e4, "nu": 0.3}, density=1000.0, tracer=True, name="far"))
    return mpmlab.Scene(dim=2, dx=0.05, domain=([0.0, 0.0], [1.0, 1.0]), bodies=bodies, gravity=[0.0, -9.8], dt=1e-3,
                        name="tracers")


@pytest.mark.parametrize("backend", ("jax", "warp"))
@pytest.mark.parametrize("transfer", ("pic", "apic"))
def test_tracers_observe_without_changing_the_run(backend, transfer):
    ref = mpmlab.simulate(scene(False), 80, 80, backend, transfer, "fp64")
    run = mpmlab.simulate(scene(True), 80, 80, backend, transfer, "fp64")
    n = ref.x.shape[1]
    P = scene(True).particles()
    assert np.all(P.mass[n:] == 0) and np.all(P.volume[n:] == 0) and np.all(P.mass[:n] > 0)
    np.testing.assert_array_equal(run.x[-1][:n], ref.x[-1])                 # nothing put into the grid
    np.testing.assert_allclose(run.x[-1][n:2 * n], ref.x[-1], rtol=0, atol=1e-14)   # co-located: the same path
    far = run.x[:, 2 * n:]
    np.testing.assert_array_equal(far[-1], far[0])                           # no mass around: the grid is at rest
    assert np.max(np.abs(run.x[-1][:n] - run.x[0][:n])) > 0.02


def test_a_scene_of_tracers_only_is_refused():
    sc = scene(True)
    sc.bodies = sc.bodies[1:]
    with pytest.raises(ConfigError, match="every body is a tracer"):
        sc.particles()



def test_a_config_recorded_before_tracers_existed_still_builds():
    """rom_eval rebuilds scenes from the config a trajectory.h5 recorded (``mpmlab.config.recorded_config``);
    one written by an mpmlab without today's optional keys (a body's ``tracer``, ``lattice``, ``enabled``)
    still builds, each missing key at its default."""
    from omegaconf import OmegaConf

    from mpmlab.build import build_scene
    from mpmlab.config import compose, recorded_config

    cfg = OmegaConf.to_container(compose(["scene=rom_beam_2d", "scene.resolution=tiny"]), resolve=True)
    for b in cfg["scene"]["bodies"].values():
        for key in ("tracer", "lattice", "enabled"):
            del b[key]
    with pytest.raises(Exception):
        build_scene(OmegaConf.create(cfg))                 # as recorded: the keys are missing
    scene = build_scene(recorded_config(OmegaConf.to_yaml(cfg)))
    assert not any(b.tracer for b in scene.bodies) and scene.particles().mass.min() > 0
