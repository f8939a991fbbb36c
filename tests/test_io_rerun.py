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
    # equal volumes: one radius, which rerun gives every particle (a per-particle radii array would be a
    # fourth per-particle component, and rerun's hover card then hides Particle:values)
    np.testing.assert_allclose(np.broadcast_to(radii, traj.volume.shape), 0.5 * np.sqrt(traj.volume), rtol=1e-6)


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


# ---------------------------------------------------------------------------------------------
# what a person sees (issue 14): per-particle values, one plot per quantity family, units, ids
# ---------------------------------------------------------------------------------------------
def _per_particle_components(path, frame, n):
    """Components of world/particles with one value per particle at ``frame`` (static or logged)."""
    summary = RrdReader(str(path)).stream().filter(content="/world/particles").collect().summary()
    cols = {c for line in summary.splitlines() for c in line.split("cols=")[-1].strip("[]").replace("'", "").split(", ")
            if ":" in c}
    out = []
    for comp in sorted(cols):
        rows = mrr.read_recording_component(path, "world/particles", comp)
        row = rows.get(frame, rows.get(None))
        if row is not None and len(row[-1]) == n:
            out.append(comp)
    return out


def test_particle_values_beside_the_positions(traj, tmp_path):
    p = mrr.write_recording(tmp_path / "v.rrd", traj, color_by="speed", every=3)
    vals = mrr.read_particle_values(p)
    assert sorted(vals) == [0, 3, 6, 7]                      # with the positions, not more often
    v = vals[6]
    assert v.dtype.names == ("speed", "J", "material_id", "particle_id")
    np.testing.assert_allclose(v["speed"], np.linalg.norm(traj.v[6], axis=1), rtol=1e-6)
    np.testing.assert_allclose(v["J"], np.linalg.det(traj.fields["F"][6]), rtol=1e-6)
    np.testing.assert_array_equal(v["particle_id"], np.arange(traj.particle_count))
    np.testing.assert_array_equal(v["material_id"], traj.material_id)
    # rerun's hover card lists a particle's values only for at most 3 per-particle components
    assert _per_particle_components(p, 6, traj.particle_count) == \
        ["Particle:values", "Points2D:colors", "Points2D:positions"]


def test_particle_values_of_fields_on_some_particles(tmp_path):
    t = _traj3d()
    p = mrr.write_recording(tmp_path / "s.rrd", t, color_by="material")
    v = mrr.read_particle_values(p)[2]
    assert v.dtype.names == ("speed", "eps_p", "stress_norm", "material_id", "particle_id")
    assert np.all(np.isnan(v["stress_norm"][:3])) and np.all(np.isnan(v["eps_p"][:3]))   # no sigma there
    np.testing.assert_allclose(v["stress_norm"][3:], np.linalg.norm(t.fields["sigma"][2].reshape(3, -1), axis=1),
                               rtol=1e-6)
    np.testing.assert_array_equal(v["material_id"], t.material_id)
    assert len(_per_particle_components(p, 2, 6)) <= 3


def test_color_variants_let_the_viewer_recolour(traj, tmp_path):
    p = mrr.write_recording(tmp_path / "c.rrd", traj, color_by="material", color_variants=True)
    rows = mrr.read_recording_component(p, "world/particles", "ParticleColors:colors")
    c = rows[4][-1]
    assert c.dtype.names == ("speed", "J", "material", "body")
    np.testing.assert_array_equal(mrr.unpack_colors(c["material"])[:, :3], mrr.PALETTE[traj.material_id])
    speed = np.linalg.norm(traj.v, axis=-1)
    want = mrr.scalar_colors(speed[4], float(speed.min()), float(speed.max()))   # one range over the run
    np.testing.assert_array_equal(mrr.unpack_colors(c["speed"])[:, :3], want)


