"""The deformation-map ROM's full-order snapshot studies (issue 16 item 1; paper Sec. 5, Tab. 2):
the scenes at `tiny` on both backends, their CFL-bounded dt and snapshot spacing, the studies' runs and
seeded splits, the generated experiments, the torsion end's rigid motion, a two-run study through
run_study and load_snapshots, and the reader's one-line refusals.

Both backends run each scene for 4 steps at `tiny` (25-208 particles; ~3 s each, Warp's kernels are
cached); the longer rollouts (rigid motion, the two-run study) run on Warp only, where a rollout of
tiny scenes costs a fraction of JAX's per-run compilation (both backends' rigid motion is checked
against the closed form in tests/test_boundaries.py::test_prescribed_rigid_motion).
"""
from __future__ import annotations

import dataclasses
import itertools
import math
import shutil

import numpy as np
import pytest
from omegaconf import OmegaConf

import mpmlab
from mpmlab.config import build_scene, compose
from mpmlab.core.errors import ConfigError
from mpmlab.rom import snapshots as S

SCENES = ("rom_torsion", "rom_poke", "rom_tower")


def one_line(exc_info) -> str:
    msg = str(exc_info.value)
    assert "\n" not in msg and msg, msg
    return msg


# ---------------------------------------------------------------------------------------------------
# scenes
# ---------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("backend", ["jax", "warp"])
@pytest.mark.parametrize("name", SCENES)
def test_scene_runs_tiny(name, backend):
    cfg = compose([f"scene={name}", "scene.resolution=tiny"])
    scene = build_scene(cfg)
    traj = mpmlab.simulate(scene, 4, 2, backend, "mls", "fp32", fields=("F",))
    assert traj.x.shape[0] == 3 and np.all(np.isfinite(traj.x)) and np.all(np.isfinite(traj.fields["F"]))
    assert cfg.material.law == "fixed_corotated" and cfg.material.density == 1000.0


@pytest.mark.parametrize("name,speed", [("poke_continual", 0.048), ("poke_slow_continual", 0.0048)])
def test_continual_poke_composes_at_tiny(name, speed):
    cfg = compose([f"experiment=rom_snapshots_{name}", "scene.resolution=tiny"])
    scene = build_scene(cfg)
    pokes = [b for b in scene.boundaries if b.name == "grid_velocity" and np.isfinite(b.t_end)]
    assert len(pokes) == 10
    assert all(np.linalg.norm(b.velocity) == pytest.approx(speed) for b in pokes)
    assert [b.t_start for b in pokes] == [3.0 * i for i in range(10)]
    dt = float(cfg.scene.dt)
    assert all(abs(b.t_end - b.t_start - 0.25 + 0.5 * dt) < 1e-12 for b in pokes)    # step start times
    assert all(len(b.select(scene.particles().x)) >= 1 for b in pokes)
    assert cfg.steps == 4320 * cfg.frame_every
    assert compose([f"experiment=rom_snapshots_{name}"]).steps == 4320 * 25


# (scene, resolution, snapshot interval [s], snapshots, max boundary speed [m/s])
TIMING = [("rom_torsion", "tiny", 1 / 1500, None, 0.6 + 2 * 0.005 * math.sqrt(2)),
          ("rom_torsion", "paper", 1 / 1500, 30, 0.6 + 2 * 0.005 * math.sqrt(2)),
          ("rom_torsion", "fine", 1 / 1500, 30, 0.6 + 2 * 0.005 * math.sqrt(2)),
          ("rom_poke", "tiny", 1 / 144, None, 0.048), ("rom_poke", "paper", 1 / 144, 432, 0.048),
          ("rom_tower", "tiny", 1 / 24, None, 0.08), ("rom_tower", "cpu", 1 / 24, 80, 0.08),
          ("rom_tower", "paper", 1 / 24, 80, 0.08)]


