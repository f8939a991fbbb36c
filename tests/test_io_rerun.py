"""rerun recordings: positions, metrics, colouring, thinning, blueprint and streaming, read back from .rrd."""
from __future__ import annotations

import os

import numpy as np
import pytest
import rerun as rr
from rerun.chunk import RrdReader

import mpmlab
from mpmlab.core.errors import ConfigError
from mpmlab.core.state import Trajectory
from mpmlab.io import rerun as mrr
from mpmlab.io.metrics import compute_metrics


@pytest.fixture(autouse=True, scope="module")
def strict():
    was = rr.strict_mode()
    rr.set_strict_mode(True)
    yield
    rr.set_strict_mode(was)


@pytest.fixture(scope="module")
def stepper():
    scene = mpmlab.Scene(dim=2, dx=0.05, domain=([0, 0], [1, 1]), bodies=[
        mpmlab.Body(shape={"kind": "box", "lo": [0.4, 0.4], "hi": [0.6, 0.6]}, material="fixed_corotated",
                    params={"E": 2.0e4, "nu": 0.3}, velocity=[0.5, 0.0], angular_velocity=3.0)],
        gravity=[0, -9.8], boundaries=[mpmlab.boundaries.Walls()], dt=1e-4)
    return mpmlab.build_stepper(scene, backend="jax", transfer="mls", precision="fp64")


@pytest.fixture(scope="module")
def traj(stepper):
    return stepper.rollout(steps=35, every=5, fields=("F", "C"))  # 8 frames, 16 particles


def _traj3d(T=4, N=6) -> Trajectory:
    rng = np.random.default_rng(3)
    return Trajectory(
        x=rng.random((T, N, 3)), v=rng.standard_normal((T, N, 3)), time=np.arange(T) * 1e-3,
        step=np.arange(T, dtype=np.int64) * 10, mass=np.ones(N), volume=np.full(N, 8e-6),
        material_id=np.array([0, 0, 0, 1, 1, 1]), body_id=np.array([0, 0, 1, 1, 2, 2]),
        materials=[{"law": "fixed_corotated", "param_names": ["E", "nu"], "start": 0, "stop": 3,
                    "provenance": "mpmlab"},
                   {"law": "drucker_prager_jaumann", "param_names": ["E", "nu", "phi"], "start": 3, "stop": 6,
                    "provenance": "mpmlab"}],
        params=np.array([[1e5, 0.3, np.nan]] * 3 + [[1e5, 0.3, 30.0]] * 3),
        meta={"dim": 3, "dt": 1e-4, "dx": 0.1, "grid_origin": [0.0] * 3, "grid_shape": [11] * 3, "backend": "warp",
              "transfer": "mls", "precision": "fp32", "scene": "sand_and_jelly"},
        fields={"sigma": rng.standard_normal((T, 3, 3, 3)), "eps_p": rng.random((T, 3))},
        field_particles={"sigma": np.arange(3, 6), "eps_p": np.arange(3, 6)},
    )


def _colors(path, static: bool):
    rows = mrr.read_recording_component(path, "world/particles", "Points3D:colors") or \
        mrr.read_recording_component(path, "world/particles", "Points2D:colors")
    return {k: mrr.unpack_colors(v[-1]) for k, v in rows.items() if (k is None) == static}


def test_positions_metrics_and_layout(traj, tmp_path):
    p = mrr.write_recording(tmp_path / "run.rrd", traj, recording_id="run-0001")
    assert os.listdir(tmp_path) == ["run.rrd"]
    pos = mrr.read_recording_positions(p)
    assert sorted(pos) == list(range(traj.frame_count))
    for k, x in pos.items():
        assert x.dtype == np.float32
        np.testing.assert_array_equal(x, traj.x[k].astype(np.float32))

    got = mrr.read_recording_metrics(p)
    want = compute_metrics(traj)
    assert set(got) == {"mass", "linear_momentum/x", "linear_momentum/y", "kinetic_energy", "angular_momentum",
                        "gravity_potential_energy", "elastic_energy"}
    for name, (frames, values) in got.items():
        base, _, comp = name.partition("/")
        ref = want[base] if not comp else want[base][:, "xyz".index(comp)]
        np.testing.assert_array_equal(frames, np.arange(traj.frame_count))
        np.testing.assert_allclose(values, ref, rtol=1e-12, atol=1e-300)

    r = RrdReader(str(p))
    (entry,) = r.recordings()
    assert (entry.application_id, entry.recording_id) == ("mpmlab", "run-0001")
    assert len(r.blueprints()) == 1
    summary = r.stream().collect().summary()
    for entity in ("/world/particles", "/world/domain", "/metrics/kinetic_energy", "/scene/metadata"):
        assert entity in summary
    assert "sim_time" in summary and "Points2D:radii" in summary
    doc = mrr.read_recording_component(p, "scene/metadata", "TextDocument:text")[None][-1]
    text = "".join(map(str, doc)) if not isinstance(doc, str) else doc
    assert "fixed_corotated" in text and "jax" in text and "mls" in text
    radii = mrr.read_recording_component(p, "world/particles", "Points2D:radii")[None][-1]
    np.testing.assert_allclose(radii, 0.5 * np.sqrt(traj.volume), rtol=1e-6)


def test_sim_time_timeline(traj, tmp_path):
    p = mrr.write_recording(tmp_path / "t.rrd", traj, metrics=False)
    rows = mrr.read_recording_component(p, "world/particles", "Points2D:positions", index="sim_time")
    # durations come back as nanoseconds
    assert sorted(rows) == [round(t * 1e9) for t in traj.time]
    assert mrr.read_recording_metrics(p) == {}


