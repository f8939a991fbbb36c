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


class JobFailed(Exception):
    """A job's error carried across a sweep launcher's process boundary (picklable; message + code)."""

    def __init__(self, message: str, code: int = EXIT_INTERNAL):
        super().__init__(message, code)
        self.message, self.code = message, code

    def __str__(self) -> str:
        return self.message


def _task_function(cfg) -> dict:
    """The Hydra task: set up the run context and dispatch to the task registry."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    from .tasks import RunContext, run_task

    logging.getLogger("jax").setLevel(logging.WARNING)  # no "Unable to initialize backend 'tpu'" lines
    hc = HydraConfig.get()
    multirun = hc.mode == RunMode.MULTIRUN
    ctx = RunContext(
        output_dir=Path(hc.runtime.output_dir), overwrite=bool(cfg.output.overwrite), progress=cfg.progress,
        multirun=multirun,
        job={"name": hc.job.name, "num": hc.job.get("num"), "override_dirname": hc.job.override_dirname,
             "overrides": list(hc.overrides.task)},
    )
    try:
        return run_task(cfg, ctx)
    except BaseException as exc:
        if isinstance(exc, (KeyboardInterrupt, SystemExit)):
            raise
        code, message = describe_error(exc)
        if not multirun:
            _log_to_files(message)
            raise _Abort(exc) from None
        log.error(message)
        if not (cfg.debug or _debug_env()):
            # launchers pickle job errors across processes; mpmlab errors with rich constructors do not
            # survive that, so the sweep gets a plain picklable error with the same sentence
            raise JobFailed(f"job {hc.job.get('num')} ({hc.job.override_dirname or 'no overrides'}): {message}",
                            code) from None
        raise


def _log_to_files(message: str) -> None:
    """Record the error in the run's log file only (the console gets the one line from ``main``)."""
    record = logging.LogRecord("mpmlab", logging.ERROR, __file__, 0, message, None, None)
    for h in logging.getLogger().handlers:
        if isinstance(h, logging.FileHandler):
            h.handle(record)


def _debug_env() -> bool:
    return os.environ.get("MPMLAB_DEBUG", "").lower() in ("1", "true", "yes")


def _first_line(text: str) -> str:
    for line in str(text).splitlines():
        if line.strip():
            return line.strip()
    return ""


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
                f"(`mpmlab --cfg job` lists every option) or add a new key with +{key}=VALUE.")
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

    from .core.errors import ConfigError, MpmlabError, SimulationDiverged

    if isinstance(exc, JobFailed):
        return exc.code, exc.message
    if isinstance(exc, SimulationDiverged):
        return EXIT_DIVERGED, str(exc)
    if isinstance(exc, ConfigError):
        return EXIT_CONFIG, str(exc)
    if isinstance(exc, MpmlabError):
        return EXIT_INTERNAL, str(exc)
    if isinstance(exc, HydraException):
        msg = _composition_message(exc)
        if "hydra/launcher" in msg or "hydra/sweeper" in msg:
            msg += " Launchers come as extras: pip install 'mpmlab[joblib]' (parallel) or 'mpmlab[slurm]' (slurm)."
        return EXIT_CONFIG, msg
    if isinstance(exc, OmegaConfBaseException):
        return EXIT_CONFIG, f"invalid configuration: {_omegaconf_detail(exc)}; fix the value (`mpmlab --cfg job` shows the options)."
    if isinstance(exc, ValueError) and "can be specified" in str(exc):  # Hydra's flag conflicts
        return EXIT_CONFIG, f"{_first_line(str(exc))} (e.g. `mpmlab --cfg job scene=...`, without -m)."
    if isinstance(exc, OSError):
        where = exc.filename or ""
        what = exc.strerror or type(exc).__name__
        return EXIT_OUTPUT, (f"cannot write '{where}' ({what}); choose a writable output directory with "
                             f"hydra.run.dir=PATH (sweeps: hydra.sweep.dir=PATH).")
    return EXIT_INTERNAL, (f"internal error: {type(exc).__name__}: {_first_line(str(exc))} "
                           f"(run again with MPMLAB_DEBUG=1 for the traceback, and please report it).")


def _hydra_app():
    import hydra

    from .config import CONF_DIR, PRIMARY

    return hydra.main(version_base="1.3", config_path=str(CONF_DIR), config_name=PRIMARY)(_task_function)


def main(argv: list[str] | None = None) -> int:
    """Console entry point. Returns (and exits with) the process exit code."""
    argv = list(sys.argv[1:] if argv is None else argv)
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
    app = _hydra_app()
    saved = sys.argv
    sys.argv = [saved[0] if saved else "mpmlab"] + argv
    try:
        app()
        code = 0
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
    except KeyboardInterrupt:
        print("mpmlab: interrupted; outputs written so far are complete files (trajectory.h5 is marked incomplete).",
              file=sys.stderr)
        code = EXIT_INTERRUPTED
    except BaseException as exc:  # noqa: BLE001 - the CLI's single error exit
        code, message = describe_error(exc)
        if debug:
            import traceback

            traceback.print_exception(exc)
        print(f"mpmlab: error: {message}", file=sys.stderr)
    finally:
        sys.argv = saved
        if saved_env is None:
            os.environ.pop("HYDRA_FULL_ERROR", None)
        else:
            os.environ["HYDRA_FULL_ERROR"] = saved_env
    return code


def console_main() -> None:
    sys.exit(main())


if __name__ == "__main__":
    console_main()
