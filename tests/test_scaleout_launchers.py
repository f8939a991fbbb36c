"""Issue 20, scale-out: sweeps through submitit (Slurm) and Ray, without a cluster.

* ``hydra/launcher=slurm`` (mpmlab's Slurm config) submits to a Slurm stand-in (``fake_slurm.py``:
  ``sbatch``/``srun``/``sacct`` on this machine), ``submitit_local`` runs submitit's local executor
  (Slurm's code path minus ``sbatch``), ``ray`` a local Ray instance. Each runs a real two-job sweep
  in which job 1 diverges: the closing line and exit code are those of the local launchers, job 0's
  outputs are all there and read back, job 1 keeps its frames marked incomplete, ``jobs.jsonl`` and
  ``mpmlab sweep-summary`` see both.

The time limit and killed jobs: tests/test_scaleout_time_limits.py.
"""
from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from mpmlab.cli import EXIT_DIVERGED, main

from . import fake_slurm
from .test_cli import OUTPUTS, error_lines

SUBMITIT = "hydra_plugins.hydra_submitit_launcher"
RAY = "hydra_plugins.hydra_ray_launcher"
# job 0 runs its 40 steps; job 1 (dt 50x larger, CFL check relaxed) diverges at step 4
SWEEP = ["scene=dam_break_2d", "scene.resolution=tiny", "scene.cfl_limit=100", "scene.dt=0.0002,0.01", "steps=40",
         "frame_every=10"]


def mpmlab(args, cwd: Path, env: dict | None = None, timeout: float = 300) -> tuple[subprocess.CompletedProcess, int]:
    """``python -m mpmlab`` with this interpreter (the launcher plugins are those of its environment);
    returns the finished process and its pid (the sweep's own process)."""
    proc = subprocess.Popen([sys.executable, "-m", "mpmlab", *args], cwd=cwd, env=dict(os.environ, **(env or {})),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
        raise AssertionError(f"mpmlab {' '.join(args)} ran over {timeout} s:\n{err[-3000:]}") from None
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err), proc.pid


@pytest.fixture(autouse=True)
def _no_job_left_behind(tmp_path):
    yield
    fake_slurm.stop_all(tmp_path / "slurm")


def _launcher(name: str, tmp_path: Path) -> tuple[list[str], dict]:
    """The overrides and environment that run a sweep through ``name``."""
    pytest.importorskip(RAY if name == "ray" else SUBMITIT, reason=f"install mpmlab[{'ray' if name == 'ray' else 'slurm'}]")
    if name == "slurm":
        return ["hydra/launcher=slurm"], fake_slurm.install(tmp_path / "bin", tmp_path / "slurm")
    if name == "ray":   # a local instance of two CPUs, no dashboard (faster to start), no token in ~/.ray
        return ["hydra/launcher=ray", "+hydra.launcher.ray.init.num_cpus=2",
                "+hydra.launcher.ray.init.include_dashboard=false"], {"RAY_AUTH_MODE": "disabled"}
    return [f"hydra/launcher={name}"], {}


def _summary(run: Path) -> dict:
    return json.loads((run / "summary.json").read_text())


