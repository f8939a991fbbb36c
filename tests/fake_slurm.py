"""A Slurm stand-in for the launcher tests: ``sbatch``, ``srun`` and ``sacct`` on this machine.

``install(bin_dir, state_dir)`` writes the three commands into ``bin_dir``; with that folder first on
PATH, submitit (``hydra/launcher=slurm``) submits to it as to a cluster:

* ``sbatch SCRIPT`` keeps the script (``state_dir/<job id>.sbatch``), answers "Submitted batch job
  <id>" and starts the array in the background, at most ``%N`` tasks at a time (``--array=0-K%N``).
  Each task runs the script with bash and the environment Slurm gives a task (SLURM_JOB_ID,
  SLURM_ARRAY_JOB_ID, SLURM_ARRAY_TASK_ID, SLURM_PROCID, ...), its output in the script's
  ``--output``/``--error`` files. Like Slurm with ``--signal=SIG@S`` and ``--time=M``, it sends SIG to
  the task's program S seconds before the M-minute limit, SIGTERM at the limit and SIGKILL 30 s later.
* ``srun [options] PROGRAM ...`` records its pid (the signals' target) and becomes PROGRAM.
* ``sacct -j ID`` reports each task's state (RUNNING, COMPLETED, FAILED, TIMEOUT) from ``state_dir``.
"""
from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

KILL_WAIT_S = 30


def install(bin_dir: Path, state_dir: Path) -> dict[str, str]:
    """Write the commands; returns the environment that puts them on PATH."""
    bin_dir.mkdir(parents=True, exist_ok=True)
    state_dir.mkdir(parents=True, exist_ok=True)
    for name in ("sbatch", "srun", "sacct"):
        cmd = bin_dir / name
        cmd.write_text(f"#!/bin/sh\nexec '{sys.executable}' '{Path(__file__).resolve()}' {name} \"$@\"\n")
        cmd.chmod(0o755)
    return {"PATH": f"{bin_dir}{os.pathsep}{os.environ.get('PATH', '')}", "FAKE_SLURM_DIR": str(state_dir)}


def wait_until_idle(state_dir: Path, timeout: float = 60.0) -> dict[str, str]:
    """Until no job runs (the launcher may return before its jobs' processes have exited); the states."""
    t0 = time.time()
    while True:
        states = {p.name: p.read_text() for p in state_dir.iterdir() if re.fullmatch(r"\d+(_\d+)?", p.name)}
        if "RUNNING" not in states.values() or time.time() - t0 > timeout:
            return states
        time.sleep(0.2)


def stop_all(state_dir: Path) -> None:
    """Kill whatever the stand-in still runs (a test that failed half-way leaves no job behind): the
    processes it recorded that still carry its FAKE_SLURM_DIR (a pid may have been reused since)."""
    import psutil

    if not state_dir.is_dir():
        return
    for pid_file in state_dir.glob("*.pid"):
        try:
            proc = psutil.Process(int(pid_file.read_text()))
            if proc.environ().get("FAKE_SLURM_DIR") == str(state_dir):
                proc.kill()
        except (psutil.Error, ValueError):
            pass


def _state() -> Path:
    return Path(os.environ["FAKE_SLURM_DIR"])


def sbatch(script: str) -> None:
    state = _state()
    job_id = str(4200 + len(list(state.glob("*.sbatch"))))
    kept = state / f"{job_id}.sbatch"   # submitit moves its script once sbatch has answered
    kept.write_text(Path(script).read_text())
    log = open(state / f"{job_id}.array.log", "w")
    # the array runs on after sbatch returns, like a queued job
    array = subprocess.Popen([sys.executable, __file__, "_array", str(kept), job_id], stdout=log,
                             stderr=subprocess.STDOUT, start_new_session=True)
    (state / f"{job_id}.array.pid").write_text(str(array.pid))
    print(f"Submitted batch job {job_id}", flush=True)


def _flags(text: str) -> dict[str, str]:
    return dict(re.findall(r"^#SBATCH --([\w-]+)(?:=(\S+))?", text, re.M))


