"""Run-out measurement (mpmlab.analysis.runout, issue 18 item 2): L_f, the height at the wall and the
deposit profile on synthetic particle sets whose answers are known (a box, a wedge with a known toe, a
lone outlier that must not move L_f, a thin front that must), the stop rule on a synthetic creeping
front, the task.runout options' errors, and one short real run of granular_collapse_2d through the CLI
with summary.json and recording.rrd read back."""
from __future__ import annotations

import json

import numpy as np
import pytest

from mpmlab.analysis.runout import (RunoutGeometry, RunoutMonitor, deposit_mask, deposit_profile, height_at_wall,
                                    measure, runout)
from mpmlab.core.errors import ConfigError

CELL = 0.01
S = CELL / 2                      # particle spacing: 2 x 2 particles per cell
G2 = RunoutGeometry(dim=2, up=1, axis=0, wall=0.0)


def lattice(lo, hi, s=S):
    """Particle centres on a lattice of spacing s filling the box [lo, hi] (cell-centred, like the sampler)."""
    axes = [np.arange(a + s / 2, b - 1e-12, s) for a, b in zip(lo, hi)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, len(lo))


def wedge(H=0.1, toe=0.3, s=S):
    """Particles under the line h(d) = H (1 - d / toe): a deposit whose toe is at d = toe."""
    x = lattice([0, 0], [toe, H], s)
    return x[x[:, 1] + s / 2 <= H * (1 - (x[:, 0] - s / 2) / toe) + 1e-12]


# ---- synthetic deposits ------------------------------------------------------------------------
def test_box_measures_its_own_size():
    x = lattice([0, 0], [0.2, 0.1])
    m = measure(x, G2, CELL, particle_size=S, profile=True)
    assert m["front"] == pytest.approx(0.2, abs=1e-12)          # the extents: exactly L0 and H0
    assert m["height_at_wall"] == pytest.approx(0.1, abs=1e-12)
    assert (m["particles_in_deposit"], m["particles_left_out"]) == (len(x), 0)
    np.testing.assert_allclose(m["profile_distance"], (np.arange(20) + 0.5) * CELL)
    np.testing.assert_allclose(m["profile_height"], 0.1)
    # without the half size: the centres of the outermost particles
    assert runout(x, G2, CELL) == pytest.approx(0.2 - S / 2)
    # the same box against a wall at x = 1 flowing towards -x
    mirrored = x * [-1, 1] + [1.0, 0.0]
    g = RunoutGeometry(dim=2, up=1, axis=0, wall=1.0, direction=-1)
    assert runout(mirrored, g, CELL, S) == pytest.approx(0.2, abs=1e-12)
    assert height_at_wall(mirrored, g, CELL, S) == pytest.approx(0.1, abs=1e-12)


def test_wedge_toe_and_profile():
    H, toe = 0.1, 0.3
    x = wedge(H, toe)
    lf = runout(x, G2, CELL, S)
    assert toe - 2 * S <= lf <= toe                             # the last particles stop short of the line
    assert height_at_wall(x, G2, CELL, S) == pytest.approx(H, abs=S)
    d, h = deposit_profile(x, G2, CELL, S)
    assert d[-1] < lf and len(d) == int(np.ceil(lf / CELL - 1e-9))
    line = H * (1 - (d - CELL / 2) / toe)                          # the line at each bin's wall-side edge
    np.testing.assert_allclose(h, line, atol=S + 1e-12)
    assert np.all(np.diff(h) <= 1e-12)                              # a wedge's profile falls monotonically


@pytest.mark.parametrize("outlier", [[1.5, 0.002], [0.5, 0.2], [0.33, 0.0025]],
                         ids=["far-along-the-floor", "flung-high", "three-cells-past-the-toe"])
def test_a_lone_outlier_does_not_move_the_front(outlier):
    x = wedge()
    ref = measure(x, G2, CELL, S, profile=True)
    xo = np.vstack([x, [outlier]])
    assert xo[:, 0].max() + S / 2 > ref["front"] + 2 * CELL         # the naive "farthest particle" would move
    got = measure(xo, G2, CELL, S, profile=True)
    assert got["front"] == ref["front"]
    assert got["height_at_wall"] == ref["height_at_wall"]
    np.testing.assert_array_equal(got["profile_height"], ref["profile_height"])
    assert (got["particles_in_deposit"], got["particles_left_out"]) == (len(x), 1)
    # a small clump flung far away is left out too
    clump = lattice([0.8, 0.0], [0.82, 0.01])
    assert runout(np.vstack([x, clump]), G2, CELL, S) == ref["front"]