@pytest.mark.parametrize("name,res,interval,snapshots,vmax", TIMING)
def test_dt_is_cfl_bounded_and_frames_are_the_snapshots(name, res, interval, snapshots, vmax):
    """dt = interval / n with the smallest n keeping dt (c_p + v_max) / dx <= 0.3, frame_every = n, and
    steps = snapshots x n: the kept frames are the paper's snapshots (Tab. 2, Sec. 5.3: 1/144 s)."""
    cfg = compose([f"scene={name}", f"scene.resolution={res}"])
    m = cfg.material
    c = S.p_wave_speed(m.params.E, m.params.nu, m.density)
    n = S.substeps(interval, cfg.scene.dx, c, vmax)
    assert cfg.frame_every == n
    assert cfg.scene.dt == pytest.approx(interval / n, rel=1e-12)
    assert cfg.scene.dt * (c + vmax) / cfg.scene.dx <= S.SNAPSHOT_CFL
    assert (interval / (n - 1)) * (c + vmax) / cfg.scene.dx > S.SNAPSHOT_CFL     # n is the smallest
    if snapshots is not None:
        assert cfg.steps == snapshots * n
    if res != "paper" or name != "rom_tower":     # the 3M-particle tower is documented, not built
        scene = build_scene(cfg)
        assert scene.cfl_number(scene.resolve_dt()) <= S.SNAPSHOT_CFL


def test_resolution_particle_counts():
    from scipy.spatial import cKDTree

    pts = lambda name, res: build_scene(compose([f"scene={name}", f"scene.resolution={res}"])).particles().x
    count = lambda name, res: len(pts(name, res))
    paper, fine = pts("rom_torsion", "paper"), pts("rom_torsion", "fine")
    assert len(paper) == 1920 and len(fine) == 8 * len(paper)   # 2x finer per axis (paper: 1,757 -> 13,900)
    assert cKDTree(paper).query(fine)[0].min() > 1e-4           # no fine point is a paper point (Sec. 5.2.1)
    assert 40_000 <= count("rom_tower", "cpu") <= 60_000  # "cpu is about 50k particles"
    cfg = compose(["scene=rom_tower", "scene.resolution=paper"])
    h = cfg.scene.dx / 3
    from mpmlab.core.geometry import make_shape
    spec = {k: v for k, v in OmegaConf.to_container(cfg.scene.bodies.tower.shape).items() if v is not None}
    vol = make_shape(**spec).volume(3)
    assert vol / h**3 == pytest.approx(3_076_115, rel=0.01)  # by volume, the paper's count


# ---------------------------------------------------------------------------------------------------
# studies and splits
# ---------------------------------------------------------------------------------------------------
def check_split(s, n_train, n_test):
    assert len(s.train) == n_train and len(s.test) == n_test
    assert not set(s.train) & set(s.test) and sorted(s.train + s.test) == list(range(len(s.runs)))
    assert len({r.name for r in s.runs}) == len(s.runs)


def test_gravity_study():
    s = S.study("gravity")
    check_split(s, 24, 6)
    np.testing.assert_allclose(s.param_array()[:, 0], np.linspace(1, 10, 30), rtol=0, atol=1e-15)
    assert s.split("test") == S.study("gravity", seed=0).test != S.study("gravity", seed=1).test
    assert s.runs[0].overrides[:2] == ("scene=cylinder_wall_gravity", "scene.gravity=[0.0,-1.0,0.0]")


def test_torsion_study():
    s = S.study("torsion")
    check_split(s, 29, 7)
    grid = set(itertools.product(np.linspace(0, 0.6, 6).tolist(), np.linspace(0, 2, 6).tolist()))
    assert {(r.params["v"], r.params["omega"]) for r in s.runs} == grid
    assert s.test == S.study("torsion").test != S.study("torsion", seed=3).test
    fine = S.study("torsion_fine")
    assert [r.params for r in fine.runs] == [s.runs[i].params for i in s.test] and len(fine.test) == 7
    assert all("scene.resolution=fine" in r.overrides for r in fine.runs)


def test_poke_study():
    s = S.study("poke")
    check_split(s, 12, 24)
    th = s.param_array()[:, 0]
    np.testing.assert_allclose(th, np.arange(36) * np.pi / 18)
    np.testing.assert_allclose(th[list(s.train)], np.arange(12) * np.pi / 6)
    assert s.snapshots == 432 and s.interval == 1 / 144


def test_the_slow_poke_is_the_poke_at_4_8_mm_per_s():
    from mpmlab.config import compose

    fast, slow = S.study("poke"), S.study("poke_slow")
    assert slow.train == fast.train and slow.test == fast.test
    np.testing.assert_array_equal(slow.param_array(), fast.param_array())
    # both the run's own overrides and the sweep (the experiment's vars merged with the swept theta)
    assert compose(list(slow.runs[1].overrides)).scene.vars.speed == 0.0048
    assert compose(list(fast.runs[1].overrides)).scene.vars.speed == 0.048
    swept = compose(["experiment=rom_snapshots_poke_slow", "scene.vars={theta:0.5}"]).scene.vars
    assert swept.speed == 0.0048 and swept.theta == 0.5


