"""Issue #12: outputs that never lie, whatever ends a run.

Each test here failed on the code before the issue (commit 4816e03):
real step/time labels when ``steps % frame_every != 0`` (both backends, fixed and adaptive dt; h5, rrd,
summary); SIGTERM and SIGINT sent to a real ``mpmlab`` subprocess (a single run and a two-job parallel
sweep) leave readable, incomplete-marked trajectories and no temporary files; ``kill -9`` leaves a
temporary file that the next run reports and recovers; a full disk (a real 3 MiB tmpfs where this
machine lets the test mount one, an injected ENOSPC in any case) ends with exit 4 and one line;
damaged inputs name the file and the dataset; the rerun refusal names ``output.overwrite=true``; a
lost Ctrl-C is raised again at the next chunk; ``mpmlab.log`` says how the run ended; a sweep's
closing line counts every failed job.
"""
from __future__ import annotations

import errno
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from mpmlab.cli import EXIT_CONFIG, EXIT_OUTPUT, main

from .test_cli import error_lines, run_cli

QUICK = ["steps=7", "frame_every=5", "output.fields=[F]"]


def _exe():
    return [shutil.which("mpmlab")] if shutil.which("mpmlab") else [sys.executable, "-m", "mpmlab"]


def _temps(folder: Path) -> list[Path]:
    return [p for p in folder.rglob("*") if p.name.endswith(".tmp")]


# ---------------------------------------------------------------------------------------------
# 1. labels are the real step and time
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("backend", ["jax", "warp"])
def test_last_frame_has_its_real_step_and_time_in_h5_rrd_and_summary(tmp_path, backend):
    from mpmlab.io import read_recording_metrics, read_recording_positions, read_trajectory

    run = tmp_path / "run"
    code = main(["scene=dam_break_2d", "scene.resolution=tiny", "scene.dt=0.0002", f"backend={backend}",
                 "precision=fp64", *QUICK, f"hydra.run.dir={run}"])
    assert code == 0
    traj = read_trajectory(run / "trajectory.h5")
    assert traj.step.tolist() == [0, 5, 7]
    np.testing.assert_allclose(traj.time, [0.0, 0.001, 0.0014], rtol=0, atol=1e-15)
    assert traj.x.dtype == np.float64
    s = json.loads((run / "summary.json").read_text())
    assert s["last_frame"] == {"step": 7, "time": pytest.approx(0.0014, abs=1e-15)}
    assert (s["steps_done"], s["steps_saved"], s["frames"]) == (7, 7, 3)
    # the recording: three frames, the last one at sim_time 0.0014 s with the last positions
    pos = read_recording_positions(run / "recording.rrd")
    assert sorted(pos) == [0, 1, 2]
    np.testing.assert_allclose(pos[2], traj.x[2], atol=1e-6)
    from mpmlab.io.rerun import read_recording_component

    times = read_recording_component(run / "recording.rrd", "world/particles", "Points2D:positions",
                                     index="sim_time")
    assert sorted(k for k in times if k is not None)[-1] == pytest.approx(0.0014e9, rel=1e-9)  # ns
    assert "kinetic_energy" in read_recording_metrics(run / "recording.rrd")


def test_adaptive_dt_labels_are_the_sums_of_the_steps_taken():
    """dt: auto recomputed every 2 steps: the streamed labels equal the rollout's own."""
    import mpmlab
    from mpmlab.config import build_scene, compose
    from mpmlab.io.h5 import TrajectoryWriter

    scene = build_scene(compose(["scene=dam_break_2d", "scene.resolution=tiny", "scene.dt=auto", "scene.dt_every=2"]))
    st = mpmlab.build_stepper(scene, "jax", "flip", "fp64")
    seen = []
    traj = st.rollout(steps=7, every=5, on_frame=lambda i, s: seen.append((s["step"], s["time"])))
    assert traj.step.tolist() == [0, 5, 7] and [s for s, _ in seen] == [0, 5, 7]
    np.testing.assert_array_equal([t for _, t in seen], traj.time)
    assert traj.time[2] > traj.time[1] > 0


def test_writer_prefers_the_state_step_over_frame_index_times_every(tmp_path):
    import mpmlab
    from mpmlab.config import build_scene, compose
    from mpmlab.io import read_trajectory
    from mpmlab.io.h5 import TrajectoryWriter

    scene = build_scene(compose(["scene=dam_break_2d", "scene.resolution=tiny", "scene.dt=0.0002"]))
    st = mpmlab.build_stepper(scene, "jax", "flip", "fp32")
    with TrajectoryWriter(tmp_path / "t.h5", stepper=st, every=50) as w:
        st.rollout(steps=105, every=50, on_frame=w)
    t = read_trajectory(tmp_path / "t.h5")
    assert t.step.tolist() == [0, 50, 100, 105]
    np.testing.assert_allclose(t.time[-1], 105 * 0.0002, rtol=1e-12)