@pytest.mark.slow
@pytest.mark.parametrize("launcher", ["submitit_local", "slurm", "ray"])
def test_a_two_job_sweep_keeps_the_good_job_and_reports_the_diverged_one(tmp_path, capsys, launcher):
    from mpmlab.io.h5 import read_attrs, read_trajectory

    overrides, env = _launcher(launcher, tmp_path)
    sweep = tmp_path / "sweep"
    proc, pid = mpmlab(["-m", *overrides, *SWEEP, f"hydra.sweep.dir={sweep}"], tmp_path, env)
    if launcher == "slurm":
        states = fake_slurm.wait_until_idle(tmp_path / "slurm")
        assert states == {"4200_0": "COMPLETED", "4200_1": "COMPLETED"}, states   # one array job, two tasks
    assert proc.returncode == EXIT_DIVERGED, proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr
    last = error_lines(proc.stderr)[-1]
    assert last.startswith("mpmlab: error: 1 of 2 jobs failed (2 jobs: 1 diverged, 1 ok); job 1 ("), last
    assert "scene.dt=0.01" in last and "diverged at step 4" in last and str(sweep / "jobs.jsonl") in last

    good, bad = _summary(sweep / "0"), _summary(sweep / "1")
    assert (good["status"], good["steps_done"], good["frames"], good["dt"]) == ("ok", 40, 5, 0.0002)
    for name in OUTPUTS:
        assert (sweep / "0" / name).is_file(), name
    traj = read_trajectory(sweep / "0" / "trajectory.h5")
    assert traj.frame_count == 5 and list(traj.step) == [0, 10, 20, 30, 40]
    assert bad["status"] == "diverged" and bad["diverged_step"] == 4
    attrs = read_attrs(sweep / "1" / "trajectory.h5")
    assert attrs["complete"] is False and attrs["frame_count"] >= 1
    jobs = [json.loads(line) for line in (sweep / "jobs.jsonl").read_text().splitlines()]
    assert sorted((j["job"], j["status"], j["exit_code"]) for j in jobs) == [(0, "ok", 0), (1, "diverged", EXIT_DIVERGED)]
    # the jobs ran in processes of the launcher, not in the sweep's own
    assert good["pid"] != pid and bad["pid"] != pid
    if launcher == "slurm":   # what mpmlab's slurm.yaml asks of Slurm
        script = (tmp_path / "slurm" / "4200.sbatch").read_text()
        for flag in ("--array=0-1%2", "--time=240", "--signal=USR2@120", "--gpus-per-node=1", "--cpus-per-task=8"):
            assert f"#SBATCH {flag}\n" in script, flag
    if launcher in ("slurm", "submitit_local"):
        assert len(list((sweep / ".submitit").rglob("*_result.pkl"))) == 2
    if launcher == "ray":
        assert "Ray Launcher is launching 2 jobs" in proc.stdout + proc.stderr

    # the same sweep in one table
    assert main(["sweep-summary", str(sweep), "--metric", "particle_steps_per_second"]) == 0
    out = capsys.readouterr().out
    assert "2 jobs (1 diverged, 1 ok); swept: scene.dt" in out
    rows = list(csv.DictReader((sweep / "sweep_summary.csv").open()))
    assert [(r["job"], r["status"], r["scene.dt"]) for r in rows] == [("0", "ok", "0.0002"), ("1", "diverged", "0.01")]
    assert float(rows[0]["particle_steps_per_second"]) == pytest.approx(good["particle_steps_per_second"])
    assert rows[1]["particle_steps_per_second"] == "" and "diverged at step 4" in rows[1]["message"]


def test_a_launcher_that_is_not_installed_names_its_extra(tmp_path, capsys):
    code = main(["-m", "hydra/launcher=nope", "steps=1", f"hydra.sweep.dir={tmp_path / 'sweep'}"])
    (line,) = error_lines(capsys.readouterr().err)
    assert code == 2 and "available options in 'hydra/launcher'" in line
    assert "'mpmlab[slurm]' (slurm, submitit_local) or 'mpmlab[ray]' (ray)" in line, line


def test_a_submitit_job_that_failed_outside_its_run_reads_as_one_line(monkeypatch):
    """What submitit raises for a job that left no result (the SIGKILL case runs for real in
    test_scaleout_time_limits.py); not an "internal error, please report it"."""
    from mpmlab import cli
    from mpmlab.cli import describe_error

    monkeypatch.setattr(cli, "_sweep_dir", None)   # no sweep of this process to point at
    utils = pytest.importorskip("submitit.core.utils")
    failed = utils.FailedJobError(
        "Job (task=0) failed during processing with trace:\n----------------------\nTraceback (most recent call "
        "last):\n  File \"x.py\", line 1\nAttributeError: Can't get attribute 'MpmlabConfig'\n"
        "----------------------\nYou can check full logs with 'job.stderr(0)' and 'job.stdout(0)'or at paths:\n"
        "  - /s/.submitit/7_0/7_0_0_log.err\n  - /s/.submitit/7_0/7_0_0_log.out")
    assert describe_error(failed) == (1, "a sweep job failed outside its run: AttributeError: Can't get attribute "
                                         "'MpmlabConfig'; its log: /s/.submitit/7_0/7_0_0_log.err (the other jobs go on).")
    killed = utils.UncompletedJobError("Job 7_1 (task: 0) with path /s/.submitit/7_1/7_1_0_result.pkl\nhas not "
                                       "produced any output (state: OUT_OF_MEMORY)\nError stream produced:\n----\nx")
    code, line = describe_error(killed)
    assert code == 1 and line.startswith("sweep job 7_1 ended without a result (state OUT_OF_MEMORY: killed")
    assert "its log: /s/.submitit/7_1/7_1_0_log.err (the other jobs go on)." in line

