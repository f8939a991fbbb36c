"""Initial fields on bodies (issue 19 item 3): velocity, F and C as functions of position, arrays or
expression strings, on both backends, in frame 0 of trajectory.h5; JAX and Warp agree from them."""
import numpy as np
import pytest

import mpmlab
from mpmlab.boundaries import Walls
from mpmlab.core.errors import ConfigError


def F_of(x):
    """A per-particle F [N, 2, 2] (shear and stretch varying with position)."""
    F = np.zeros((len(x), 2, 2))
    F[:, 0, 0] = 1.0 + 0.05 * x[:, 0]
    F[:, 0, 1] = 0.02
    F[:, 1, 0] = 0.01 * x[:, 1]
    F[:, 1, 1] = 1.0 - 0.03 * x[:, 1]
    return F


C_SOLID = np.array([[0.5, -0.2], [0.3, 0.1]])
F_FLUID = np.array([[1.02, 0.01], [0.0, 0.99]])


def scene(**over):
    """A solid with an expression velocity, F from a function and a uniform C, and a J-only fluid with a
    constant F (-> J = det F) and an expression C."""
    solid = dict(shape={"kind": "box", "lo": [0.3, 0.3], "hi": [0.5, 0.5]}, material="fixed_corotated",
                 params={"E": 1e4}, particles_per_cell=4, velocity=["0.2 * x[1]", "-0.1 * sin(pi * x[0])"],
                 F=F_of, C=C_SOLID, name="solid")
    fluid = dict(shape={"kind": "box", "lo": [0.6, 0.3], "hi": [0.8, 0.5]}, material="weakly_compressible",
                 params={"bulk_modulus": 1e4}, particles_per_cell=4, velocity=[0.0, 0.1], F=F_FLUID,
                 C=[["0.1 * x[0]", "0.2 * x[1]"], [0, "-0.1"]], name="fluid")
    solid.update(over.pop("solid", {}))
    fluid.update(over.pop("fluid", {}))
    return mpmlab.Scene(dim=2, dx=0.1, domain=([0, 0], [1, 1]), gravity=[0, -1.0], dt=1e-3,
                        bodies=[mpmlab.Body(**solid), mpmlab.Body(**fluid)],
                        boundaries=[Walls(default="slip", thickness=2)], name="initial_fields", **over)


def expected(sc):
    P = sc.particles()
    x, s, f = P.x, P.body_id == 0, P.body_id == 1
    v = np.zeros_like(x)
    v[s, 0], v[s, 1] = 0.2 * x[s, 1], -0.1 * np.sin(np.pi * x[s, 0])
    v[f, 1] = 0.1
    C = np.zeros((len(x), 2, 2))
    C[s] = C_SOLID
    C[f, 0, 0], C[f, 0, 1], C[f, 1, 1] = 0.1 * x[f, 0], 0.2 * x[f, 1], -0.1
    return {"x": x, "v": v, "C": C, "F": F_of(x[s]), "J": np.full(f.sum(), np.linalg.det(F_FLUID))}


@pytest.fixture(scope="module")
def runs():
    sc = scene()
    return sc, {b: mpmlab.simulate(sc, steps=5, every=5, backend=b, transfer="apic", precision="fp64",
                                   fields=("F", "C", "J")) for b in ("jax", "warp")}


@pytest.mark.parametrize("backend", ["jax", "warp"])
def test_initial_fields_round_trip_through_h5(runs, backend, tmp_path):
    from mpmlab.io import read_trajectory, write_trajectory

    sc, trajs = runs
    write_trajectory(tmp_path / "t.h5", trajs[backend])
    tr = read_trajectory(tmp_path / "t.h5")
    want = expected(sc)
    P = sc.particles()
    np.testing.assert_array_equal(tr.field_particles["F"], np.nonzero(P.body_id == 0)[0])
    np.testing.assert_array_equal(tr.field_particles["J"], np.nonzero(P.body_id == 1)[0])
    for k in ("x", "v"):
        np.testing.assert_allclose(getattr(tr, k)[0], want[k], rtol=0, atol=1e-15, err_msg=k)
    for k in ("F", "C", "J"):
        np.testing.assert_allclose(tr.fields[k][0], want[k], rtol=0, atol=1e-15, err_msg=k)


def test_backends_agree_from_initial_fields(runs):
    """Five steps from the same nonzero v, F, C (and J) on JAX and Warp, fp64: the same state."""
    _, t = runs
    a, b = t["jax"], t["warp"]
    assert np.abs(a.fields["C"][-1] - a.fields["C"][0]).max() > 1e-3      # the run moved away from frame 0
    for k in ("x", "v"):
        d = np.abs(getattr(a, k)[-1] - getattr(b, k)[-1]).max()
        assert d <= 1e-9 * max(1.0, np.abs(getattr(a, k)[-1]).max()), (k, d)
    for k in ("F", "C", "J"):
        d = np.abs(a.fields[k][-1] - b.fields[k][-1]).max()
        assert d <= 1e-9 * max(1.0, np.abs(a.fields[k][-1]).max()), (k, d)