def test_streamed_rollout_keeps_no_frames_in_memory():
    """keep_frames=False (what the simulate task uses with a trajectory): memory bounded on any horizon."""
    import mpmlab
    from mpmlab.config import build_scene, compose

    scene = build_scene(compose(["scene=dam_break_2d", "scene.resolution=tiny", "scene.dt=0.0002"]))
    st = mpmlab.build_stepper(scene, "jax", "flip", "fp32")
    n = []
    traj = st.rollout(steps=20, every=1, keep_frames=False, on_frame=lambda i, s: n.append(i))
    assert len(n) == 21 and traj.frame_count == 0 and traj.step.tolist() == list(range(21))


# ---------------------------------------------------------------------------------------------
# 2, 3, 11. stop signals
# ---------------------------------------------------------------------------------------------
LONG = ["scene=dam_break_2d", "scene.resolution=tiny", "scene.dt=0.0002", "steps=1000000", "frame_every=20"]


def _wait_for_frames(folder: Path, proc, frames: int = 2, timeout: float = 120.0) -> None:
    """Until the streamed trajectory in ``folder`` holds ``frames`` frames (it is flushed per frame)."""
    t0 = time.time()
    while time.time() - t0 < timeout:
        assert proc.poll() is None, proc.communicate()
        for tmp in folder.glob(".trajectory.h5.*.tmp"):
            try:
                with h5py.File(tmp, "r", locking=False) as f:
                    if "frames/x" in f and f["frames/x"].shape[0] >= frames:
                        return
            except (OSError, KeyError):
                pass
        time.sleep(0.3)
    raise AssertionError(f"no {frames} frames in {folder} after {timeout} s")