def test_thinning_keeps_every_nth_and_last(traj, tmp_path):
    p = mrr.write_recording(tmp_path / "thin.rrd", traj, every=3)
    pos = mrr.read_recording_positions(p)
    assert sorted(pos) == [0, 3, 6, 7]
    np.testing.assert_array_equal(pos[6], traj.x[6].astype(np.float32))
    frames, _ = mrr.read_recording_metrics(p)["kinetic_energy"]
    assert list(frames) == list(range(traj.frame_count))  # metrics are not thinned


def test_color_by_material_is_static(traj, tmp_path):
    p = mrr.write_recording(tmp_path / "m.rrd", traj, color_by="material")
    static = _colors(p, static=True)
    assert _colors(p, static=False) == {}
    (c,) = static.values()
    assert c.shape == (traj.particle_count, 4)
    np.testing.assert_array_equal(c[:, :3], np.tile(mrr.PALETTE[0], (traj.particle_count, 1)))


@pytest.mark.parametrize("color_by", ["speed", "J"])
def test_color_by_scalar_per_frame(traj, tmp_path, color_by):
    p = mrr.write_recording(tmp_path / f"{color_by}.rrd", traj, color_by=color_by, every=2)
    per_frame = _colors(p, static=False)
    assert sorted(per_frame) == [0, 2, 4, 6, 7]
    for c in per_frame.values():
        assert c.shape == (traj.particle_count, 4)
    if color_by == "speed":  # the fastest particle over the run gets the top of the colour map
        speed = np.linalg.norm(traj.v, axis=-1)
        k, i = np.unravel_index(np.argmax(speed[[0, 2, 4, 6, 7]]), (5, traj.particle_count))
        frame = [0, 2, 4, 6, 7][k]
        np.testing.assert_array_equal(per_frame[frame][i, :3], mrr.scalar_colors(np.array([1.0]), 0.0, 1.0)[0])


def test_color_by_unavailable_lists_choices(traj, tmp_path):
    with pytest.raises(ConfigError) as e:
        mrr.write_recording(tmp_path / "s.rrd", traj, color_by="stress")
    msg = str(e.value)
    assert "material, body, speed, J" in msg and "sigma" in msg and "\n" not in msg
    with pytest.raises(ConfigError, match="choose one of"):
        mrr.write_recording(tmp_path / "s.rrd", traj, color_by="temperature")
    assert os.listdir(tmp_path) == []


def test_3d_fields_colouring_and_missing_values(tmp_path):
    t = _traj3d()
    assert mrr.color_choices(list(t.fields)) == ["material", "body", "speed", "eps_p", "stress"]
    p = mrr.write_recording(tmp_path / "s.rrd", t, color_by="stress", metrics={"loss": np.arange(4.0)})
    pos = mrr.read_recording_positions(p)
    assert pos[3].shape == (6, 3)
    np.testing.assert_array_equal(pos[3], t.x[3].astype(np.float32))
    c = _colors(p, static=False)[0]
    np.testing.assert_array_equal(c[:3, :3], np.tile(mrr.MISSING_COLOR, (3, 1)))  # no sigma on particles 0..2
    assert not np.any(np.all(c[3:, :3] == mrr.MISSING_COLOR, axis=1))
    assert set(mrr.read_recording_metrics(p)) == {"loss"}
    p2 = mrr.write_recording(tmp_path / "b.rrd", t, color_by="body", metrics=None)
    static = list(_colors(p2, static=True).values())[0][:, :3]
    np.testing.assert_array_equal(static, mrr.PALETTE[t.body_id])
    m = mrr.read_recording_metrics(p2)
    assert {"angular_momentum/x", "angular_momentum/z", "linear_momentum/z"} <= set(m)
    assert "elastic_energy" not in m  # no F recorded: not estimated


def test_refuses_overwrite_and_bad_metrics(traj, tmp_path):
    p = mrr.write_recording(tmp_path / "r.rrd", traj)
    before = p.read_bytes()
    with pytest.raises(ConfigError, match="already exists"):
        mrr.write_recording(p, traj)
    assert p.read_bytes() == before
    mrr.write_recording(p, traj, every=4, overwrite=True)
    assert sorted(mrr.read_recording_positions(p)) == [0, 4, 7]
    with pytest.raises(ConfigError, match="metric 'loss' has 2 entries"):
        mrr.write_recording(tmp_path / "x.rrd", traj, metrics={"loss": [1.0, 2.0]})
    assert sorted(os.listdir(tmp_path)) == ["r.rrd"]


def test_streaming_recording_from_rollout(stepper, traj, tmp_path):
    p = tmp_path / "live.rrd"
    with mrr.RecordingWriter(p, stepper=stepper, color_by="J", color_range=(0.9, 1.1), every=2) as w:
        assert not p.exists()
        stepper.rollout(steps=35, every=5, fields=("F",), on_frame=w)
    pos = mrr.read_recording_positions(p)
    assert sorted(pos) == [0, 2, 4, 6]
    np.testing.assert_array_equal(pos[4], traj.x[4].astype(np.float32))
    m = mrr.read_recording_metrics(p)
    # the on_frame state carries C (MLS) and F, so the streamed metrics match compute_metrics exactly
    np.testing.assert_allclose(m["angular_momentum"][1], compute_metrics(traj)["angular_momentum"], rtol=1e-12)
    np.testing.assert_allclose(m["elastic_energy"][1], compute_metrics(traj)["elastic_energy"], rtol=1e-12)
    assert os.listdir(tmp_path) == ["live.rrd"]