def test_initial_fields_reach_the_controls():
    """Gradient rollouts start where rollouts do: controls() carry the initial F / J and C."""
    sc = scene()
    want = expected(sc)
    for backend in ("jax", "warp"):
        c = mpmlab.build_stepper(sc, backend, "apic", "fp64").controls()
        np.testing.assert_allclose(np.asarray(c["C"]), want["C"], atol=1e-15)
        np.testing.assert_allclose(np.asarray(c["law_state"][0]["F"]), want["F"], atol=1e-15)
        np.testing.assert_allclose(np.asarray(c["law_state"][1]["J"]), want["J"], atol=1e-15)


def test_bad_initial_fields_are_refused():
    def refused(match, **over):
        with pytest.raises(ConfigError, match=match):
            scene(**over).particles()

    refused(r"body solid: F of particle 0 .* has det F = -1; .* det F > 0", solid={"F": [[-1.0, 0.0], [0.0, 1.0]]})
    refused(r"body solid: F has shape \[3, 3\]; give \[2, 2\] \(every particle\) or \[16, 2, 2\]",
            solid={"F": np.eye(3)})
    refused(r"body fluid: velocity has shape \[3\]", fluid={"velocity": [0.0, 0.1, 0.0]})
    refused(r"body solid: C\[1\]\[0\]: 'y': unknown name 'y'", solid={"C": [[0, 0], ["y", 0]]})
    refused(r"body solid: velocity of particle 0 .* is not finite", solid={"velocity": lambda x: x * np.inf})
    refused(r"the velocity function failed", solid={"velocity": lambda x: x[:, 7]})
    sc = scene()
    with pytest.raises(ConfigError, match="body solid, fluid sets an initial C, but transfer 'pic' stores no C"):
        mpmlab.build_stepper(sc, "jax", "pic", "fp64")
    from mpmlab.core.initial_fields import law_state_from_F
    from types import SimpleNamespace

    with pytest.raises(ConfigError, match="law 'clocked' has no F or J in its state"):
        law_state_from_F(SimpleNamespace(name="clocked", state_fields=("clock",)), np.eye(2)[None], "body b")


def test_profiled_scene_is_a_velocity_function():
    """ProfiledScene (the validation scenes' position-dependent velocity) now sets each body's velocity to
    its own plus the profile: the same particle velocities as before."""
    from mpmlab.scenes.validation import bar_reference, vibrating_bar

    sc = vibrating_bar(cells=10)
    P = sc.particles()
    beta = bar_reference()["beta"]
    np.testing.assert_allclose(P.v[:, 0], 0.1 * np.sin(beta * P.x[:, 0]), atol=1e-15)
    assert not P.v[:, 1].any() and callable(sc.bodies[0].velocity)


def test_initial_fields_from_the_scene_config():
    """scene.bodies.<b>.velocity / F / C take expression strings in the YAML config (and on the command
    line); a body_force with an expression field is a boundary entry (field, values)."""
    from omegaconf import OmegaConf, open_dict

    from mpmlab.config import BoundaryConfig, build_scene, compose

    cfg = compose(["scene=dam_break_2d", "scene.resolution=tiny", "scene.bodies.water.velocity=['0.5 * x[1]',0]",
                   "scene.bodies.water.F=[[0.98,0],[0,0.98]]"])
    # (a new boundary entry from a YAML file; Hydra's command line cannot add one to the typed dict)
    push = OmegaConf.structured(BoundaryConfig(kind="body_force", field="expression",
                                               values={"b": ["a * t", 0], "constants": {"a": 2.0}}))
    with open_dict(cfg):
        cfg.scene.boundaries["push"] = push
    sc = build_scene(cfg)
    P = sc.particles()
    np.testing.assert_allclose(P.v[:, 0], 0.5 * P.x[:, 1], atol=1e-15)
    np.testing.assert_allclose(P.groups[0].initial_state(2)["J"], 0.98**2, atol=1e-15)   # newtonian_fluid: J only
    bf = sc.boundaries[-1]
    assert bf.field == "expression" and bf.packed(2).tolist() == [2.0]
    with open_dict(cfg):
        cfg.scene.boundaries.push.field = "nope"
    with pytest.raises(ConfigError, match="unknown field 'nope'"):
        build_scene(cfg)
