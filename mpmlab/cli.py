"""The ``mpmlab`` command (also ``python -m mpmlab``): a Hydra 1.3 app over the config tree in
``mpmlab/conf``.

    mpmlab                                        # the default experiment (NCLaw JELL-O cube, JAX)
    mpmlab scene=dam_break_2d transfer=apic backend=warp precision=fp64
    mpmlab -m backend=jax,warp scene=nclaw_jelly,nclaw_sand hydra/launcher=parallel
    mpmlab task=replay input=outputs/.../trajectory.h5 output.color_by=speed

Outputs go to the Hydra run directory (``hydra.run.dir=...``); the working directory is never changed.

Errors a user can cause end the run with one line on stderr (what, where, what to do) and a non-zero
exit code: 2 for a bad option or value (config composition, parameters, CFL, files), 3 for a
simulation that diverged, 4 for an output that cannot be written, 1 for anything unexpected. The
traceback is shown with ``MPMLAB_DEBUG=1``, ``debug=true`` or ``--debug``.
"""
from __future__ import annotations

import logging
import os
import re
import sys
from pathlib import Path

from .io.sweep_summary import JOBS_FILE   # <sweep dir>/jobs.jsonl: every job's outcome

EXIT_INTERNAL = 1
EXIT_CONFIG = 2
EXIT_DIVERGED = 3
EXIT_OUTPUT = 4
EXIT_INTERRUPTED = 130

log = logging.getLogger("mpmlab")

_DEBUG_TOKENS = {"debug=true", "debug=True", "debug=1", "+debug=true", "++debug=true", "debug=yes"}


class _Abort(BaseException):
    """Carries a single run's error past Hydra's job runner, which catches ``Exception`` and prints an
    extra "Error executing job" line; ``main`` unwraps it and prints the one-line message."""

    def __init__(self, error: BaseException):
        super().__init__(error)
        self.error = error


#: The sweep directory of a multirun started in this process (set by ``SweepRecorder``).
_sweep_dir: Path | None = None
_sweep_on_slurm = False   # its jobs run on a Slurm cluster, where they outlive this process
STOP_FILE = ".mpmlab-stop"   # a stopped parallel sweep: jobs that start after the signal do not run


try:
    from hydra.experimental.callback import Callback as _HydraCallback
except ImportError:  # pragma: no cover - hydra-core < 1.1
    _HydraCallback = object


class SweepRecorder(_HydraCallback):
    """Hydra callback (``hydra.callbacks`` in conf/config.yaml): remembers the sweep directory in the
    process that launches the sweep, so ``main`` can read every job's outcome from ``jobs.jsonl``."""

    def on_multirun_start(self, config, **kwargs) -> None:
        global _sweep_dir, _sweep_on_slurm
        _sweep_dir = Path(str(config.hydra.sweep.dir))
        _sweep_on_slurm = str(config.hydra.launcher.get("_target_", "")).endswith("SlurmLauncher")
        (_sweep_dir / STOP_FILE).unlink(missing_ok=True)
        if _parallel_launcher(config.hydra.launcher):
            from .core.signals import forward_to

            forward_to(_stop_sweep)


def _parallel_launcher(launcher_cfg) -> bool:
    """The joblib launcher: jobs run in worker processes of this machine, which a stop signal reaches."""
    return "joblib" in str(launcher_cfg.get("_target_", ""))


def _stop_sweep(signum: int) -> None:
    """First stop signal in the process running a parallel sweep: jobs not yet started are skipped
    (STOP_FILE), running ones get the signal and close their outputs; the sweep then ends normally."""
    import signal as _signal

    import psutil

    try:
        (_sweep_dir / STOP_FILE).write_text(f"{_signal.Signals(signum).name}\n")
    except OSError:
        pass
    children = psutil.Process().children(recursive=True)
    for child in children:
        try:
            child.send_signal(signum)
        except psutil.Error:
            pass
    print(f"mpmlab: {_signal.Signals(signum).name}: stopping the sweep; {len(children)} job process(es) are "
          f"closing their outputs (send it again to stop at once, losing their last frames).",
          file=sys.stderr, flush=True)