def _check_interrupted_run(run: Path, signame: str) -> None:
    from mpmlab.io.h5 import read_attrs, read_trajectory

    assert _temps(run) == [], _temps(run)
    a = read_attrs(run / "trajectory.h5")
    assert a["complete"] is False and signame in a["error"], a
    with pytest.warns(UserWarning, match="incomplete"):
        traj = read_trajectory(run / "trajectory.h5")
    assert traj.frame_count >= 2 and traj.step[-1] % 20 == 0
    s = json.loads((run / "summary.json").read_text())
    assert s["status"] == "interrupted" and signame in s["error"]
    assert s["last_frame"]["step"] == int(traj.step[-1]) and s["frames"] == traj.frame_count
    log = (run / "mpmlab.log").read_text()
    assert f"run {'terminated' if signame == 'SIGTERM' else 'interrupted'} by {signame}" in log
    assert "marked incomplete" in log


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_stop_signal_keeps_a_readable_incomplete_trajectory(tmp_path, sig):
    run = tmp_path / "run"
    proc = subprocess.Popen(_exe() + LONG + [f"hydra.run.dir={run}"], cwd=tmp_path, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    _wait_for_frames(run, proc)
    proc.send_signal(sig)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 128 + sig, err
    assert "Traceback" not in err and "Exception ignored" not in err
    last = error_lines(err)[-1]
    name = signal.Signals(sig).name
    assert last.startswith(f"mpmlab: {'terminated' if sig == signal.SIGTERM else 'interrupted'} by {name}")
    assert "trajectory.h5 keeps" in last and "marked incomplete" in last
    _check_interrupted_run(run, name)


@pytest.mark.slow
def test_ctrl_c_on_a_parallel_sweep_keeps_every_jobs_frames(tmp_path):
    pytest.importorskip("hydra_plugins.hydra_joblib_launcher")
    sweep = tmp_path / "sweep"
    proc = subprocess.Popen(_exe() + ["-m", "hydra/launcher=parallel", "hydra.launcher.n_jobs=2", "transfer=flip,apic",
                                      *LONG, f"hydra.sweep.dir={sweep}"], cwd=tmp_path, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)
    for job in ("0", "1"):
        while not (sweep / job).is_dir():
            assert proc.poll() is None, proc.communicate()
            time.sleep(0.3)
        _wait_for_frames(sweep / job, proc)
    os.killpg(proc.pid, signal.SIGINT)            # what Ctrl-C in a terminal does: the whole group
    out, err = proc.communicate(timeout=180)
    assert proc.returncode == 130, err
    assert "Traceback" not in err
    last = error_lines(err)[-1]
    assert last.startswith("mpmlab: error: the sweep was stopped (2 jobs: 2 interrupted)"), last
    for job in ("0", "1"):
        _check_interrupted_run(sweep / job, "SIGINT")
    jobs = [json.loads(l) for l in (sweep / "jobs.jsonl").read_text().splitlines()]
    assert sorted(j["job"] for j in jobs) == [0, 1] and {j["status"] for j in jobs} == {"interrupted"}


def test_a_lost_interrupt_is_raised_again_at_the_next_chunk():
    """Python drops an exception raised in a finaliser ("Exception ignored in ..."): the pending signal
    is raised again by the rollout loop, so one Ctrl-C always stops a run."""
    import mpmlab
    from mpmlab.config import build_scene, compose
    from mpmlab.core import signals

    scene = build_scene(compose(["scene=dam_break_2d", "scene.resolution=tiny", "scene.dt=0.0002"]))
    st = mpmlab.build_stepper(scene, "jax", "flip", "fp32")

    class Swallows:
        def __del__(self):
            os.kill(os.getpid(), signal.SIGINT)   # the handler's raise happens here and is ignored

    frames = []

    def on_frame(i, s):
        frames.append(i)
        if i == 2:
            Swallows()                         # dropped at once: __del__ runs, the KeyboardInterrupt is lost

    with signals.handle_stop_signals():
        with pytest.raises(signals.RunInterrupted) as info:
            st.rollout(steps=1000, every=1, on_frame=on_frame)
    assert info.value.signum == signal.SIGINT
    assert frames[-1] == 2                     # stopped before the next chunk, not 1000 steps later


# ---------------------------------------------------------------------------------------------
# kill -9: the next run says what it found
# ---------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_after_kill_9_the_next_run_recovers_the_frames_and_says_so(tmp_path):
    from mpmlab.io.h5 import read_attrs

    run = tmp_path / "run"
    proc = subprocess.Popen(_exe() + LONG + [f"hydra.run.dir={run}"], cwd=tmp_path, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    _wait_for_frames(run, proc, frames=3)
    proc.kill()
    proc.communicate()
    (tmp, ) = run.glob(".trajectory.h5.*.tmp")
    assert f".{proc.pid}." in tmp.name        # temporary files carry their writer's pid
    again = run_cli(LONG + [f"hydra.run.dir={run}"], cwd=tmp_path)
    assert again.returncode == EXIT_CONFIG     # config.yaml of the killed run is there: refused, as any rerun
    found = [l for l in (again.stdout + again.stderr).splitlines() if "found '" in l]
    assert len(found) == 1 and f"pid {proc.pid}" in found[0] and "recovered its" in found[0], again.stderr
    assert _temps(run) == []
    a = read_attrs(run / "trajectory.h5")
    assert a["complete"] is False and "killed before it finished" in a["error"] and a["frame_count"] >= 3
    assert "killed before it finished" in (run / "mpmlab.log").read_text()


def test_stale_temporary_files_of_dead_writers_are_removed_and_reported(tmp_path):
    from mpmlab.io.files import handle_stale_temps, stale_temps

    live = tmp_path / f".summary.json.{os.getpid()}.abc.tmp"
    dead = tmp_path / ".recording.rrd.999999999.xyz.tmp"
    old = tmp_path / ".config.yaml.q1w2e3.tmp"            # an mpmlab before the pid was in the name
    for p in (live, dead, old):
        p.write_text("x")
    assert sorted(p.name for p, _, _ in stale_temps(tmp_path)) == sorted([dead.name, old.name])
    lines = handle_stale_temps(tmp_path)
    assert len(lines) == 2 and all("removed it" in l for l in lines)
    assert live.exists() and not dead.exists() and not old.exists()


# ---------------------------------------------------------------------------------------------
# 4. a full disk
# ---------------------------------------------------------------------------------------------
def _mount_tmpfs(path: Path, size: str) -> bool:
    path.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)], capture_output=True)
    return r.returncode == 0


