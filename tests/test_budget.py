"""Size pre-flight (issue #12 item 5): particle, memory and output estimates, refusals and warnings.

Everything here runs on estimates except the comparisons with real sampling (tiny/cpu library scenes)
and with a real trajectory file; the refusal of ``scene.dx=1e-5`` must come within a second and
without allocating anything proportional to the requested sizes.
"""
from __future__ import annotations

import json
import logging
import os
import re
import subprocess
import sys
import tracemalloc

import pytest

from mpmlab.config import build_scene, compose
from mpmlab.core import budget
from mpmlab.core.budget import GiB, KiB, MiB, TiB
from mpmlab.core.errors import ConfigError
from mpmlab.core.scene import Body, Scene


#: nclaw_jelly's cube sampled one particle per cell (its own NCLaw lattice does not depend on dx): the
#: tests that refine dx to stress the budget need the count to follow dx
CELL = ("scene.bodies.cube.sampling=regular", "scene.bodies.cube.lattice=null")


def _scene(*overrides):
    """A scene from the packaged config, particles not sampled."""
    scene = build_scene(compose(list(overrides)), validate=False)
    assert "_particles" not in vars(scene)
    return scene


# ---- particles ---------------------------------------------------------------------------------
@pytest.mark.parametrize("overrides", [
    ["scene=dam_break_2d", "scene.resolution=tiny"],              # 2D box, 1 per cell
    ["scene=dam_break_2d", "scene.resolution=cpu"],               # 2D box, 4 per cell
    ["scene=granular_collapse_2d", "scene.resolution=tiny"],
    ["scene=jelly_pool_drop", "scene.resolution=tiny"],           # 3D box + ball, two laws
    ["scene=jelly_pool_drop", "scene.resolution=cpu"],
    ["scene=granular_cylinder_3d", "scene.resolution=tiny"],      # cylinder, z axis
    ["scene=granular_cylinder_3d", "scene.resolution=cpu"],
    ["scene=cylinder_wall_gravity"],                               # cylinder, x axis, 8 per cell
    ["scene=nclaw_jelly"],
    ["scene=nclaw_jelly", *CELL],                                  # 1 per cell
    ["scene=nclaw_jelly", *CELL, "scene.bodies.cube.shape.lo=[0.2501,0.2533,0.31]", "scene.dx=0.0371"],  # off-lattice
], ids=lambda o: "-".join(a.split("=", 1)[1] for a in o))
def test_particle_estimate_matches_sampling(overrides):
    scene = _scene(*overrides)
    est = budget.estimate_particles(scene)
    assert "_particles" not in vars(scene), "the estimate must not sample"
    real = scene.particles().count
    assert est == pytest.approx(real, rel=0.01), (est, real)   # regular lattices are counted exactly
    assert budget.estimate_particles(scene) == real             # a sampled scene reports its real count


def _disc_scene(sampling="regular", ppc=4, dx=0.02):
    body = Body(shape={"kind": "sphere", "center": [0.5, 0.43], "radius": 0.2}, material="fixed_corotated",
                particles_per_cell=ppc, sampling=sampling, name="disc")
    return Scene(dim=2, dx=dx, domain=([0.0, 0.0], [1.0, 1.0]), bodies=[body], name="disc")


def test_particle_estimate_disc_2d():
    scene = _disc_scene()
    assert budget.estimate_particles(scene) == scene.particles().count


@pytest.mark.parametrize("overrides", [
    ["scene=jelly_pool_drop", "scene.resolution=cpu", "scene.bodies.ball.sampling=jittered",
     "scene.bodies.pool.sampling=jittered"],
    ["scene=granular_cylinder_3d", "scene.resolution=cpu", "scene.bodies.cylinder.sampling=jittered"],
    ["scene=dam_break_2d", "scene.resolution=cpu", "scene.bodies.water.sampling=jittered"],
], ids=["ball+box", "cylinder", "box2d"])
def test_particle_estimate_jittered(overrides):
    scene = _scene(*overrides)
    est = budget.estimate_particles(scene)
    assert est == pytest.approx(scene.particles().count, rel=0.1)