@pytest.mark.parametrize("spacing_cells", [0.5, 0.9])
def test_a_thin_genuine_front_counts(spacing_cells):
    """One particle layer on the floor running 10 cells past the wedge's toe (particles 0.5 or 0.9 cell
    apart): the deposit ends where the layer ends."""
    x = wedge()
    s = spacing_cells * CELL
    along = x[:, 0].max() + np.arange(1, 11 / spacing_cells) * s
    layer = np.stack([along, np.full(len(along), S / 2)], -1)
    xl = np.vstack([x, layer])
    assert layer[-1, 0] - x[:, 0].max() >= 10 * CELL
    assert runout(xl, G2, CELL, S) == pytest.approx(layer[-1, 0] + S / 2)
    assert deposit_mask(xl, CELL).all()


def test_3d_slab_and_radial_cylinder():
    s = 0.005
    g = RunoutGeometry(dim=3, up=2, axis=0, wall=0.0)
    slab = lattice([0, 0, 0], [0.08, 0.04, 0.16], s)
    cell = 2 * s
    assert runout(slab, g, cell, s) == pytest.approx(0.08, abs=1e-12)
    assert height_at_wall(slab, g, cell, s) == pytest.approx(0.16, abs=1e-12)
    far = np.vstack([slab, [[0.7, 0.02, 0.003]]])
    assert runout(far, g, cell, s) == pytest.approx(0.08, abs=1e-12)
    # a cylinder of radius 0.1 about (0.5, 0.5), z up: the radial run-out is its radius
    box = lattice([0.4, 0.4, 0.0], [0.6, 0.6, 0.05], s)
    cyl = box[np.hypot(box[:, 0] - 0.5, box[:, 1] - 0.5) <= 0.1 - s / 2]
    gr = RunoutGeometry(dim=3, up=2, center=(0.5, 0.5))
    assert 0.1 - s <= runout(cyl, gr, cell, s) <= 0.1 + 1e-12
    assert height_at_wall(cyl, gr, cell, s) == pytest.approx(0.05, abs=1e-12)   # at the centre
    d, h = deposit_profile(cyl, gr, cell, s)
    np.testing.assert_allclose(h, 0.05)


@pytest.mark.parametrize("dim", [2, 3])
def test_lookup_table_and_sort_label_alike(dim):
    """Clumps scattered over a large region, some touching: the labelling through a lookup table and the
    one through np.unique (positions too spread for a table) find the same deposit."""
    rng = np.random.default_rng(dim)
    centres = rng.uniform(0, 40 * CELL, (30, dim))
    x = np.concatenate([c + rng.normal(0, 1.5 * CELL, (rng.integers(1, 60), dim)) for c in centres])
    x = np.vstack([x, np.full((1, dim), 1e4)])            # one particle 10 km away
    dense, sort = deposit_mask(x, CELL), deposit_mask(x, CELL, dense_limit=0)
    np.testing.assert_array_equal(dense, sort)
    assert 0 < dense.sum() < len(x) - 1 and not dense[-1]


def test_non_finite_particles_and_bad_input():
    x = lattice([0, 0], [0.2, 0.1])
    xn = np.vstack([x, [[np.nan, 0.0]], [[np.inf, 0.01]]])
    assert runout(xn, G2, CELL, S) == pytest.approx(0.2, abs=1e-12)
    assert not deposit_mask(xn, CELL)[-2:].any()
    with pytest.raises(ConfigError, match="cell size"):
        deposit_mask(x, 0.0)
    with pytest.raises(ConfigError, match="up axis"):
        RunoutGeometry(dim=2, up=0, axis=0)
    with pytest.raises(ConfigError, match="positions must be"):
        runout(x, RunoutGeometry(dim=3, up=2, axis=0), CELL)