@pytest.mark.slow
@pytest.mark.parametrize("trajectory", [True, False])
def test_a_real_full_disk_ends_with_exit_4_and_one_line(tmp_path, trajectory):
    """A 4 MiB tmpfs that another process fills while the run streams (the size pre-flight passed:
    the outputs fit when the run started)."""
    small = tmp_path / "small"
    if not _mount_tmpfs(small, "4m"):
        pytest.skip("this machine does not let the test mount a 4 MiB tmpfs (not root, or no mount rights); "
                    "test_injected_enospc_* cover the same code paths")
    try:
        run = small / "run"
        args = ["scene=dam_break_2d", "scene.resolution=tiny", "scene.dt=0.0002", "steps=3000", "frame_every=20",
                f"output.trajectory={str(trajectory).lower()}", f"hydra.run.dir={run}"]
        proc = subprocess.Popen(_exe() + args, cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                text=True)
        if trajectory:
            _wait_for_frames(run, proc)
        else:
            while not (run / "config.yaml").exists():
                assert proc.poll() is None, proc.communicate()
                time.sleep(0.2)
        free = shutil.disk_usage(small).free
        (small / "filler").write_bytes(b"\0" * (free - 256 * 1024))   # leaves 256 KiB
        out, err = proc.communicate(timeout=180)
        assert proc.returncode == EXIT_OUTPUT, err
        assert "Traceback" not in err and "Segmentation" not in err
        assert len(err.splitlines()) < 10, err
        last = error_lines(err)[-1]
        name = "trajectory.h5" if trajectory else "recording.rrd"
        assert last.startswith(f"mpmlab: error: cannot write '{run / name}': no space left on device"), last
        assert _temps(run) == []
        assert not (run / "recording.rrd").exists()
        if trajectory:   # the frames before the full disk: a readable file, marked incomplete
            from mpmlab.io.h5 import read_attrs

            assert read_attrs(run / "trajectory.h5")["complete"] is False
    finally:
        subprocess.run(["umount", str(small)], capture_output=True)


def test_injected_enospc_in_the_frame_guard_keeps_the_frames_before(tmp_path, monkeypatch, capsys):
    """The guard (``ensure_space``) refuses a frame while the disk still has room for closing the file."""
    import mpmlab.io.files as files
    from mpmlab.io.h5 import read_attrs

    calls = {"n": 0}
    real = files.free_bytes

    def free(path):
        calls["n"] += 1
        return real(path) if calls["n"] < 4 else 1000   # the 4th check: 1000 bytes left

    monkeypatch.setattr(files, "free_bytes", free)
    run = tmp_path / "run"
    code = main(["scene=dam_break_2d", "scene.resolution=tiny", "scene.dt=0.0002", "steps=40", "frame_every=5",
                 f"hydra.run.dir={run}"])
    err = capsys.readouterr().err
    assert code == EXIT_OUTPUT
    last = error_lines(err)[-1]
    assert last.startswith(f"mpmlab: error: cannot write '{run / 'trajectory.h5'}': no space left on device"), last
    assert "marked incomplete" in last and "hydra.run.dir=PATH" in last
    assert read_attrs(run / "trajectory.h5")["complete"] is False
    assert json.loads((run / "summary.json").read_text())["status"] == "failed"
    assert _temps(run) == []


def test_injected_enospc_from_hdf5_removes_the_partial_file(tmp_path, monkeypatch, capsys):
    """A write that fails inside HDF5 (another process filled the disk): no flood of finaliser errors,
    no crash, nothing half-written."""
    import h5py as _h5py

    real = _h5py.Dataset.__setitem__
    count = {"n": 0}

    def failing(self, key, value):
        if self.name == "/frames/x":
            count["n"] += 1
            if count["n"] == 3:
                raise OSError(errno.ENOSPC, "No space left on device")
        return real(self, key, value)

    monkeypatch.setattr(_h5py.Dataset, "__setitem__", failing)
    run = tmp_path / "run"
    code = main(["scene=dam_break_2d", "scene.resolution=tiny", "scene.dt=0.0002", "steps=40", "frame_every=5",
                 f"hydra.run.dir={run}"])
    err = capsys.readouterr().err
    assert code == EXIT_OUTPUT
    assert "no space left on device" in error_lines(err)[-1] and "partial file was removed" in error_lines(err)[-1]
    assert not (run / "trajectory.h5").exists() and _temps(run) == []


# ---------------------------------------------------------------------------------------------
# 6. damaged inputs; 7. the rerun refusal names the CLI key
# ---------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def good_h5(tmp_path_factory):
    run = tmp_path_factory.mktemp("good") / "run"
    assert main(["scene=dam_break_2d", "scene.resolution=tiny", "scene.dt=0.0002", *QUICK,
                 "output.recording=false", "output.plots=false", f"hydra.run.dir={run}"]) == 0
    return run / "trajectory.h5"