def test_one_plot_per_quantity_family_with_units(traj, tmp_path):
    m = compute_metrics(traj)
    # as task=simulate writes it: no value at frame 0, none for the chunk 0 -> 1 that compiles
    m["step_time_ms"] = np.r_[np.nan, np.nan, np.full(traj.frame_count - 2, 2.0)]
    p = mrr.write_recording(tmp_path / "b.rrd", traj, metrics=m)
    views = mrr.read_blueprint_views(p)
    plots = {v["name"]: v["contents"] for v in views if v["kind"] == "TimeSeries"}
    assert set(plots) == {"energy [J/m]", "linear momentum [(kg·m/s)/m]", "angular momentum [(kg·m²/s)/m]",
                          "mass [kg/m]", "step time [ms/step]"}
    assert plots["energy [J/m]"] == ["/metrics/kinetic_energy", "/metrics/elastic_energy",
                                     "/derived/gravity_potential_energy_rel", "/derived/total_energy"]
    assert plots["linear momentum [(kg·m/s)/m]"] == ["/metrics/linear_momentum/x", "/metrics/linear_momentum/y"]
    assert plots["mass [kg/m]"] == ["/metrics/mass"]
    (particles,) = [v for v in views if v["name"] == "particles"]
    assert particles["kind"] == "2D" and particles["contents"] == ["/world/**"]
    assert {v["kind"] for v in views} == {"2D", "TimeSeries", "TextDocument"}   # particles, legend, plots, scene
    names = mrr.read_series_names(p)
    plotted = [e.strip("/") for c in plots.values() for e in c]
    assert all("[" in names[e] and names[e].endswith("]") for e in plotted), names
    assert names["metrics/kinetic_energy"] == "kinetic [J/m]"
    assert names["metrics/linear_momentum/y"] == "p_y [(kg·m/s)/m]"
    assert names["metrics/step_time_ms"] == "per step, compile chunk left out [ms]"
    colours = mrr.read_recording_component(p, "metrics/kinetic_energy", "SeriesLines:colors")
    energy_colours = {int(mrr.read_recording_component(p, e, "SeriesLines:colors")[None][-1][0])
                      for e in plots["energy [J/m]"]}
    assert colours and len(energy_colours) == 4                                     # no repeated colours
    # the step time: no NaN at frame 0, no compile spike at frame 1
    frames, values = mrr.read_recording_metrics(p)["step_time_ms"]
    assert list(frames) == list(range(2, traj.frame_count)) and np.all(values == 2.0)
    # the total energy: kinetic + (gravitational - its frame-0 value) + elastic
    from rerun.chunk import RrdReader as R

    tot = [float(row.values.to_numpy()[0]) for ch in R(str(p)).stream().filter(content="/derived/total_energy",
           components="Scalars:scalars") for row in ch.to_record_batch().column("Scalars:scalars")]
    g = m["gravity_potential_energy"]
    np.testing.assert_allclose(tot, m["kinetic_energy"] + g - g[0] + m["elastic_energy"], rtol=1e-9)


def test_3d_units_domain_wireframe_and_up_axis(tmp_path):
    t = _traj3d()
    t.meta["gravity"] = [0.0, 0.0, -9.8]
    p = mrr.write_recording(tmp_path / "d.rrd", t, color_by="stress")
    plots = {v["name"] for v in mrr.read_blueprint_views(p) if v["kind"] == "TimeSeries"}
    assert {"energy [J]", "linear momentum [kg·m/s]", "angular momentum [kg·m²/s]", "mass [kg]"} == plots
    (fill,) = mrr.read_recording_component(p, "world/domain", "Boxes3D:fill_mode")[None]
    assert int(fill[0]) == rr.components.FillMode.MajorWireframe.value     # not the default translucent solid
    colour = mrr.unpack_colors(mrr.read_recording_component(p, "world/domain", "Boxes3D:colors")[None][-1])[0]
    assert colour[0] == colour[1] == colour[2]                              # grey
    xyz = mrr.read_recording_component(p, "world", "ViewCoordinates:xyz")[None][-1]
    np.testing.assert_array_equal(np.reshape(xyz, -1), [3, 5, 1])          # rerun's code of RIGHT_HAND_Z_UP
    eye = mrr.eye_for_box([0, 0, 0], [1, 1, 1], 2)
    assert eye["eye_up"] == [0, 0, 1] and eye["look_target"] == [0.5, 0.5, 0.5]
    assert np.linalg.norm(np.subtract(eye["position"], 0.5)) > 1.5 * np.sqrt(3) / 2   # outside the box
    (legend,) = mrr.read_recording_component(p, "legend/colors", "EncodedImage:blob")[None]
    assert bytes(np.asarray(legend, dtype=np.uint8)[:8]) == b"\x89PNG\r\n\x1a\n" and legend.size < 100_000