# ---- the stop rule -------------------------------------------------------------------------
def creeping(monitor, times, front_shift, ke):
    """Feed the monitor a box stretched along the floor so that its front moves out by front_shift(t)."""
    base = lattice([0, 0], [0.2, 0.1])
    fired = []
    for t in times:
        x = base * [1.0 + front_shift(t) / (0.2 - S / 2), 1.0]   # the last centre moves by front_shift
        fired.append(monitor.update(t, x, kinetic_energy=ke(t)))
    return np.array(fired)


def test_monitor_does_not_stop_a_creeping_front_and_stops_a_halted_one():
    m = RunoutMonitor(G2, CELL, particle_size=S)           # 0.1 cell over 0.1 s, KE < 1e-3 of its peak
    dt = 0.01
    t = np.arange(0.0, 2.0, dt)
    # KE: a peak at t = 0.05 s, then 1e-6 of it; the front creeps 0.2 cell per 0.1 s until t = 1 s, then halts
    ke = lambda tt: 1.0 if tt < 0.1 else 1e-6
    shift = lambda tt: 0.2 * CELL * min(tt, 1.0) / 0.1
    fired = creeping(m, t, shift, ke)
    assert not fired[t < 1.0].any()                        # never while it creeps, whatever the energy
    # settled once the last 0.1 s holds less than 0.1 cell of creep: between 0.05 and 0.1 s after the halt
    assert m.settled and 1.0 + 0.05 - 1e-9 <= m.settled_time <= 1.0 + 0.1 + dt + 1e-9
    assert fired[np.searchsorted(t, m.settled_time):].all()
    front_cells, height_cells = m.moved_cells()
    assert front_cells < 0.1 and height_cells < 0.1
    assert m.fronts[-1] == pytest.approx(0.2 + 2.0 * CELL, abs=1e-9)   # crept 10 x 0.2 cell


def test_monitor_waits_for_the_energy_and_for_a_full_window():
    m = RunoutMonitor(G2, CELL, particle_size=S, ke_fraction=1e-3)
    t = np.arange(0.0, 1.0, 0.01)
    fired = creeping(m, t, lambda tt: 0.0, lambda tt: 1.0 if tt < 0.5 else 0.01)   # still, KE only 1e-2 of peak
    assert not fired.any() and not m.settled
    m2 = RunoutMonitor(G2, CELL, particle_size=S)
    fired = creeping(m2, t, lambda tt: 0.0, lambda tt: 0.0)   # never moved: settled once a window is covered
    assert not fired[t < 0.1 - 1e-9].any() and m2.settled_time == pytest.approx(0.1)
    # a front oscillating by 0.3 cell is not still, though it comes back
    m3 = RunoutMonitor(G2, CELL, particle_size=S)
    fired = creeping(m3, t, lambda tt: 0.3 * CELL * (int(round(tt / 0.01)) % 2), lambda tt: 0.0)
    assert not fired.any()
    with pytest.raises(ConfigError, match="window_s"):
        RunoutMonitor(G2, CELL, window_s=0.0)


# ---- task.runout options ---------------------------------------------------------------------
@pytest.mark.parametrize("overrides, match", [
    (["task.runout.axis=w"], "task.runout.axis = 'w' is not an axis"),
    (["task.runout.axis=y"], "the flow axis and the up axis are both 'y'"),
    (["task.runout.center=[0.1]"], None),
    (["task.runout.center=[0.1,0.1]", "task.runout.axis=x"], "either a flow axis"),
    (["task.runout.center=[0.1,0.1,0.1]"], "needs 2 coordinates"),
    (["task.runout.enabled=false", "task.runout.stop_when_settled=true"], "needs the run-out analysis"),
    (["task.runout.L0=-1"], "task.runout.L0 = -1.0 must be positive"),
    (["task.runout.window_s=0"], "task.runout.window_s = 0.0 must be a positive number"),
    (["task.runout.ke_fraction=2"], "task.runout.ke_fraction = 2.0 must be in"),
    (["task.runout.up=q"], "task.runout.up = 'q' is not an axis"),
    (["scene=dam_break_2d", "scene.resolution=tiny", "task.runout.enabled=true"], "declares no run-out geometry"),
])
def test_bad_options_are_one_line_errors(overrides, match):
    from mpmlab.config import build_scene, compose
    from mpmlab.tasks.simulate import runout_plan

    cfg = compose(["scene=granular_collapse_2d", "scene.resolution=tiny", *overrides])
    if match is None:   # a centre with one coordinate in 2D: the horizontal one, a radial geometry
        assert runout_plan(cfg, build_scene(cfg)).monitor.geometry.center == (0.1, 0.0)
        return
    with pytest.raises(ConfigError, match=match) as e:
        runout_plan(cfg, build_scene(cfg))
    assert "\n" not in str(e.value)