def _damage(src: Path, dst: Path, how: str) -> Path:
    shutil.copy(src, dst)
    n = dst.stat().st_size
    if how == "truncated":
        os.truncate(dst, n // 2)
    elif how == "overwritten":
        with h5py.File(dst, "r") as f:
            off = f["frames/x"].id.get_offset() or f["frames/x"].id.get_chunk_info(0).byte_offset
        with open(dst, "r+b") as fh:
            fh.seek(off)
            fh.write(b"\xff" * 64)
    elif how == "missing":
        with h5py.File(dst, "r+") as f:
            del f["frames/v"]
    elif how == "shapes":
        with h5py.File(dst, "r+") as f:
            f["frames/time"].resize(1, axis=0)
    return dst


@pytest.mark.parametrize("how, says", [
    ("truncated", "HDF5 cannot open it"),
    ("overwritten", "frames/x cannot be read"),
    ("missing", "dataset(s) frames/v are missing"),
    ("shapes", "frames/time has 1 frames but frames/x has 3"),
])
def test_replay_of_a_damaged_trajectory_names_the_file_and_dataset(tmp_path, good_h5, capsys, how, says):
    bad = _damage(good_h5, tmp_path / f"{how}.h5", how)
    code = main(["task=replay", f"input={bad}", f"hydra.run.dir={tmp_path / 'out'}"])
    last = error_lines(capsys.readouterr().err)[-1]
    assert code == EXIT_CONFIG
    assert last.startswith(f"mpmlab: error: trajectory file '{bad}' is damaged: ") and says in last, last
    assert "cannot write" not in last and "internal error" not in last


def test_a_refused_rerun_names_output_overwrite_and_leaves_the_log_alone(tmp_path, capsys):
    run = tmp_path / "run"
    args = ["scene=dam_break_2d", "scene.resolution=tiny", "scene.dt=0.0002", *QUICK, "output=minimal",
            f"hydra.run.dir={run}"]
    assert main(args) == 0
    log_before = (run / "mpmlab.log").read_text()
    assert "run completed" in log_before
    capsys.readouterr()
    assert main(args) == EXIT_CONFIG
    last = error_lines(capsys.readouterr().err)[-1]
    assert last == (f"mpmlab: error: '{run / 'config.yaml'}' already exists (an earlier run's output); rerun with "
                    f"output.overwrite=true to replace it, or choose another directory with hydra.run.dir=PATH.")
    assert (run / "mpmlab.log").read_text() == log_before
    assert main(args + ["output.overwrite=true"]) == 0


# ---------------------------------------------------------------------------------------------
# 12. what a run leaves behind
# ---------------------------------------------------------------------------------------------
def test_a_diverged_run_says_so_in_its_log_plot_and_summary(tmp_path, capsys):
    run = tmp_path / "run"
    code = main(["scene=dam_break_2d", "scene.resolution=tiny", "scene.dt=0.01", "scene.cfl_limit=100", "steps=40",
                 "frame_every=1", f"hydra.run.dir={run}"])
    assert code == 3
    log = (run / "mpmlab.log").read_text()
    assert "run ended: simulation diverged at step" in log
    s = json.loads((run / "summary.json").read_text())
    assert s["status"] == "diverged" and s["outputs"].get("energy_plot") == "energy.png"
    from PIL import Image

    assert "DIVERGED at step" in Image.open(run / "energy.png").text["Title"]


def test_a_sweep_closing_line_counts_every_failed_job(tmp_path, capsys):
    sweep = tmp_path / "sweep"
    code = main(["-m", "scene=dam_break_2d", "scene.resolution=tiny", "scene.dt=0.1,0.0002,0.2", "steps=2",
                 "output=minimal", f"hydra.sweep.dir={sweep}"])
    err = capsys.readouterr().err
    assert code == EXIT_CONFIG
    last = error_lines(err)[-1]
    assert last.startswith("mpmlab: error: 2 of 3 jobs failed (3 jobs: 1 ok, 2 refused); job 0 ("), last
    assert "job 2 (" in last and "scene.dt=0.2" in last
    assert "Error executing job" not in err
    jobs = [json.loads(l) for l in (sweep / "jobs.jsonl").read_text().splitlines()]
    assert sorted((j["job"], j["status"]) for j in jobs) == [(0, "refused"), (1, "ok"), (2, "refused")]


def test_a_sweep_refused_for_one_reason_names_it_once(tmp_path, capsys):
    code = main(["-m", "scene=dam_break_2d", "scene.resolution=huge", "steps=2,3,4", "output=minimal",
                 f"hydra.sweep.dir={tmp_path / 'sweep'}"])
    last = error_lines(capsys.readouterr().err)[-1]
    assert code == EXIT_CONFIG
    assert "3 of 3 jobs failed" in last and "and 2 more (jobs 1, 2): failed: " in last, last
    assert last.count("scene.resolutions.huge") == 1, last