def test_2d_is_drawn_y_up_and_framed_on_the_particles(traj, tmp_path):
    p = mrr.write_recording(tmp_path / "f.rrd", traj)
    scale = mrr.read_recording_component(p, "world", "Transform3D:scale")[None][-1]
    np.testing.assert_array_equal(np.reshape(scale, -1), [1.0, -1.0, 1.0])
    # framed on the particles' extent over the run, the room above them (against gravity)
    lo = traj.x.reshape(-1, 2).min(0)
    hi = traj.x.reshape(-1, 2).max(0)
    b_lo, b_hi = mrr.frame_bounds_2d(lo, hi, 0.01, [0, -9.8])
    assert np.all(b_lo < lo) and np.all(b_hi > hi)
    assert lo[1] - b_lo[1] < 0.2 * (hi[1] - lo[1]) + 0.03                 # just under the particles
    flat_lo, flat_hi = mrr.frame_bounds_2d([0.0, 0.0], [2.0, 0.1], 0.005, [0, -9.8])
    assert flat_hi[1] - flat_lo[1] >= 0.5 * (flat_hi[0] - flat_lo[0]) - 1e-12  # not a thin strip
    assert flat_lo[1] > -0.1                                               # the floor stays at the bottom


def test_recording_ids_are_distinct(traj, tmp_path):
    a = mrr.write_recording(tmp_path / "a.rrd", traj, metrics=False)
    b = mrr.write_recording(tmp_path / "b.rrd", traj, metrics=False)
    ids = [RrdReader(str(x)).recordings()[0].recording_id for x in (a, b)]
    assert ids[0] != ids[1]
    u = {mrr.unique_recording_id("replay", "dam_break_2d", "12-00-00") for _ in range(50)}
    assert len(u) == 50 and all(x.startswith("replay-dam_break_2d-12-00-00-") for x in u)


def test_replays_of_one_scene_get_their_own_recording_ids(traj, tmp_path):
    from mpmlab.config import compose
    from mpmlab.io.h5 import write_trajectory
    from mpmlab.tasks import RunContext, get_task

    src = tmp_path / "trajectory.h5"
    write_trajectory(src, traj)
    ids = []
    for k in range(2):
        out = tmp_path / f"replay{k}"
        get_task("replay")(compose(["task=replay", f"input={src}", "output.plots=false"]), RunContext(output_dir=out))
        (entry,) = RrdReader(str(out / "recording.rrd")).recordings()
        ids.append(entry.recording_id)
    assert ids[0] != ids[1] and all(i.startswith("replay-") for i in ids)


def test_epoch_recorder_blueprint_for_a_fit(tmp_path):
    rec = mrr.EpochRecorder(tmp_path / "fit.rrd", "inverse-test", title="inverse fit")
    for e in range(4):
        rec.log(e, 10.0 ** -e, {"alpha": 0.5 * e, "v0": [e, -e]})
    rec.log_rollout(3, np.random.default_rng(0).random((3, 5, 2)), time=[0.0, 0.1, 0.2])
    assert not (tmp_path / "fit.rrd").exists()
    assert rec.close() == tmp_path / "fit.rrd"
    m = mrr.read_recording_metrics(tmp_path / "fit.rrd", timeline="epoch")
    assert set(m) == {"loss", "alpha", "v0/0", "v0/1"}
    np.testing.assert_allclose(m["loss"][1], [1.0, 0.1, 0.01, 0.001])
    views = {v["name"]: v for v in mrr.read_blueprint_views(tmp_path / "fit.rrd")}
    assert {"log₁₀ loss", "loss (linear)", "alpha", "v0", "rollout, epoch 3"} == set(views)
    assert views["v0"]["contents"] == ["/metrics/v0/0", "/metrics/v0/1"]
    assert views["rollout, epoch 3"]["kind"] == "2D"
    pos = mrr.read_recording_positions(tmp_path / "fit.rrd", "rollouts/epoch_00003/particles")
    assert sorted(pos) == [0, 1, 2]


def test_comparison_recording_reduced_beside_full_order(tmp_path):
    t = _traj3d(T=5)
    r = _traj3d(T=5)
    r.x = t.x + 0.01
    r.x[0] = t.x[0]
    p = mrr.write_comparison_recording(tmp_path / "rom.rrd", t, r)
    m = mrr.read_recording_metrics(p)
    np.testing.assert_allclose(m["position_rms_error"][1], [0.0] + [0.01 * np.sqrt(3)] * 4, rtol=1e-6, atol=1e-12)
    assert list(m["relative_error"][0]) == [1, 2, 3, 4]
    views = mrr.read_blueprint_views(p)
    spatial = sorted(v["name"] for v in views if v["kind"] == "3D")
    assert spatial == ["full order", "reduced"]
    assert sum(v["kind"] == "TimeSeries" for v in views) == 2
    np.testing.assert_array_equal(mrr.read_recording_positions(p, "reduced/particles")[2], r.x[2].astype(np.float32))