def test_plan_defaults_and_off_switch():
    from mpmlab.config import build_scene, compose
    from mpmlab.tasks.simulate import runout_plan

    cfg = compose(["scene=granular_collapse_2d", "scene.resolution=tiny"])
    plan = runout_plan(cfg, build_scene(cfg))            # on by default: the scene declares its geometry
    g = plan.monitor.geometry
    assert (g.axis, g.up, g.wall, g.base, plan.L0, plan.H0) == (0, 1, 0.0, 0.0, 0.2, 0.1)
    assert plan.monitor.cell == pytest.approx(0.01) and not plan.stop_when_settled
    off = compose(["scene=granular_collapse_2d", "scene.resolution=tiny", "task.runout.enabled=false"])
    assert runout_plan(off, build_scene(off)) is None
    dam = compose(["scene=dam_break_2d", "scene.resolution=tiny"])
    assert runout_plan(dam, build_scene(dam)) is None     # a scene without scene.vars.runout: off
    col = compose(["scene=granular_column_3d", "scene.resolution=tiny", "scene.vars.aspect_ratio=3"])
    plan = runout_plan(col, build_scene(col))
    g = plan.monitor.geometry
    assert (g.axis, g.up, g.wall, plan.L0, plan.H0) == (0, 2, 0.0, 0.08, pytest.approx(0.24))
    cyl = compose(["scene=granular_cylinder_3d", "scene.resolution=tiny"])
    plan = runout_plan(cyl, build_scene(cyl))
    g = plan.monitor.geometry
    assert (g.radial, g.center, g.up, plan.L0, plan.H0) == (True, (0.5, 0.5, 0.0), 2, 0.1, 0.17)
    on = compose(["scene=dam_break_2d", "scene.resolution=tiny", "task.runout.enabled=true", "task.runout.axis=x"])
    g = runout_plan(on, build_scene(on)).monitor.geometry  # up against gravity, wall and floor at the domain's lo
    assert (g.axis, g.up, g.wall, g.base) == (0, 1, 0.0, 0.0)