def _record_job(sweep_dir: Path, entry: dict) -> None:
    """Append one job's outcome to ``<sweep dir>/jobs.jsonl`` (one short line, O_APPEND: jobs of a
    parallel or Slurm sweep append to the same file)."""
    import json

    try:
        sweep_dir.mkdir(parents=True, exist_ok=True)
        fd = os.open(sweep_dir / JOBS_FILE, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        try:
            os.write(fd, (json.dumps(entry) + "\n").encode())
        finally:
            os.close(fd)
    except OSError as exc:
        log.warning("could not record job %s in %s: %s", entry.get("job"), sweep_dir / JOBS_FILE, exc)


def _task_function(cfg) -> dict:
    """The Hydra task: set up the run context and dispatch to the task registry."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    from .tasks import RunContext

    logging.getLogger("jax").setLevel(logging.WARNING)  # no "Unable to initialize backend 'tpu'" lines
    hc = HydraConfig.get()
    multirun = hc.mode == RunMode.MULTIRUN
    ctx = RunContext(
        output_dir=Path(hc.runtime.output_dir), overwrite=bool(cfg.output.overwrite), progress=cfg.progress,
        multirun=multirun,
        job={"name": hc.job.name, "num": hc.job.get("num"), "override_dirname": hc.job.override_dirname,
             "overrides": list(hc.overrides.task)},
    )
    job = {"job": hc.job.get("num"), "overrides": list(hc.overrides.task), "dir": str(ctx.output_dir)}
    try:
        return _run_job(cfg, ctx, hc, multirun, job)
    finally:
        if multirun and _parallel_launcher(hc.launcher):
            # a Ctrl-C reaches a joblib worker twice (the terminal's, and the one the sweep's parent
            # passes on): the second must not kill the worker between jobs; the parent stops the sweep
            import signal

            signal.signal(signal.SIGINT, signal.SIG_IGN)


def _run_job(cfg, ctx, hc, multirun: bool, job: dict) -> dict:
    from .core.errors import ConfigError
    from .core.signals import handle_stop_signals
    from .io.files import OutputExistsError, handle_stale_temps
    from .tasks import run_task

    # a sweep worker process gets its own handlers
    with handle_stop_signals(_job_stop_signals(hc) if multirun else ()):
        if multirun and (Path(hc.sweep.dir) / STOP_FILE).exists():
            reason = (Path(hc.sweep.dir) / STOP_FILE).read_text().strip()
            _record_job(Path(hc.sweep.dir), {**job, "status": "skipped", "exit_code": 0,
                                             "message": f"the sweep was stopped by {reason} before this job started"})
            return {"status": "skipped"}
        try:
            from .config import check_known_keys

            check_known_keys(cfg)   # every task: a `+key` that nothing reads is refused before any work
            for line in handle_stale_temps(ctx.output_dir):   # what a run killed with SIGKILL left
                log.warning("%s", line)
            summary = run_task(cfg, ctx)
            if multirun:
                _record_job(Path(hc.sweep.dir), {**job, "status": "ok", "exit_code": 0})
            return summary
        except BaseException as exc:
            if isinstance(exc, SystemExit):
                raise
            code, message = describe_error(exc)
            if isinstance(exc, KeyboardInterrupt) and not hasattr(exc, "mpmlab_detail"):
                from .core.signals import stop_reason

                _log_to_files(f"run {stop_reason(exc)} before its first step; nothing was written but config.yaml.")
            elif not isinstance(exc, (OutputExistsError, KeyboardInterrupt)):
                # how the run ended, in its log; a refused rerun leaves the earlier run's log alone
                _log_to_files(f"run {'refused' if isinstance(exc, ConfigError) else 'ended'}: {message}")
            if not multirun:
                if isinstance(exc, KeyboardInterrupt):
                    raise
                raise _Abort(exc) from None
            status = _status_of(exc)
            _record_job(Path(hc.sweep.dir), {**job, "status": status, "exit_code": code, "message": message})
            if isinstance(exc, KeyboardInterrupt) and hc.launcher.get("_target_", "").endswith("BasicLauncher"):
                raise                  # one process runs the whole sweep: Ctrl-C stops all of it
            if not isinstance(exc, KeyboardInterrupt):
                log.error(message)
            if cfg.debug or _debug_env():
                import traceback

                traceback.print_exception(exc)
            # the sweep goes on; main() reads jobs.jsonl and reports every failed job at the end
            return {"status": status, "exit_code": code, "error": message}


def _submitit_launcher(launcher_cfg) -> bool:
    """submitit's launchers (``slurm``, ``submitit_slurm``, ``submitit_local``): each job is a process that
    submitit starts and signals before the time limit."""
    return "hydra_submitit_launcher" in str(launcher_cfg.get("_target_", ""))


def _job_stop_signals(hc) -> tuple[int, ...]:
    """Stop signals of a sweep job besides SIGINT and SIGTERM: submitit's warning before the time limit."""
    from .core.signals import submitit_warning_signal

    sig = submitit_warning_signal() if _submitit_launcher(hc.launcher) else None
    return (sig,) if sig is not None else ()


def _status_of(exc: BaseException) -> str:
    from .core.errors import ConfigError, FitDiverged, GradientError, SimulationDiverged
    from .io.files import OutputExistsError

    if isinstance(exc, (SimulationDiverged, FitDiverged, GradientError)):
        return "diverged"
    if isinstance(exc, KeyboardInterrupt):
        return "interrupted"
    if isinstance(exc, OutputExistsError):
        return "refused (outputs exist)"
    if isinstance(exc, ConfigError):
        return "refused"
    return "failed"


def _log_to_files(message: str) -> None:
    """Record the error in the run's log file only (the console gets the one line from ``main``)."""
    record = logging.LogRecord("mpmlab", logging.ERROR, __file__, 0, message, None, None)
    for h in logging.getLogger().handlers:
        if isinstance(h, logging.FileHandler):
            h.handle(record)


def _debug_env() -> bool:
    return os.environ.get("MPMLAB_DEBUG", "").lower() in ("1", "true", "yes")


def _first_line(text: str) -> str:
    from .core.errors import first_line

    return first_line(text)


def _omegaconf_detail(exc) -> str:
    """An OmegaConf error as 'message (key: full_key)'."""
    msg = _first_line(str(exc).split("\n    full_key")[0])
    key = getattr(exc, "full_key", None)
    return f"{msg} (key: {key})" if key and key not in msg else msg


def _composition_message(exc) -> str:
    from omegaconf.errors import ConfigAttributeError, ConfigKeyError, OmegaConfBaseException

    text = str(exc)
    lines = [l.rstrip() for l in text.splitlines()]
    head = _first_line(text)
    if "Available options in" in text:  # MissingConfigException: list the options of the group
        opts, grab, group = [], False, ""
        for line in lines:
            if line.startswith("Available options in"):
                grab, group = True, line.split("'")[1] if "'" in line else ""
                continue
            if grab:
                if line.startswith("\t") or line.startswith("    ") and line.strip() and "=" not in line:
                    opts.append(line.strip())
                elif line.strip():
                    break
        head = re.sub(r"^In '[^']*': ", "", head)
        return f"{head}; available options in '{group}': {', '.join(opts)}."
    cause = exc.__cause__
    if isinstance(cause, (ConfigAttributeError, ConfigKeyError)):
        key = getattr(cause, "full_key", "") or head
        return (f"unknown option '{key}' ({_omegaconf_detail(cause)}); check the spelling "
                f"(`mpmlab --cfg job` lists every option); `+{key}=VALUE` adds a key only where entries "
                f"are open (scene.vars, a law's params, a plugin boundary's options).")
    new_boundary = re.search(r"scene\.boundaries\.(\w+)\.\w+=", text)
    if isinstance(cause, OmegaConfBaseException) and new_boundary and "BoundaryConfig" in str(cause):
        name = new_boundary.group(1)      # the typed boundaries take a new entry whole, not key by key
        return (f"{head.rstrip('.')}: '{name}' is not one of the scene's boundaries, and a new boundary is "
                f"added whole, e.g. '+scene.boundaries={{{name}:{{kind:friction_walls,face:y-,along:x,mu:[0.3]}}}}' "
                f"(`mpmlab --cfg job` lists the scene's boundaries).")
    if isinstance(cause, OmegaConfBaseException):
        return f"{head.rstrip('.')}: {_omegaconf_detail(cause)}; fix the value (`mpmlab --cfg job` shows the options and types)."
    if "Could not override" in text and "No match in the defaults list" in text:
        return f"{head} Pick a config group listed by `mpmlab --help`."
    rest = []
    for line in lines[1:]:
        if line.startswith("Config search path"):
            break
        if line.strip() and not line.startswith("\t"):
            rest.append(line.strip())
    return re.sub(r"^In '[^']*': ", "", " ".join([head] + rest[:2]))


def describe_error(exc: BaseException) -> tuple[int, str]:
    """(exit code, one-line message) for an exception that ends a run."""
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    from .core.errors import ConfigError, FitDiverged, GradientError, MpmlabError, SimulationDiverged
    from .core.signals import RunInterrupted, stop_reason
    from .io.files import OutputError, OutputExistsError

    detail = getattr(exc, "mpmlab_detail", "")
    if isinstance(exc, KeyboardInterrupt):
        code = exc.exit_code if isinstance(exc, RunInterrupted) else EXIT_INTERRUPTED
        return code, f"{stop_reason(exc)}" + (f" {detail}" if detail else "") + "."
    if isinstance(exc, SimulationDiverged):
        return EXIT_DIVERGED, str(exc) + (f" ({detail.split('; ', 1)[1]})" if "; " in detail else "")
    if isinstance(exc, (FitDiverged, GradientError)):      # the optimisation diverged, not the input
        return EXIT_DIVERGED, str(exc)
    if isinstance(exc, OutputExistsError):
        return EXIT_CONFIG, (f"'{exc.path}' already exists (an earlier run's output); rerun with "
                             f"output.overwrite=true to replace it, or choose another directory with hydra.run.dir=PATH.")
    if isinstance(exc, OutputError):
        return EXIT_OUTPUT, (f"{exc}" + (f"; {detail.split('; ', 1)[1]}" if "; " in detail else "")
                             + "; free space there or choose another directory with hydra.run.dir=PATH "
                               "(sweeps: hydra.sweep.dir=PATH).")
    if isinstance(exc, ConfigError):
        return EXIT_CONFIG, str(exc)
    if isinstance(exc, MpmlabError):
        return EXIT_INTERNAL, str(exc)
    if isinstance(exc, HydraException):
        msg = _composition_message(exc)
        if "hydra/launcher" in msg or "hydra/sweeper" in msg:
            msg += (" Launchers come as extras: pip install 'mpmlab[joblib]' (parallel), 'mpmlab[slurm]' "
                    "(slurm, submitit_local) or 'mpmlab[ray]' (ray).")
        return EXIT_CONFIG, msg
    if isinstance(exc, OmegaConfBaseException):
        return EXIT_CONFIG, f"invalid configuration: {_omegaconf_detail(exc)}; fix the value (`mpmlab --cfg job` shows the options)."
    if isinstance(exc, ValueError) and "can be specified" in str(exc):  # Hydra's flag conflicts
        return EXIT_CONFIG, f"{_first_line(str(exc))} (e.g. `mpmlab --cfg job scene=...`, without -m)."
    if (lost := _lost_job_message(exc)) is not None:
        return EXIT_INTERNAL, lost
    if isinstance(exc, OSError) and exc.filename:
        what = (exc.strerror or type(exc).__name__).lower()
        return EXIT_OUTPUT, (f"cannot write '{exc.filename}' ({what}); choose a writable output directory with "
                             f"hydra.run.dir=PATH (sweeps: hydra.sweep.dir=PATH).")
    return EXIT_INTERNAL, (f"internal error: {type(exc).__name__}: {_first_line(str(exc))} "
                           f"(run again with MPMLAB_DEBUG=1 for the traceback, and please report it).")


def _lost_job_message(exc: BaseException) -> str | None:
    """submitit's error for a sweep job that left no result, as one line: the job was killed (out of
    memory, SIGKILL when its time limit's grace ran out) or failed outside the run (Hydra's job set-up).
    submitit raises it at the first such job; the others go on."""
    if not type(exc).__module__.startswith("submitit") or not isinstance(exc, RuntimeError):
        return None
    text = str(exc)
    where = f"; every job's outcome: `mpmlab sweep-summary {_sweep_dir}`" if _sweep_dir is not None else ""
    killed = re.search(r"Job (\S+) \(task: \d+\) with path (\S+)_result\.pkl\s+has not produced any output "
                       r"\(state: ([^)]*)\)", text)
    if killed:
        job, stem, state = killed.groups()
        return (f"sweep job {job} ended without a result (state {state}: killed, e.g. out of memory or past its "
                f"time limit; the next run into its folder recovers its streamed frames); its log: "
                f"{stem}_log.err{where} (the other jobs go on).")
    # FailedJobError: the job's traceback between two rules of 22 dashes; its last line says what failed
    lines = [l.strip() for l in text.split("-" * 22)[1].splitlines() if l.strip()] if "-" * 22 in text else []
    log_path = re.search(r"paths:\s+- (\S+)", text)
    return (f"a sweep job failed outside its run: {lines[-1] if lines else _first_line(text)}"
            + (f"; its log: {log_path.group(1)}" if log_path else "") + f"{where} (the other jobs go on).")


def _hydra_app():
    import hydra

    from .config import CONF_DIR, PRIMARY

    return hydra.main(version_base="1.3", config_path=str(CONF_DIR), config_name=PRIMARY)(_task_function)


def main(argv: list[str] | None = None) -> int:
    """Console entry point. Returns (and exits with) the process exit code."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["sweep-summary"]:   # a command of its own, which Hydra never sees
        return _sweep_summary([a for a in argv[1:] if a != "--debug"], _debug_env() or "--debug" in argv)
    debug = _debug_env() or "--debug" in argv or any(a in _DEBUG_TOKENS for a in argv)
    if "--debug" in argv:
        argv.remove("--debug")
        argv.append("debug=true")
    if debug:
        os.environ["MPMLAB_DEBUG"] = "1"  # sweep workers inherit it
    # mpmlab reports errors itself: Hydra re-raises instead of printing its own multi-line report
    saved_env = os.environ.get("HYDRA_FULL_ERROR")
    os.environ["HYDRA_FULL_ERROR"] = "1"
    from .config import register_configs, register_search_path_plugin

    register_configs()
    register_search_path_plugin()
    from .core.signals import handle_stop_signals

    global _sweep_dir
    _sweep_dir = None
    app = _hydra_app()
    saved = sys.argv
    sys.argv = [saved[0] if saved else "mpmlab"] + argv
    stop_signals = handle_stop_signals()
    try:
        stop_signals.__enter__()
        app()
        code = _sweep_outcome() if _sweep_dir is not None else 0
    except SystemExit as exc:  # argparse (--help, bad flags) and Hydra's own exits
        code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    except BrokenPipeError:  # `mpmlab --help | head`
        sys.stdout = open(os.devnull, "w")
        code = 0
    except _Abort as abort:
        code, message = describe_error(abort.error)
        if debug:
            import traceback

            traceback.print_exception(abort.error)
        print(f"mpmlab: error: {message}", file=sys.stderr)
    except KeyboardInterrupt as exc:
        code, message = describe_error(exc)
        if _sweep_dir is not None:
            message += " " + _sweep_interrupted_note()
        elif not hasattr(exc, "mpmlab_detail"):
            message += " Nothing was written but config.yaml (if the run had begun)."
        print(f"mpmlab: {message}", file=sys.stderr)
    except BaseException as exc:  # noqa: BLE001 - the CLI's single error exit
        code, message = describe_error(exc)
        if debug:
            import traceback

            traceback.print_exception(exc)
        print(f"mpmlab: error: {message}", file=sys.stderr)
    finally:
        stop_signals.__exit__(None, None, None)
        sys.argv = saved
        if saved_env is None:
            os.environ.pop("HYDRA_FULL_ERROR", None)
        else:
            os.environ["HYDRA_FULL_ERROR"] = saved_env
    return code


def _sweep_summary(args: list[str], debug: bool) -> int:
    """``mpmlab sweep-summary DIR [--metric KEY] [--out DIR]`` (mpmlab.io.sweep_summary)."""
    from .io.sweep_summary import cli

    try:
        return cli(args)
    except SystemExit as exc:   # --help
        return exc.code if isinstance(exc.code, int) else 0
    except BaseException as exc:  # noqa: BLE001 - the command's single error exit
        code, message = describe_error(exc)
        if debug:
            import traceback

            traceback.print_exception(exc)
        print(f"mpmlab: error: {message}", file=sys.stderr)
        return code


def _read_jobs() -> list[dict]:
    from .io.sweep_summary import read_jobs

    return read_jobs(_sweep_dir)


def _sweep_outcome() -> int:
    """After a sweep: one closing line that counts every job by how it ended and names each one that
    did not complete (exit code: that of the first such job)."""
    jobs = _read_jobs()
    stop_file = _sweep_dir / STOP_FILE
    # "stopped" when the sweep's own process got the stop signal; a job that its scheduler stopped
    # (time limit, preemption) is one job that did not complete
    stopped = stop_file.exists() or any(j.get("status") == "skipped" for j in jobs)
    stop_file.unlink(missing_ok=True)
    bad = [j for j in jobs if j.get("status") != "ok"]
    if not bad:
        return 0
    counts: dict[str, int] = {}
    for j in jobs:
        counts[j.get("status", "?")] = counts.get(j.get("status", "?"), 0) + 1
    tally = ", ".join(f"{n} {s}" for s, n in sorted(counts.items()))
    # jobs that failed the same way are named once (a sweep refused for one reason is one reason, not 30)
    groups: dict[tuple, list] = {}
    for j in bad:
        if j.get("status") != "skipped":
            groups.setdefault((j.get("status"), j.get("message", "")), []).append(j)
    parts = []
    for (status, message), js in groups.items():
        first = js[0]
        who = f"job {first.get('job')} ({','.join(first.get('overrides', [])) or 'no overrides'})"
        if len(js) > 1:
            who += f" and {len(js) - 1} more (jobs {', '.join(str(j.get('job')) for j in js[1:6])}{', ...' if len(js) > 6 else ''})"
        parts.append(f"{who}: {status}: {message}")
    head = "the sweep was stopped" if stopped else f"{len(bad)} of {len(jobs)} jobs failed"
    print(f"mpmlab: error: {head} ({len(jobs)} jobs: {tally})" + ("; " + " | ".join(parts) if parts else "")
          + f" (every job's outcome: {_sweep_dir / JOBS_FILE}).", file=sys.stderr)
    return int(next((j.get("exit_code") for j in bad if j.get("exit_code")), EXIT_INTERRUPTED))


def _sweep_interrupted_note() -> str:
    """What an interrupted sweep left, from the jobs that recorded their end."""
    jobs = _read_jobs()
    counts: dict[str, int] = {}
    for j in jobs:
        counts[j.get("status", "?")] = counts.get(j.get("status", "?"), 0) + 1
    done = ", ".join(f"{n} {s}" for s, n in sorted(counts.items())) or "no job had recorded its end"
    if _sweep_on_slurm:
        return (f"Sweep {_sweep_dir}: {done}; the Slurm jobs go on without this process (scancel stops them, "
                f"each keeping its frames); `mpmlab sweep-summary {_sweep_dir}` reads their outcomes.")
    return (f"Sweep {_sweep_dir}: {done}; an interrupted job's trajectory.h5 keeps its frames so far, marked "
            f"incomplete (every job's outcome: {_sweep_dir / JOBS_FILE}).")


def console_main() -> None:
    sys.exit(main())


if __name__ == "__main__":
    console_main()
