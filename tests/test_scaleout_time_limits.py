"""Issue 20, scale-out: how a submitit (Slurm) sweep job ends at its time limit, or killed.

* submitit's warning signal (SIGUSR2, ``signal_delay_s`` before ``timeout_min``: Slurm's ``--signal``,
  or the local executor's controller) stops the job like SIGTERM ("Outputs that never lie"): its frames
  kept and marked incomplete, its summary and ``jobs.jsonl`` "interrupted", and no requeue (submitit's
  own handler would requeue it to start over, which an mpmlab run cannot resume).
* A job killed without a word (SIGKILL: out of memory, the limit's grace run out) is named in one line
  with its log, and ``mpmlab sweep-summary`` lists it next to the jobs that ended.

The Slurm here is tests/fake_slurm.py; two-job sweeps through each launcher: test_scaleout_launchers.py.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys

import pytest

from mpmlab.cli import main

from . import fake_slurm
from .test_cli import error_lines
from .test_run_endings import LONG, _temps, _wait_for_frames
from .test_scaleout_launchers import _launcher, _no_job_left_behind, _summary, mpmlab  # noqa: F401 - a fixture

@pytest.mark.slow
@pytest.mark.parametrize("launcher", ["slurm", "submitit_local"])
def test_the_time_limit_warning_stops_the_job_and_keeps_its_frames(tmp_path, launcher):
    """timeout_min=1: SIGUSR2 signal_delay_s before it (Slurm's ``--signal``: 40 s, so 20 s after the job
    starts; submitit's local controller: its fixed 30 s), SIGTERM at the limit. The job stops at the warning."""
    from mpmlab.io.h5 import read_attrs, read_trajectory

    overrides, env = _launcher(launcher, tmp_path)
    if launcher == "slurm":
        overrides.append("hydra.launcher.signal_delay_s=40")
    sweep = tmp_path / "sweep"
    proc, _ = mpmlab(["-m", *overrides, "hydra.launcher.timeout_min=1", *LONG, f"hydra.sweep.dir={sweep}"], tmp_path,
                     env, timeout=180)
    if launcher == "slurm":
        assert "#SBATCH --signal=USR2@40\n" in (tmp_path / "slurm" / "4200.sbatch").read_text()
        # ended by the job itself, before the limit's SIGTERM
        assert fake_slurm.wait_until_idle(tmp_path / "slurm") == {"4200": "COMPLETED"}
    assert proc.returncode == 128 + signal.SIGUSR2, proc.stderr[-3000:]
    last = error_lines(proc.stderr)[-1]
    assert last.startswith("mpmlab: error: 1 of 1 jobs failed (1 jobs: 1 interrupted); job 0 ("), last
    assert "stopped by SIGUSR2 (the scheduler's warning before the job's time limit" in last
    assert "marked incomplete" in last
    run = sweep / "0"
    assert _temps(run) == []
    attrs = read_attrs(run / "trajectory.h5")
    assert attrs["complete"] is False and "SIGUSR2" in attrs["error"], attrs
    with pytest.warns(UserWarning, match="incomplete"):
        traj = read_trajectory(run / "trajectory.h5")
    assert traj.frame_count >= 2 and traj.step[-1] % 20 == 0
    s = _summary(run)
    assert s["status"] == "interrupted" and "SIGUSR2" in s["error"] and s["steps_done"] < 1_000_000
    assert s["last_frame"]["step"] == int(traj.step[-1]) and s["frames"] == traj.frame_count
    assert "run stopped by SIGUSR2" in (run / "mpmlab.log").read_text()
    jobs = [json.loads(line) for line in (sweep / "jobs.jsonl").read_text().splitlines()]
    assert [(j["job"], j["status"], j["exit_code"]) for j in jobs] == [(0, "interrupted", 128 + signal.SIGUSR2)]
    # mpmlab's handler took the signal: submitit did not checkpoint and requeue the job to start over
    logs = "".join(p.read_text() for p in (sweep / ".submitit").rglob("*_log.*"))
    assert "Caught signal" not in logs and "requeue" not in logs.lower(), logs[-2000:]


@pytest.mark.slow
def test_a_killed_slurm_job_is_named_and_the_others_are_kept(tmp_path, capsys):
    overrides, env = _launcher("slurm", tmp_path)
    sweep = tmp_path / "sweep"
    sweep_args = [a for a in LONG if not a.startswith("steps=")] + ["steps=1000000,40"]   # job 1 is short
    proc = subprocess.Popen([sys.executable, "-m", "mpmlab", "-m", *overrides, *sweep_args, f"hydra.sweep.dir={sweep}"],
                            cwd=tmp_path, env=dict(os.environ, **env), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    _wait_for_frames(sweep / "0", proc)
    os.kill(int((tmp_path / "slurm" / "4200_0.pid").read_text()), signal.SIGKILL)   # what the OOM killer does
    _, err = proc.communicate(timeout=180)
    assert fake_slurm.wait_until_idle(tmp_path / "slurm") == {"4200_0": "FAILED", "4200_1": "COMPLETED"}
    assert proc.returncode == 1 and "Traceback" not in err
    last = error_lines(err)[-1]
    assert last.startswith("mpmlab: error: sweep job 4200_0 ended without a result (state FAILED: killed"), last
    assert f"its log: {sweep / '.submitit' / '4200_0' / '4200_0_0_log.err'}" in last
    assert f"`mpmlab sweep-summary {sweep}`" in last and "please report" not in last
    assert _summary(sweep / "1")["status"] == "ok"
    assert main(["sweep-summary", str(sweep)]) == 0
    md = (sweep / "sweep_summary.md").read_text()
    assert "2 jobs (1 no outcome, 1 ok); swept: steps" in capsys.readouterr().out
    assert "| 0 | no outcome | 1000000 |" in md and "killed" in md and "| 1 | ok | 40 |" in md
