"""Scenes: shapes, sampling, materials, initial velocity, time-step policy, bad input."""
import math

import numpy as np
import pytest

import mpmlab
from mpmlab.core.geometry import Box, Cylinder, Mesh, Sphere, sample


def body(shape, **kw):
    kw.setdefault("material", "fixed_corotated")
    return mpmlab.Body(shape=shape, **kw)


def test_regular_sampling_fills_box_volume_exactly():
    for dim, ppc in ((2, 4), (3, 8), (2, 9)):
        x, vol = sample(Box([0.2] * dim, [0.6] * dim), dim, 0.05, ppc)
        assert len(x) == round((0.4 / 0.05) ** dim) * ppc
        assert math.isclose(len(x) * vol, 0.4**dim, rel_tol=1e-12)


def test_sphere_cylinder_volume_converges():
    x, vol = sample(Sphere((0.5, 0.5, 0.5), 0.2), 3, 0.02, 8)
    assert abs(len(x) * vol - 4 / 3 * math.pi * 0.2**3) < 0.02 * 4 / 3 * math.pi * 0.2**3
    x, vol = sample(Cylinder((0.5, 0.1, 0.5), 0.1, 0.3, axis=1), 3, 0.02, 8)
    assert abs(len(x) * vol - math.pi * 0.01 * 0.3) < 0.03 * math.pi * 0.01 * 0.3
    assert np.all(x[:, 1] >= 0.1) and np.all(x[:, 1] <= 0.4)


def test_mesh_body(tmp_path):
    import trimesh

    path = tmp_path / "ball.stl"
    trimesh.creation.icosphere(subdivisions=2, radius=0.15).apply_translation([0.5, 0.5, 0.5]).export(path)
    x, vol = sample(Mesh(str(path)), 3, 0.02, 8)
    assert abs(len(x) * vol - 4 / 3 * math.pi * 0.15**3) < 0.05 * 4 / 3 * math.pi * 0.15**3
    with pytest.raises(mpmlab.ConfigError, match="does not exist"):
        Mesh(str(tmp_path / "missing.obj")).bounds(3)


def test_jittered_and_random_sampling():
    x, _ = sample(Box([0.2, 0.2], [0.6, 0.6]), 2, 0.05, 4, "jittered", seed=1)
    assert len(x) == 256 and np.all((x >= 0.2) & (x <= 0.6))
    x, vol = sample(Box([0.2, 0.2], [0.6, 0.6]), 2, 0.05, sampling="random", count=1000)
    assert len(x) == 1000 and math.isclose(vol * 1000, 0.16)
    with pytest.raises(mpmlab.ConfigError, match="perfect"):
        sample(Box([0.2, 0.2], [0.6, 0.6]), 2, 0.05, 3)


def test_multi_material_grouping_and_velocity():
    scene = mpmlab.Scene(dim=2, dx=0.05, domain=([0, 0], [1, 1]), bodies=[
        body({"kind": "box", "lo": [0.1, 0.1], "hi": [0.3, 0.3]}, velocity=[1.0, 0.0], name="a"),
        body({"kind": "sphere", "center": [0.7, 0.7], "radius": 0.1}, angular_velocity=2.0, density=500.0, name="b"),
        body({"kind": "box", "lo": [0.5, 0.1], "hi": [0.7, 0.2]}, params={"E": 3e4}, name="c")],
        dt=1e-4)
    P = scene.particles()
    assert len(P.groups) == 1 and P.groups[0].count == P.count     # one law -> one block
    assert np.allclose(P.v[P.body_id == 0], [1.0, 0.0])
    xb, vb = P.x[P.body_id == 1], P.v[P.body_id == 1]
    r = xb - xb.mean(0)
    assert np.allclose(vb, 2.0 * np.stack([-r[:, 1], r[:, 0]], 1))
    assert np.allclose(P.groups[0].params[P.body_id == 2][:, 0], 3e4)
    assert np.allclose(P.mass[P.body_id == 1], 500.0 * P.volume[P.body_id == 1])