# ---- a real run through the CLI ---------------------------------------------------------------
def test_granular_collapse_run_records_the_runout(tmp_path):
    """granular_collapse_2d at its tiny resolution (200 particles, JAX) for up to 1 s, stopping when the
    deposit settles: summary.json has the run-out, the trajectory is complete up to the stop, the
    recording has the front and wall-height series and the final profile."""
    import h5py

    from mpmlab.cli import main
    from mpmlab.io.h5 import read_trajectory
    from mpmlab.io.rerun import read_blueprint_views, read_recording_metrics
    from rerun.chunk import RrdReader

    run = tmp_path / "run"
    rc = main(["scene=granular_collapse_2d", "scene.resolution=tiny", "backend=jax", "steps=10000",
               "frame_every=100", "task.runout.stop_when_settled=true", f"hydra.run.dir={run}"])
    assert rc == 0
    s = json.loads((run / "summary.json").read_text())
    r = s["runout"]
    assert s["status"] == "ok" and r["settled"] and r["stopped_early"]
    assert s["steps_done"] < 10000 and s["stopped_when_settled"]["step"] == s["steps_done"]
    assert r["settled_time"] == pytest.approx(s["last_frame"]["time"]) == pytest.approx(r["time"])
    assert r["L0"] == 0.2 and r["d_n"] == pytest.approx((r["L_f"] - 0.2) / 0.2)
    assert r["L_initial"] == pytest.approx(0.2, abs=1e-6)                 # the box column measures L0
    assert 0.2 < r["L_f"] < 0.6 and 0.0 < r["H_wall"] <= 0.1 + 1e-6
    assert r["front_moved_last_window_cells"] < 0.1 and r["particles_in_deposit"] + r["particles_left_out"] == 200
    prof = r["profile"]
    assert len(prof["distance"]) == len(prof["height"]) and prof["bin"] == pytest.approx(0.01)
    assert prof["distance"][-1] - 0.005 < r["L_f"] <= prof["distance"][-1] + 0.005 + 1e-9   # the bins end at L_f
    assert max(prof["height"]) == pytest.approx(r["H_wall"], abs=0.01)
    assert {"runout_plot", "recording", "trajectory"} <= set(s["outputs"]) and (run / "runout.png").is_file()

    # the trajectory: complete, the steps actually run, the final frame the one measured
    with h5py.File(run / "trajectory.h5") as f:
        assert bool(f.attrs["complete"]) and int(f.attrs["steps"]) == s["steps_done"]
        assert int(f.attrs["steps_planned"]) == 10000 and bool(f.attrs["stopped_when_settled"])
    traj = read_trajectory(run / "trajectory.h5", require_complete=True)
    assert traj.frame_count == s["frames"] and int(traj.step[-1]) == s["steps_done"]
    size = np.sqrt(traj.volume)
    assert runout(traj.x[-1], G2, 0.01, size) == pytest.approx(r["L_f"], rel=1e-6)

    # the recording: both series on every frame, the last values those of the summary, the profile line
    m = read_recording_metrics(run / "recording.rrd")
    frames, front = m["runout_front"]
    assert list(frames) == list(range(s["frames"])) and len(m["runout_height_at_wall"][1]) == s["frames"]
    assert front[0] == pytest.approx(0.2, abs=1e-6) and front[-1] == pytest.approx(r["L_f"], rel=1e-6)
    views = {v["name"]: v for v in read_blueprint_views(run / "recording.rrd")}
    assert views["run-out [m]"]["contents"] == ["/metrics/runout_front", "/metrics/runout_height_at_wall"]
    logged = []
    for ch in RrdReader(str(run / "recording.rrd")).stream().filter(content="/world/deposit_profile",
                                                                    components="LineStrips2D:strips"):
        rb = ch.to_record_batch()
        logged += [(int(f), np.array(strip.as_py()[0])) for f, strip in
                   zip(rb.column("frame").to_numpy(), rb.column("LineStrips2D:strips")) if strip.is_valid]
    (frame, pts), = logged
    assert frame == s["frames"] - 1 and pts.shape == (len(prof["distance"]) + 3, 2)
    assert pts[:, 0].max() == pytest.approx(r["L_f"], rel=1e-6)
    assert pts[:, 1].max() == pytest.approx(max(prof["height"]), rel=1e-6)


def test_settled_stop_without_a_trajectory_keeps_the_recordings_frames(tmp_path):
    """output.trajectory=false: the rollout's own frames are lost with the stop, so the task keeps them for
    the recording; every frame up to the stop is in it, the last one the deposit measured."""
    from mpmlab.cli import main
    from mpmlab.io.rerun import read_recording_metrics, read_recording_positions

    run = tmp_path / "run"
    rc = main(["scene=granular_collapse_2d", "scene.resolution=tiny", "backend=jax", "steps=10000",
               "frame_every=100", "output.trajectory=false", "task.runout.stop_when_settled=true",
               f"hydra.run.dir={run}"])
    assert rc == 0
    s = json.loads((run / "summary.json").read_text())
    assert s["runout"]["stopped_early"] and s["steps_done"] < 10000 and "trajectory" not in s["outputs"]
    pos = read_recording_positions(run / "recording.rrd")
    assert sorted(pos) == list(range(s["frames"]))
    size = np.full(len(pos[0]), 0.01)                       # tiny: one particle per 1 cm cell
    assert runout(pos[s["frames"] - 1].astype(np.float64), G2, 0.01, size) == pytest.approx(s["runout"]["L_f"], rel=1e-6)
    assert read_recording_metrics(run / "recording.rrd")["runout_front"][1][-1] == pytest.approx(s["runout"]["L_f"])