def test_continual_pokes_are_seeded():
    a, b = S.continual_pokes(0), S.continual_pokes(1)
    assert len(a) == 10 and [p["t_start"] for p in a] == [3.0 * i for i in range(10)]
    assert all(0 <= p["theta"] < 2 * np.pi for p in a) and a == S.continual_pokes(0) and a != b
    assert S.study("poke_continual").snapshots == 4320


def test_tower_study_is_two_latin_hypercubes():
    s = S.study("tower")
    check_split(s, 16, 4)
    P = s.param_array()
    for j, k in enumerate(s.param_names):
        lo, hi = S.TOWER_RANGES[k]
        assert np.all((P[:, j] >= lo) & (P[:, j] < hi))
        for idx in (s.train, s.test):          # one point in each of the n strata per dimension
            u = (P[list(idx), j] - lo) / (hi - lo)
            assert sorted(np.floor(u * len(idx)).astype(int)) == list(range(len(idx)))
    assert np.array_equal(P, S.study("tower").param_array()) and not np.allclose(P, S.study("tower", seed=5).param_array())


@pytest.mark.parametrize("name", list(S.STUDIES))
def test_experiments_are_generated_from_the_studies(name):
    """conf/experiment/rom_snapshots_<study>.yaml is what experiment_yaml writes, and its sweep is the runs."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    s = S.study(name)
    assert S.experiment_path(name).read_text() == S.experiment_yaml(s), "rerun `python -m mpmlab.rom.snapshots`"
    cfg = compose([f"experiment=rom_snapshots_{name}", "scene.resolution=tiny"], return_hydra_config=True)
    assert cfg.scene.name == s.scene and list(cfg.output.fields) == ["F"]
    if not s.sweep:
        return
    (key, value), = cfg.hydra.sweeper.params.items()
    swept = list(OverridesParser.create().parse_overrides([f"{key}={value}"])[0].sweep_iterator())
    assert len(swept) == len(s.runs)
    for run, val in zip(s.runs, swept):
        got = {"g": -val[1]} if key == "scene.gravity" else dict(val)
        assert got == pytest.approx(run.params)


# ---------------------------------------------------------------------------------------------------
# the torsion end's rigid motion
# ---------------------------------------------------------------------------------------------------
def test_torsion_end_follows_the_rigid_motion():
    v, w = 0.36, 1.6
    cfg = compose(["scene=rom_torsion", "scene.resolution=tiny", f"scene.vars.v={v}", f"scene.vars.omega={w}"])
    scene = build_scene(cfg)
    fixed, pulled = scene.boundaries[1], scene.boundaries[2]
    X = scene.particles().x
    i_f, i_p = fixed.select(X), pulled.select(X)
    assert len(i_f) == len(i_p) == 4 and not set(i_f) & set(i_p)
    c0 = X[i_p].mean(axis=0)
    traj = mpmlab.simulate(scene, cfg.steps, 1, "warp", "mls", "fp64")
    for k, t in enumerate(traj.time):
        a = w * t
        R = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
        c = c0 + np.array([v, 0, 0]) * t
        np.testing.assert_allclose(traj.x[k, i_p], c + (X[i_p] - c0) @ R.T, rtol=0, atol=1e-12)
        np.testing.assert_allclose(traj.x[k, i_f], X[i_f], rtol=0, atol=1e-12)
    assert traj.time[-1] == pytest.approx(2 / 1500)
    # the rest of the bar moves: stretched and twisted
    free = np.setdiff1d(np.arange(len(X)), np.concatenate([i_f, i_p]))
    assert np.abs(traj.x[-1, free, 0] - X[free, 0]).max() > 1e-4


# ---------------------------------------------------------------------------------------------------
# a two-run study: run_study -> load_snapshots, and the reader's refusals
# ---------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def tiny_study(tmp_path_factory):
    root = tmp_path_factory.mktemp("torsion")
    s = S.study("torsion")
    runs = (s.test[0], s.train[0])
    S.run_study(s, root, runs=runs, overrides=["scene.resolution=tiny", "backend=warp", "output.plots=false"])
    return s, root, runs


def test_two_run_study_round_trip(tiny_study):
    s, root, runs = tiny_study
    snap = S.load_snapshots(root, s, runs=runs)
    assert snap.x.shape == (2, 3, 40, 3) and snap.v.shape == (2, 3, 40, 3) and snap.F.shape == (2, 3, 40, 3, 3)
    np.testing.assert_allclose(snap.params, s.param_array(runs))
    np.testing.assert_allclose(snap.time, [0, 1 / 1500, 2 / 1500], rtol=1e-6)
    assert snap.names == tuple(s.runs[i].name for i in runs)
    np.testing.assert_allclose(snap.X[0], snap.X[1])
    np.testing.assert_allclose(snap.F[:, 0], np.broadcast_to(np.eye(3), (2, 40, 3, 3)), atol=1e-7)
    assert np.all(np.isfinite(snap.F))
    # reversed order and files given as a list: the study's order comes back
    back = S.load_snapshots(list(snap.paths[::-1]), s, runs=runs)
    np.testing.assert_array_equal(back.x, snap.x)
    # files of another scene are skipped; a split with runs missing is refused in one line
    with pytest.raises(ConfigError) as e:
        S.load_snapshots(root, s, split="test")
    assert "6 run(s) of the test split have no trajectory.h5" in one_line(e)
    with pytest.raises(ConfigError) as e:
        S.load_snapshots(root, "gravity", runs=[0])
    assert "no trajectory.h5" in one_line(e)


def _rewrite(src, dst, **changes):
    from mpmlab.io.h5 import read_attrs, read_trajectory, write_trajectory

    attrs = read_attrs(src)
    traj = dataclasses.replace(read_trajectory(src), **changes)
    dst.parent.mkdir(parents=True, exist_ok=True)
    write_trajectory(dst, traj, config_yaml=attrs["config_yaml"], overwrite=True)


def test_reader_refusals_are_one_line(tiny_study, tmp_path):
    s, root, runs = tiny_study
    a, b = (root / s.runs[i].name / "trajectory.h5" for i in runs)
    from mpmlab.io.h5 import read_trajectory

    # F missing
    shutil.copytree(root, tmp_path / "noF")
    _rewrite(a, tmp_path / "noF" / s.runs[runs[0]].name / "trajectory.h5", fields={}, field_particles={})
    with pytest.raises(ConfigError) as e:
        S.load_snapshots(tmp_path / "noF", s, runs=runs)
    assert "stores no F" in one_line(e)
    # another particle count
    t = read_trajectory(b)
    keep = slice(0, 30)
    sub = dict(x=t.x[:, keep], v=t.v[:, keep], mass=t.mass[keep], volume=t.volume[keep],
               material_id=t.material_id[keep], body_id=t.body_id[keep], params=t.params[keep],
               fields={"F": t.fields["F"][:, keep]}, field_particles={"F": np.arange(30)},
               materials=[{**t.materials[0], "stop": 30}])
    shutil.copytree(root, tmp_path / "fewer")
    _rewrite(b, tmp_path / "fewer" / s.runs[runs[1]].name / "trajectory.h5", **sub)
    with pytest.raises(ConfigError) as e:
        S.load_snapshots(tmp_path / "fewer", s, runs=runs)
    assert "has 30 particles but" in one_line(e)
    # v missing: the trajectory reader refuses the file as damaged, in one line
    import h5py

    shutil.copytree(root, tmp_path / "noV")
    with h5py.File(tmp_path / "noV" / s.runs[runs[0]].name / "trajectory.h5", "a") as f:
        del f["frames/v"]
    with pytest.raises(ConfigError) as e:
        S.load_snapshots(tmp_path / "noV", s, runs=runs)
    assert "frames/v" in one_line(e)
    # two files for one run
    shutil.copytree(root, tmp_path / "dup")
    shutil.copytree(root / s.runs[runs[0]].name, tmp_path / "dup" / "again")
    with pytest.raises(ConfigError) as e:
        S.load_snapshots(tmp_path / "dup", s, runs=runs)
    assert "has two files" in one_line(e)
    # a file whose parameters are no run of the study
    shutil.copytree(root, tmp_path / "alien")
    p = tmp_path / "alien" / s.runs[runs[0]].name / "trajectory.h5"
    from mpmlab.io.h5 import read_attrs, write_trajectory

    cfg = OmegaConf.create(read_attrs(p)["config_yaml"])
    cfg.scene.vars.omega = 0.123
    traj = read_trajectory(p)
    p.unlink()
    write_trajectory(p, traj, config_yaml=OmegaConf.to_yaml(cfg))
    with pytest.raises(ConfigError) as e:
        S.load_snapshots(tmp_path / "alien", s, runs=runs)
    assert "is not a run of study 'torsion'" in one_line(e)
    for bad in (dict(split="validation"), dict(runs=[99])):
        with pytest.raises(ConfigError) as e:
            S.load_snapshots(root, s, **bad)
        one_line(e)
    with pytest.raises(ConfigError) as e:
        S.study("bending")
    one_line(e)


def test_cli_sweep_of_a_study_reads_back(tmp_path):
    """`mpmlab -m experiment=rom_snapshots_tower` with two of the study's test runs swept from the
    command line (it replaces the experiment's 20): per-job trajectory.h5 files that load_snapshots
    matches back to those runs by their recorded parameters."""
    import os
    import subprocess
    import sys

    s = S.study("tower")
    pick = s.test[:2]
    value = ",".join("{" + ",".join(f"{k}:{s.runs[i].params[k]!r}" for k in s.param_names) + "}" for i in pick)
    proc = subprocess.run([sys.executable, "-m", "mpmlab", "-m", "experiment=rom_snapshots_tower", "scene.resolution=tiny",
                           "backend=warp", "output.plots=false", f"scene.vars={value}", f"hydra.sweep.dir={tmp_path}"],
                          cwd=tmp_path, capture_output=True, text=True, timeout=300, env=dict(os.environ))
    assert proc.returncode == 0, proc.stderr[-2000:]
    snap = S.load_snapshots(tmp_path, s, runs=pick)
    assert snap.x.shape == (2, 3, 208, 3) and snap.F.shape == (2, 3, 208, 3, 3)
    np.testing.assert_allclose(snap.params, s.param_array(pick))
    np.testing.assert_allclose(snap.time, [0, 1 / 24, 2 / 24], rtol=1e-6)


@pytest.mark.parametrize("name", list(S.STUDIES))
def test_a_study_run_composes_with_its_parameters(name):
    """A run's overrides make the scene with that run's parameters (read back as load_snapshots does)."""
    s = S.study(name)
    run = s.runs[-1]
    cfg = compose([*run.overrides, "scene.resolution=tiny"] if s.scene != "cylinder_wall_gravity" else run.overrides)
    plain = OmegaConf.to_container(cfg, resolve=True)
    assert plain["scene"]["name"] == s.scene and s.param_of(plain) == pytest.approx(
        {k: run.params[k] for k in s.param_names})
    assert list(cfg.output.fields) == ["F"] and cfg.output.recording is False
    scene = build_scene(cfg)
    assert scene.particles().count > 0


def test_the_poke_pushes_the_cylinder_and_it_springs_back():
    """rom_poke at `paper` (theta = pi/18), 0.5 s: the poke (grid nodes near the top point, moved 12 mm in
    0.25 s) pushes the body, not only the particles it holds, and after the release the body returns. With
    a particle grip the poked particles were dragged 12 mm through the body and stayed 11.6 mm away while
    the rest moved at most 0.8 mm (the scene's comment)."""
    th = np.pi / 18
    cfg = compose(["scene=rom_poke", f"scene.vars.theta={th!r}", "scene.steps=1800", "scene.frame_every=900",
                   "transfer=pic", "precision=fp64"])
    scene = build_scene(cfg)
    traj = mpmlab.simulate(scene, 1800, 900, "jax", "pic", "fp64")      # frames at 0, 0.25 and 0.5 s
    x = np.asarray(traj.x)
    x0 = x[0]
    point = np.array([0.028 - 0.01 * np.cos(th), 0.028 - 0.01 * np.sin(th), 0.048])
    poked = np.linalg.norm(x0 - point, axis=1) <= 0.004
    u = np.linalg.norm(x - x0, axis=-1)
    assert u[1][poked].mean() > 6e-3 and u[1][~poked].max() > 5e-3          # pushed as a body at 0.25 s
    assert u[-1][poked].mean() < 5e-4 and u[-1][~poked].max() < 5e-4        # back within 0.5 mm at 0.5 s
