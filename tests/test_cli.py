"""The ``mpmlab`` command: a real subprocess run and a two-job joblib sweep with their outputs read back,
replay, and every bad-input case (one line on stderr, its exit code, nothing written or overwritten)."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest
from omegaconf import OmegaConf

from mpmlab.cli import EXIT_CONFIG, EXIT_DIVERGED, EXIT_OUTPUT, main

OUTPUTS = ("trajectory.h5", "recording.rrd", "summary.json", "config.yaml", "energy.png")


def run_cli(args, cwd, env=None, timeout=300):
    """The installed console script (falls back to ``python -m mpmlab`` where no script is on PATH)."""
    import shutil

    exe = [shutil.which("mpmlab")] if shutil.which("mpmlab") else [sys.executable, "-m", "mpmlab"]
    e = dict(os.environ, **(env or {}))
    e.pop("MPMLAB_DEBUG", None) if not (env and "MPMLAB_DEBUG" in env) else None
    return subprocess.run(exe + list(args), cwd=cwd, env=e, capture_output=True, text=True, timeout=timeout)


def error_lines(stderr: str) -> list[str]:
    return [l for l in stderr.splitlines() if l.strip()]


# ---------------------------------------------------------------------------------------------
# a real run, its outputs read back
# ---------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    """`mpmlab experiment=quick` (the default experiment cut to 100 steps) in a subprocess."""
    cwd = tmp_path_factory.mktemp("cwd")
    run_dir = tmp_path_factory.mktemp("runs") / "quick"
    proc = run_cli(["experiment=quick", f"hydra.run.dir={run_dir}"], cwd=cwd)
    return proc, run_dir, cwd


def test_run_writes_outputs_and_one_line_summary(quick_run):
    proc, run_dir, cwd = quick_run
    assert proc.returncode == 0, proc.stderr
    for name in OUTPUTS:
        assert (run_dir / name).is_file(), name
    assert list(cwd.iterdir()) == []  # the working directory is never used (no outputs/, no chdir)
    last = proc.stdout.strip().splitlines()[-1]
    assert last.startswith("mpmlab: nclaw_jelly jax/mls/fp32") and "particle-steps/s" in last
    assert "it/s" not in proc.stderr and "%|" not in proc.stderr  # no progress bar when not a terminal
    assert "Traceback" not in proc.stderr


def test_summary(quick_run):
    _, run_dir, _ = quick_run
    s = json.loads((run_dir / "summary.json").read_text())
    assert (s["backend"], s["transfer"], s["precision"], s["scene"], s["status"]) == ("jax", "mls", "fp32", "nclaw_jelly", "ok")
    assert s["particles"] == 1000 and s["steps"] == 100 and s["frames"] == 11
    assert s["wall_time_s"] > s["rollout_time_s"] > 0
    assert s["compile_time_s"] is not None and s["compile_time_s"] >= 0
    assert s["throughput_includes_compile"] is False and s["steady_steps"] == 90
    assert s["particle_steps_per_second"] == pytest.approx(1000 * s["steady_steps"] / s["steady_time_s"])
    assert s["mass_drift_rel"] == 0.0 and len(s["momentum_drift"]) == 3 and s["momentum_drift_rel"] >= 0


def test_trajectory_h5(quick_run):
    from mpmlab.io.h5 import read_attrs, read_trajectory

    _, run_dir, _ = quick_run
    attrs = read_attrs(run_dir / "trajectory.h5")
    assert attrs["schema"] == "mpmlab.trajectory" and attrs["schema_version"] == 1 and attrs["complete"]
    assert attrs["backend"] == "jax" and attrs["transfer"] == "mls" and attrs["precision"] == "fp32"
    assert OmegaConf.create(attrs["config_yaml"]).steps == 100  # the resolved config travels with the data
    traj = read_trajectory(run_dir / "trajectory.h5")
    assert traj.x.shape == (11, 1000, 3) and list(traj.step) == list(range(0, 101, 10))
    assert {"F", "C"} <= set(traj.fields)
    assert traj.x[-1, :, 1].mean() < traj.x[0, :, 1].mean()  # thrown downwards, falls


def test_recording_rrd(quick_run):
    from mpmlab.io.h5 import read_trajectory
    from mpmlab.io.rerun import read_recording_metrics, read_recording_positions

    _, run_dir, _ = quick_run
    traj = read_trajectory(run_dir / "trajectory.h5")
    pos = read_recording_positions(run_dir / "recording.rrd")
    assert sorted(pos) == list(range(11))
    np.testing.assert_allclose(pos[7], traj.x[7], atol=1e-6)
    metrics = read_recording_metrics(run_dir / "recording.rrd")
    assert {"kinetic_energy", "mass", "step_time_ms"} <= set(metrics)
    assert len(metrics["kinetic_energy"][0]) == 11


def test_composed_config_and_plot(quick_run):
    _, run_dir, _ = quick_run
    cfg = OmegaConf.load(run_dir / "config.yaml")
    assert cfg.steps == 100 and cfg.scene.name == "nclaw_jelly" and cfg.backend.name == "jax"
    assert (run_dir / "energy.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_existing_outputs_are_not_overwritten(quick_run, capsys):
    _, run_dir, _ = quick_run
    before = {n: (run_dir / n).read_bytes() for n in OUTPUTS}
    code = main(["experiment=quick", f"hydra.run.dir={run_dir}"])
    err = capsys.readouterr().err
    assert code == EXIT_CONFIG and "already exists" in err and "overwrite" in err
    assert {n: (run_dir / n).read_bytes() for n in OUTPUTS} == before


def test_replay_turns_a_trajectory_into_a_recording(quick_run, tmp_path, capsys):
    from mpmlab.io.rerun import read_recording_positions

    _, run_dir, _ = quick_run
    out = tmp_path / "replay"
    code = main(["task=replay", f"input={run_dir / 'trajectory.h5'}", "output.color_by=speed",
                 "output.record_every=5", f"hydra.run.dir={out}"])
    assert code == 0, capsys.readouterr().err
    assert sorted(read_recording_positions(out / "recording.rrd")) == [0, 5, 10]
    s = json.loads((out / "summary.json").read_text())
    assert s["task"] == "replay" and s["frames"] == 11 and s["input_complete"]


# ---------------------------------------------------------------------------------------------
# sweeps
# ---------------------------------------------------------------------------------------------
def test_joblib_multirun_two_backends(tmp_path):
    pytest.importorskip("hydra_plugins.hydra_joblib_launcher")
    sweep = tmp_path / "sweep"
    proc = run_cli(["-m", "backend=jax,warp", "hydra/launcher=parallel", "hydra.launcher.n_jobs=2",
                    "scene=dam_break_2d", "scene.resolution=tiny", "steps=20", "frame_every=10",
                    f"hydra.sweep.dir={sweep}"], cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    summaries = [json.loads((sweep / str(i) / "summary.json").read_text()) for i in (0, 1)]
    assert [s["backend"] for s in summaries] == ["jax", "warp"]
    assert all(s["status"] == "ok" and s["scene"] == "dam_break_2d" for s in summaries)
    assert summaries[0]["pid"] != summaries[1]["pid"]  # two joblib worker processes
    assert summaries[0]["pid"] != os.getpid()
    for i in (0, 1):  # each job has its own outputs and recording
        for name in OUTPUTS:
            assert (sweep / str(i) / name).is_file(), (i, name)
    assert (sweep / "multirun.yaml").is_file()


def test_python_m_mpmlab_help(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "mpmlab", "--help"], cwd=tmp_path, capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 0
    for line in ("backend: jax, warp", "transfer: apic, flip, flip_pic_time, mls, pic, tpic", "precision: fp32, fp64",
                 "task: bench, inverse, nclaw_eval, nclaw_train, replay, rom_eval, rom_train, simulate"):
        assert line in proc.stdout
    assert "nclaw_jelly" in proc.stdout and "experiment:" in proc.stdout


# ---------------------------------------------------------------------------------------------
# bad input: one line, an exit code, nothing written
# ---------------------------------------------------------------------------------------------
@pytest.fixture
def other_schema_h5(tmp_path):
    import h5py

    p = tmp_path / "other.h5"
    with h5py.File(p, "w") as f:
        f.attrs["schema"] = "somebody.else"
        f.create_dataset("positions", data=np.zeros((2, 3)))
    return p


BAD = [
    (["foo=1"], EXIT_CONFIG, "unknown option 'foo'"),
    (["scene.bodies.cube.velocty=[1,0,0]"], EXIT_CONFIG, "velocty"),
    (["steps=abc"], EXIT_CONFIG, "could not be converted to Integer"),
    (["scene=nope"], EXIT_CONFIG, "available options in 'scene'"),
    (["backend=nope"], EXIT_CONFIG, "available options in 'backend'"),
    (["material.params.E=-1e5"], EXIT_CONFIG, "Young's modulus 'E' = -100000 Pa is outside"),
    (["material.params.nu=0.5"], EXIT_CONFIG, "Poisson ratio 'nu' = 0.5"),
    (["material=sand", "material.params.friction_angle=95"], EXIT_CONFIG, "friction_angle' = 95 deg is outside"),
    (["scene.bodies.cube.shape.hi=[1.2,0.75,0.75]"], EXIT_CONFIG, "outside the domain"),
    (["scene.dt=0.01"], EXIT_CONFIG, "CFL number"),
    (["material.params.E=1e39", "precision=fp32", "scene.dt=auto"], EXIT_CONFIG,
     "parameter E = 1e+39 exceeds fp32's largest value"),
    (["transfer=flip", "transfer.flip_ratio=2"], EXIT_CONFIG, "flip_ratio"),
    (["scene=granular_collapse_2d", "+scene.boundaries.base.kind=friction_walls"], EXIT_CONFIG,
     "'base' is not one of the scene's boundaries, and a new boundary is added whole, e.g. '+scene.boundaries={base:{"),
    (["transfer.shape=quintic"], EXIT_CONFIG, "unknown shape 'quintic'; known shapes: cpdi, cubic, quadratic, ugimp"),
    (["transfer.shape=cubic", "scene.bodies.cube.shape.lo=[0.03,0.25,0.25]"], EXIT_CONFIG,
     "4-node window of shape function 'cubic'"),
    (["output.color_by=eps_p"], EXIT_CONFIG, "color_by='eps_p' is not possible"),
    (["task=replay"], EXIT_CONFIG, "add input=PATH"),
    (["task=replay", "input={tmp}/missing.h5"], EXIT_CONFIG, "does not exist"),
    (["task=replay", "input={other}"], EXIT_CONFIG, "not an mpmlab.trajectory file"),
    (["hydra.run.dir={tmp}/a_file/run"], EXIT_OUTPUT, "cannot write"),
]


@pytest.mark.parametrize("args, code, needle", BAD, ids=[" ".join(a) for a, _, _ in BAD])
def test_bad_input_one_line(tmp_path, other_schema_h5, capsys, args, code, needle):
    (tmp_path / "a_file").write_text("not a directory")
    run_dir = tmp_path / "run"
    args = [a.format(tmp=tmp_path, other=other_schema_h5) for a in args]
    if not any(a.startswith("hydra.run.dir=") for a in args):
        args.append(f"hydra.run.dir={run_dir}")
    got = main(args + ["steps=10"])
    err = capsys.readouterr().err
    lines = error_lines(err)
    assert got == code, err
    assert len(lines) == 1 and lines[0].startswith("mpmlab: error: ") and needle in lines[0], err
    assert "Traceback" not in err
    for name in OUTPUTS:  # nothing was written
        assert not (run_dir / name).exists()


def test_bad_input_subprocess_and_debug_switch(tmp_path):
    proc = run_cli(["material.params.E=-1", f"hydra.run.dir={tmp_path / 'r'}"], cwd=tmp_path)
    assert proc.returncode == EXIT_CONFIG
    assert error_lines(proc.stderr) == [l for l in error_lines(proc.stderr) if l.startswith("mpmlab: error:")]
    assert len(error_lines(proc.stderr)) == 1 and "Traceback" not in proc.stderr
    dbg = run_cli(["material.params.E=-1", f"hydra.run.dir={tmp_path / 'r2'}"], cwd=tmp_path, env={"MPMLAB_DEBUG": "1"})
    assert dbg.returncode == EXIT_CONFIG and "Traceback" in dbg.stderr and "mpmlab: error:" in dbg.stderr


def test_divergence_keeps_the_frames_before_it(tmp_path, capsys):
    from mpmlab.io.h5 import read_attrs

    run_dir = tmp_path / "run"
    code = main(["scene.cfl_limit=100", "scene.dt=0.02", "steps=40", "frame_every=5", f"hydra.run.dir={run_dir}"])
    lines = error_lines(capsys.readouterr().err)
    assert code == EXIT_DIVERGED and len(lines) == 1 and "diverged at step" in lines[0]
    attrs = read_attrs(run_dir / "trajectory.h5")
    assert attrs["complete"] is False and attrs["frame_count"] >= 1
    s = json.loads((run_dir / "summary.json").read_text())
    assert s["status"] == "diverged" and "diverged" in s["error"]