def test_cfl_auto_and_refusal():
    scene = mpmlab.Scene(dim=2, dx=0.05, domain=([0, 0], [1, 1]), bodies=[
        body({"kind": "box", "lo": [0.1, 0.1], "hi": [0.3, 0.3]}, params={"E": 1e5, "nu": 0.3}, density=1000.0,
             velocity=[2.0, 0.0])], dt="auto", cfl=0.2)
    mu, lam = 1e5 / 2.6, 1e5 * 0.3 / (1.3 * 0.4)
    c = math.sqrt((lam + 2 * mu) / 1000.0)
    assert math.isclose(scene.resolve_dt(), 0.2 * 0.05 / (c + 2.0), rel_tol=1e-9)
    scene.dt = 0.9 * 0.05 / (c + 2.0)
    with pytest.raises(mpmlab.TimeStepError, match="cfl_limit"):
        scene.resolve_dt()


@pytest.mark.parametrize("bad, match", [
    (dict(params={"E": -1.0}), "outside its valid range"),
    (dict(params={"nu": 0.5}), "outside its valid range"),
    (dict(params={"youngs": 1.0}), "no parameter"),
    (dict(shape={"kind": "box", "lo": [0.9, 0.9], "hi": [1.2, 1.2]}), "outside the domain"),
    (dict(material="rubber"), "unknown law 'rubber'"),
    (dict(shape={"kind": "cube", "lo": [0, 0]}), "unknown shape"),
])
def test_bad_input_is_one_clear_sentence(bad, match):
    spec = dict(shape={"kind": "box", "lo": [0.1, 0.1], "hi": [0.3, 0.3]}, material="fixed_corotated")
    spec.update(bad)
    with pytest.raises(mpmlab.ConfigError, match=match) as err:
        mpmlab.Scene(dim=2, dx=0.05, domain=([0, 0], [1, 1]), bodies=[mpmlab.Body(**spec)], dt=1e-4).particles()
    assert "\n" not in str(err.value)


def test_each_body_law_is_built_once_and_serves_every_reader(monkeypatch):
    """``Scene._law`` builds a body's law instance once (``from_config``) and keeps it: sampling, the
    wave speed, dt: auto's safety factor, the capability check and the size budget all read it, and
    bodies of equal material and options share one instance."""
    from mpmlab.core import budget
    from mpmlab.core.interfaces import AbstractConstitutiveLaw
    from mpmlab.simulator import check_capabilities
    from mpmlab.transfers import make_transfer

    built = []
    orig = AbstractConstitutiveLaw.from_config.__func__

    def counting(cls, options, where):
        built.append((cls.name, where))
        return orig(cls, options, where)

    monkeypatch.setattr(AbstractConstitutiveLaw, "from_config", classmethod(counting))
    scene = mpmlab.Scene(dim=2, dx=0.05, domain=([0, 0], [1, 1]), bodies=[
        body({"kind": "box", "lo": [0.1, 0.1], "hi": [0.3, 0.3]}, name="a"),
        body({"kind": "box", "lo": [0.5, 0.1], "hi": [0.7, 0.3]}, name="b"),
        body({"kind": "box", "lo": [0.1, 0.5], "hi": [0.3, 0.7]}, material="hencky_von_mises", name="c")],
        dt="auto")
    budget.estimate_memory(scene)               # before sampling: reads the instances, samples nothing
    assert "_particles" not in vars(scene)
    P = scene.particles()
    scene.wave_speed(); scene.resolve_dt(); scene.cfl_number(1e-4); scene.effective_cfl
    check_capabilities(scene, "jax", make_transfer("mls"))
    budget.estimate_memory(scene)
    assert [w for _, w in built] == [f"scene 'scene', body {n}" for n in "abc"]     # once per body
    assert scene._law(0) is scene._law(1) is P.groups[0].law and scene._law(2) is P.groups[1].law
    assert scene.body_laws() == [P.groups[0].law, P.groups[0].law, P.groups[1].law]