def test_sampling_peak_is_the_lattice():
    """nclaw_jelly at dx = 1e-5: 50000^3 lattice points; the sampler's meshgrid alone is 910 TiB."""
    scene = _scene(*CELL, "scene.dx=1e-5")
    (body,) = budget.estimate_bodies(scene)
    assert 50_000**3 <= body.lattice <= 50_001**3    # floor/ceil of the bounds may add a layer
    assert body.particles == 50_000**3
    assert body.peak >= 3 * 50_000**3 * 8          # D meshgrid arrays of float64 (910 TiB) and more
    assert budget.estimate_sampling_peak(scene) >= body.peak


# ---- memory ------------------------------------------------------------------------------------
def test_memory_refuses_dx_1e5_without_sampling_or_allocating():
    """Refused from the counts alone: the particles are never sampled and the Python heap's peak stays
    small (no wall-clock bound: a timed assertion fails on a loaded machine, and these two are what make
    the refusal immediate)."""
    scene = _scene(*CELL, "scene.dx=1e-5")         # build_scene(validate=False) does not sample
    available = int(21.3 * GiB)
    tracemalloc.start()
    with pytest.raises(ConfigError) as err:
        budget.check_memory(scene, "jax", "fp32", "mls", available=available)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    msg = str(err.value)
    assert peak < 20 * MiB, peak
    assert "_particles" not in vars(scene)
    assert "\n" not in msg
    assert msg.startswith("scene 'nclaw_jelly': dx = 1e-05 m needs about ")
    assert "PiB of memory (a 100000^3-cell grid, ~1.25e+14 particles) but 21.3 GiB are available" in msg
    assert "(memory scales as dx^-3) or choose a coarser scene.resolution." in msg
    # the suggested dx fits (below the warning threshold, even)
    dx_fit = float(re.search(r"set scene\.dx >= ([0-9.e+-]+) ", msg).group(1))
    assert 1e-3 < dx_fit < 1e-2
    fit = _scene(*CELL, f"scene.dx={dx_fit}")
    assert budget.estimate_memory(fit, "jax", "fp32", "mls")["total"] <= 0.5 * available
    budget.check_memory(fit, "jax", "fp32", "mls", available=available)   # no error


def test_memory_refusal_on_a_directly_built_scene():
    """A Scene constructed directly (no config) is refused as well; Warp and fp64 too."""
    body = Body(shape={"kind": "box", "lo": [0.25] * 3, "hi": [0.75] * 3}, material="fixed_corotated")
    scene = Scene(dim=3, dx=1e-5, domain=([0.0] * 3, [1.0] * 3), bodies=[body], name="direct")
    for backend, precision in (("warp", "fp32"), ("jax", "fp64")):
        with pytest.raises(ConfigError, match=r"^scene 'direct': dx = 1e-05 m needs about .* set scene\.dx >= "):
            budget.check_memory(scene, backend, precision, "apic", available=16 * GiB)
    assert "_particles" not in vars(scene)            # refused from the counts: nothing was sampled


def test_memory_estimate_parts_scale_with_dx():
    a = budget.estimate_memory(_scene(*CELL, "scene.dx=0.02", "scene.dt=1e-4"), "jax", "fp32", "mls")
    b = budget.estimate_memory(_scene(*CELL, "scene.dx=0.01", "scene.dt=1e-4"), "jax", "fp32", "mls")
    for part in ("particles", "grid", "scratch"):
        assert 6 < b[part] / a[part] < 10          # dx^-3
    assert a["total"] == max(a["sampling"], a["particles"] + a["grid"] + a["scratch"]) + a["runtime"]
    w = budget.estimate_memory(_scene(*CELL, "scene.dx=0.01", "scene.dt=1e-4"), "warp", "fp32", "mls", threads=4)
    w1 = budget.estimate_memory(_scene(*CELL, "scene.dx=0.01", "scene.dt=1e-4"), "warp", "fp32", "mls", threads=1)
    assert w["grid"] > 2 * w1["grid"]              # one private P2G grid per CPU thread
    gpu = budget.estimate_memory(_scene(*CELL, "scene.dx=0.01"), "warp", "fp32", "mls", device="cuda:0")
    assert gpu["grid"] == 0                        # on the device, not in host memory