def _array(script: str, job_id: str) -> None:
    flags = _flags(Path(script).read_text())
    if "array" not in flags:   # one job: no array task ids
        _task(script, job_id, "")
        return
    first, last, parallel = map(int, re.fullmatch(r"(\d+)-(\d+)%(\d+)", flags["array"]).groups())
    pending, running = list(range(first, last + 1)), {}
    while pending or running:
        while pending and len(running) < parallel:
            task = pending.pop(0)
            running[task] = subprocess.Popen([sys.executable, __file__, "_task", script, job_id, str(task)])
        for task, proc in list(running.items()):
            if proc.poll() is not None:
                del running[task]
        time.sleep(0.2)


def _task(script: str, job_id: str, task: str) -> None:
    """One job, or array task ``task`` of job ``job_id``."""
    flags = _flags(Path(script).read_text())
    name = f"{job_id}_{task}" if task else job_id
    state = _state()
    env = dict(os.environ, SLURM_JOB_ID=str(int(job_id) + 1 + int(task)) if task else job_id, SLURM_NTASKS="1",
               SLURM_JOB_NUM_NODES="1", SLURM_NODEID="0", SLURM_PROCID="0", SLURM_LOCALID="0",
               SLURM_JOB_NODELIST="localhost", FAKE_SLURM_TASK=name)
    if task:
        env.update(SLURM_ARRAY_JOB_ID=job_id, SLURM_ARRAY_TASK_ID=task)

    def log(key):
        path = Path(flags[key].replace("%A", job_id).replace("%a", task).replace("%j", job_id))
        path.parent.mkdir(parents=True, exist_ok=True)
        return open(path, "a")

    (state / name).write_text("RUNNING")
    proc = subprocess.Popen(["bash", script], env=env, stdout=log("output"), stderr=log("error"))
    (state / f"{name}.batch.pid").write_text(str(proc.pid))
    limit = 60 * float(flags.get("time", "5"))
    sig_name, _, delay = flags.get("signal", "USR2@0").partition("@")
    warn_at, t0, warned, outcome = limit - float(delay), time.time(), False, None
    while proc.poll() is None:
        elapsed = time.time() - t0
        if not warned and elapsed >= warn_at:
            _signal_program(name, getattr(signal, "SIG" + sig_name.removeprefix("SIG")))
            warned = True
        if elapsed >= limit and outcome is None:
            _signal_program(name, signal.SIGTERM)
            outcome = "TIMEOUT"
        if elapsed >= limit + KILL_WAIT_S:
            proc.kill()
        time.sleep(0.1)
    (state / name).write_text(outcome or ("COMPLETED" if proc.returncode == 0 else "FAILED"))


def _signal_program(task: str, sig: int) -> None:
    """Slurm signals the job steps (what srun started), not the batch shell."""
    pid_file = _state() / f"{task}.pid"
    if pid_file.exists():
        try:
            os.kill(int(pid_file.read_text()), sig)
        except ProcessLookupError:
            pass


def srun(args: list[str]) -> None:
    takes_value = {"--output", "--error", "-o", "-e", "--ntasks", "-n", "--cpus-per-task", "-c"}
    i = 0
    while i < len(args) and args[i].startswith("-"):
        i += 2 if args[i] in takes_value else 1
    (_state() / f"{os.environ['FAKE_SLURM_TASK']}.pid").write_text(str(os.getpid()))
    os.execvp(args[i], args[i:])


def sacct(args: list[str]) -> None:
    wanted = [args[i + 1] for i, a in enumerate(args) if a == "-j"]
    print("JobID|State|NodeList")
    for path in sorted(_state().iterdir()):
        if re.fullmatch(r"\d+(_\d+)?", path.name) and path.name.split("_")[0] in wanted:
            print(f"{path.name}|{path.read_text()}|localhost")


if __name__ == "__main__":
    cmd, rest = sys.argv[1], sys.argv[2:]
    if cmd == "sbatch":
        sbatch(rest[-1])
    elif cmd == "_array":
        _array(*rest)
    elif cmd == "_task":
        _task(*rest)
    elif cmd == "srun":
        srun(rest)
    elif cmd == "sacct":
        sacct(rest)