def test_memory_warning_one_line(caplog):
    scene = _scene(*CELL, "scene.dx=0.01", "scene.dt=1e-4")
    need = budget.estimate_memory(scene, "jax", "fp32", "mls")["total"]
    with caplog.at_level(logging.WARNING, logger="mpmlab"):
        est = budget.check_memory(scene, "jax", "fp32", "mls", available=int(need / 0.7))
    assert est["total"] == need
    warnings = [r for r in caplog.records if r.name == "mpmlab" and r.levelno == logging.WARNING]
    assert len(warnings) == 1
    line = warnings[0].getMessage()
    assert "\n" not in line and "70 %" in line and "scene.dx" in line
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="mpmlab"):
        budget.check_memory(scene, "jax", "fp32", "mls", available=10 * need)
    assert not [r for r in caplog.records if r.name == "mpmlab"]


def test_memory_frames_kept_suggest_frame_every():
    """A rollout that keeps 10^6 frames in memory is refused with a frame_every that fits."""
    scene = _scene()                                               # nclaw_jelly: 1000 particles
    steps, avail = 1_000_000, 21 * GiB
    T, _ = budget.frame_counts(steps, 1)
    with pytest.raises(ConfigError) as err:
        budget.check_memory(scene, "jax", "fp32", "mls", available=avail, frames=T, fields=("F", "C"),
                            steps=steps, frame_every=1)
    msg = str(err.value)
    assert msg.startswith("scene 'nclaw_jelly': keeping 1000001 frames of ~1000 particles in memory needs about ")
    fe = int(re.search(r"raise frame_every \(>= (\d+) fits\)", msg).group(1))
    T_fit, _ = budget.frame_counts(steps, fe)
    est = budget.estimate_memory(scene, "jax", "fp32", "mls", frames=T_fit, fields=("F", "C"))
    assert est["total"] <= avail
    T_less, _ = budget.frame_counts(steps, max(1, fe // 2))
    assert budget.estimate_memory(scene, "jax", "fp32", "mls", frames=T_less, fields=("F", "C"))["total"] > 0.5 * avail


def test_phase_change_body_is_counted_with_its_law_instance_before_sampling():
    """The budget reads each body's law instance (``Scene._law``), not the registered class: the
    ``phase_change`` class declares only switch_time and the clock, its configured pair both laws'
    parameters and state (F). Unsampled, the estimate counts what sampling then holds."""
    scene = _scene("scene=nclaw_melting", "scene.resolution=tiny", "precision=fp64")
    law = scene._law(0)
    assert type(law).__name__ == "Law_hencky_von_mises_to_hencky_drucker_prager"
    assert budget._params_per_particle(scene) == len(law.param_names()) == 7
    assert budget._laws(scene) == [(law, budget.estimate_particles(scene))]
    assert budget.carried_fields(scene, "mls") == {"C", "F", "clock", "eps_zz"}   # eps_zz: plane strain (declared, 0 in 3D)
    before = budget.estimate_memory(scene, "jax", "fp64", "mls")
    per_particle = budget._scene_particle_bytes(scene, 1)
    assert "_particles" not in vars(scene)
    P = scene.particles()
    assert P.groups[0].law is law and P.groups[0].params.shape[1] == 7
    after = budget.estimate_memory(scene, "jax", "fp64", "mls")
    assert before["particles"] == after["particles"] and per_particle == budget._scene_particle_bytes(scene, 1)


def test_available_memory_is_positive():
    assert 0 < budget.available_memory() < 1 << 60


# ---- outputs -----------------------------------------------------------------------------------
@pytest.mark.parametrize("steps, every, record_every, expected", [
    (1_000_000, 1, 1, (1_000_001, 1_000_001)),
    (10, 3, 1, (5, 5)),            # 0, 3, 6, 9 and the last step, 10
    (5, 10, 1, (2, 2)),            # frame_every > steps: frames 0 and 5
    (0, 10, 1, (1, 1)),
    (8, 2, 2, (5, 3)),             # recording: frames 0, 2, 4
    (10, 2, 2, (6, 4)),            # 0, 2, 4 and the last, 5
])
def test_frame_counts(steps, every, record_every, expected):
    assert budget.frame_counts(steps, every, record_every) == expected


def test_output_estimate_layout():
    sizes = budget.estimate_outputs(1000, 3, "fp32", 1_000_001, ("F", "C"))
    per_frame = 1000 * (3 + 3 + 9 + 9) * 4                        # 96 kB: x, v, F, C in fp32
    assert sizes["trajectory.h5"] == pytest.approx(1_000_001 * per_frame, rel=0.01)
    # recording: positions (3 f32) and the hover values speed, J (from F), material and particle id (4 f32)
    assert sizes["recording.rrd"] == pytest.approx(1_000_001 * 1000 * (3 + 4) * 4, rel=0.15)
    fp64 = budget.estimate_outputs(1000, 3, "fp64", 11, ("F",), recording=False)
    assert set(fp64) == {"trajectory.h5"}
    coloured = budget.estimate_outputs(1000, 2, "fp32", 11, (), 11, color_scalar=True)["recording.rrd"]
    plain = budget.estimate_outputs(1000, 2, "fp32", 11, (), 11)["recording.rrd"]
    assert coloured - plain == 11 * 1000 * 4                        # packed RGBA per particle and frame


def test_outputs_refused_with_injected_free(tmp_path):
    steps = 1_000_000
    T, R = budget.frame_counts(steps, 1)
    sizes = budget.estimate_outputs(1000, 3, "fp32", T, ("F", "C"), R, recording=False)
    run_dir = tmp_path / "outputs" / "run"                          # not created yet
    free = 50 * GiB
    with pytest.raises(ConfigError) as err:
        budget.check_outputs_fit(run_dir, sizes, free=free, steps=steps, frame_every=1)
    msg = str(err.value)
    assert "\n" not in msg
    assert msg.startswith("trajectory.h5 would need about 89.")     # 96.4e9 bytes
    assert "GiB (1000001 frames x 94.1 KiB) but '" in msg and "' has 50 GiB free; raise frame_every (>= " in msg
    assert msg.endswith("fits) or set output.trajectory=false.")
    fe = int(re.search(r"raise frame_every \(>= (\d+) fits\)", msg).group(1))
    T_fit, _ = budget.frame_counts(steps, fe)
    fit = budget.estimate_outputs(1000, 3, "fp32", T_fit, ("F", "C"), recording=False)
    assert fit["trajectory.h5"] <= free
    budget.check_outputs_fit(run_dir, fit, free=free)               # no error
    # both files: the message names both and their frames
    sizes = budget.estimate_outputs(1000, 3, "fp32", T, ("F", "C"), R)
    with pytest.raises(ConfigError, match=r"^trajectory\.h5 \+ recording\.rrd would need about .*"
                                          r"recording\.rrd: 1000001 frames x "):
        budget.check_outputs_fit(run_dir, sizes, free=free, steps=steps, frame_every=1)


def test_outputs_refused_without_frame_info(tmp_path):
    with pytest.raises(ConfigError, match=r"^recording\.rrd would need about 2 GiB \(2 GiB\) but .* free; "
                                          r"set output\.recording=false or choose another hydra\.run\.dir\.$"):
        budget.check_outputs_fit(tmp_path, {"recording.rrd": 2 * GiB}, free=1 * GiB)


def test_outputs_warning(tmp_path, caplog):
    with caplog.at_level(logging.WARNING, logger="mpmlab"):
        total = budget.check_outputs_fit(tmp_path, {"trajectory.h5": 12 * GiB}, free=100 * TiB, frames=1001)
    assert total == 12 * GiB
    (rec,) = [r for r in caplog.records if r.name == "mpmlab"]
    assert "trajectory.h5 would need about 12 GiB (1001 frames x 12.3 MiB)" in rec.getMessage()
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="mpmlab"):
        budget.check_outputs_fit(tmp_path, {"trajectory.h5": 3 * GiB}, free=5 * GiB)   # > 50 % of free
        budget.check_outputs_fit(tmp_path, {"trajectory.h5": 3 * GiB}, free=50 * GiB)  # fine
    assert len([r for r in caplog.records if r.name == "mpmlab"]) == 1


def test_free_disk_nearest_existing_parent(tmp_path):
    free, where = budget.free_disk(tmp_path / "a" / "b" / "c")
    assert where == tmp_path and free > 0


def test_trajectory_estimate_against_a_written_file(tmp_path):
    """The uncompressed trajectory.h5 estimate is an upper bound within 20 % of a real file."""
    import mpmlab
    from mpmlab.io import write_recording, write_trajectory

    scene = build_scene(compose(["scene=nclaw_jelly"]))
    fields = ("F", "C")
    steps, every = 20, 1
    traj = mpmlab.simulate(scene, steps=steps, every=every, backend="jax", transfer="mls", precision="fp32",
                           fields=fields)
    T, R = budget.frame_counts(steps, every)
    assert traj.frame_count == T
    h5 = write_trajectory(tmp_path / "trajectory.h5", traj, compression=None)
    rrd = write_recording(tmp_path / "recording.rrd", traj, color_by="J")
    est = budget.estimate_outputs(scene.particles().count, 3, "fp32", T, fields, R,
                                  field_particles=budget.field_particles(scene, fields, "mls"),
                                  params_per_particle=traj.params.shape[1], color_scalar=True)
    real = os.path.getsize(h5)
    assert real <= est["trajectory.h5"] <= 1.2 * real, (est, real)
    real_rrd = os.path.getsize(rrd)
    assert real_rrd <= est["recording.rrd"] <= 3 * real_rrd, (est, real_rrd)


def test_output_preflight_from_config(tmp_path, caplog):
    cfg = compose(["steps=1000000", "frame_every=1"])
    scene = _scene("steps=1000000", "frame_every=1")
    with pytest.raises(ConfigError, match=r"^trajectory\.h5 \+ recording\.rrd would need about"):
        budget.output_preflight(cfg, scene, tmp_path / "run", free=50 * GiB)
    # a recording without a trajectory keeps the frames in memory: refused by memory first
    cfg = compose(["steps=1000000", "frame_every=1", "output.trajectory=false"])
    with pytest.raises(ConfigError, match=r"keeping 1000001 frames of ~1000 particles in memory.*raise frame_every \(>= \d+ fits\)"):
        budget.output_preflight(cfg, scene, tmp_path / "run", free=100 * TiB, available=8 * GiB)
    sizes = budget.output_preflight(compose([]), scene, tmp_path / "run", free=100 * GiB)
    assert set(sizes) == {"trajectory.h5", "recording.rrd"}
    est = budget.memory_preflight(compose([]), scene, available=100 * GiB)
    assert est["total"] < 1 * GiB
    assert "_particles" not in vars(scene)


# ---- formatting --------------------------------------------------------------------------------
@pytest.mark.parametrize("n, text", [(512, "512 B"), (96 * KiB, "96 KiB"), (int(21.3 * GiB), "21.3 GiB"),
                                     (910 * TiB, "910 TiB"), (1010 * KiB, "0.99 MiB"), (1.25 * 1024**5, "1.25 PiB")])
def test_human_bytes(n, text):
    assert budget.human_bytes(n) == text
