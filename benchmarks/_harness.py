"""What the benchmark scripts share: the machine description, common command-line options, results
JSON (read, keep what a partial run did not redo, write), Markdown tables, the sections a script
regenerates in ``benchmarks/README.md`` (or any Markdown file), and the throughput scenes.

Imported by the scripts in this folder (run as ``python benchmarks/<name>.py``, so this folder is on
``sys.path``; tests that import a script put it there too). No heavy imports at module level:
``gradients.py`` keeps JAX/Warp/torch out of its parent process on purpose (a child inherits the
parent's peak RSS), so :func:`machine_info` imports the modules it reports only when called.
"""
from __future__ import annotations

import argparse
import importlib
import json
import os
import platform
import sys
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

import numpy as np

HERE = Path(__file__).resolve().parent
#: the repository root (``tests.scenes`` and the top-level README live there)
ROOT = HERE.parent
#: benchmarks/README.md: the generated sections of every script
README = HERE / "README.md"
#: committed results (small JSON), figures, and the uncommitted raw output folder
RESULTS = HERE / "results"
FIGURES = HERE / "figures"
OUT = HERE / "out"
#: the backends a script runs by default
BACKENDS = ("jax", "warp")


# ---- environment ----------------------------------------------------------------------------------
def quiet_warp(threads: int | None = 1) -> None:
    """Call before Warp is imported: no per-module load lines (``WARP_QUIET``) and, unless the
    environment says otherwise, ``threads`` Warp CPU threads (``MPMLAB_WARP_THREADS``; one is steadier
    on a shared machine). ``threads=None`` leaves the thread count to mpmlab."""
    os.environ.setdefault("WARP_QUIET", "1")
    if threads is not None:
        os.environ.setdefault("MPMLAB_WARP_THREADS", str(threads))


def on_path(*folders: Path) -> None:
    """Put ``folders`` first on ``sys.path`` (e.g. :data:`ROOT`: ``tests.scenes`` and this checkout's mpmlab)."""
    for folder in reversed(folders):
        sys.path.insert(0, str(folder))


def log(*args: Any, err: bool = False) -> None:
    """A progress line, flushed (``err``: to stderr, which keeps stdout for the tables)."""
    print(*args, file=sys.stderr if err else sys.stdout, flush=True)


# ---- machine --------------------------------------------------------------------------------------
def load_average() -> str:
    """The 1, 5 and 15 minute load averages, ``"0.4 0.3 0.2"`` (recorded before and after a run)."""
    return " ".join(f"{x:.1f}" for x in os.getloadavg())


def machine_info(modules: Sequence[str] = BACKENDS, *, with_platform: bool = False, load: bool = False) -> dict:
    """CPU, cores, Python, the versions of ``modules`` (imported here) and NumPy; ``with_platform``
    adds ``platform`` (the OS), ``load`` the load average before the run (``load_before``)."""
    cpu = platform.processor() or platform.machine()
    try:
        cpu = next(l.split(":", 1)[1].strip() for l in open("/proc/cpuinfo") if l.startswith("model name"))
    except (OSError, StopIteration):
        pass
    info = {"cpu": cpu, "cores": len(os.sched_getaffinity(0)), "python": platform.python_version()}
    for name in modules:
        mod = importlib.import_module(name)
        info[name] = mod.config.version if name == "warp" else mod.__version__
    info["numpy"] = np.__version__
    if with_platform:
        info["platform"] = platform.platform()
    if load:
        info["load_before"] = load_average()
    return info


# ---- command line ---------------------------------------------------------------------------------
def parser(description: str, raw: bool = False) -> argparse.ArgumentParser:
    """An argument parser; ``raw`` keeps the description's line breaks (a docstring with usage lines)."""
    kw = {"formatter_class": argparse.RawDescriptionHelpFormatter} if raw else {}
    return argparse.ArgumentParser(description=description, **kw)


def add_quick(ap: argparse.ArgumentParser, help: str) -> None:
    ap.add_argument("--quick", action="store_true", help=help)


def add_backends(ap: argparse.ArgumentParser, default: str = ",".join(BACKENDS), *, as_list: bool = False) -> None:
    """``--backends``: a comma list (``jax,warp``; read it with :func:`csv`), or with ``as_list`` words
    (``--backends jax warp``)."""
    if as_list:
        ap.add_argument("--backends", nargs="+", default=list(BACKENDS), choices=list(BACKENDS))
    else:
        ap.add_argument("--backends", default=default)


def add_readme(ap: argparse.ArgumentParser, default: Path = README) -> None:
    ap.add_argument("--readme", default=str(default), help="'' to leave the README alone")


def csv(text: str) -> list[str]:
    """The items of a comma list (empty items dropped)."""
    return [s for s in text.split(",") if s]


# ---- results JSON ---------------------------------------------------------------------------------
def read_json(path: str | os.PathLike, default: Any = None) -> Any:
    """The parsed file, or ``default`` when it does not exist."""
    path = Path(path)
    return json.loads(path.read_text()) if path.exists() else default


def write_json(path: str | os.PathLike, obj: Any, *, indent: int = 1, default: Callable | None = None,
               newline: bool = False) -> Path:
    """Write ``obj`` as JSON (parent folders created; ``newline``: end the file with one)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(obj, indent=indent, default=default) + ("\n" if newline else ""))
    return path


def keep_parts(res: dict, previous: dict | None, parts: Iterable[str]) -> list[str]:
    """A partial run keeps the other parts of the previous results: copies each of ``parts`` that
    ``res`` lacks and ``previous`` has; returns the names copied."""
    if not previous:
        return []
    kept = [k for k in parts if k not in res and k in previous]
    for k in kept:
        res[k] = previous[k]
    return kept


def keep_rows(old: Iterable[dict], new: list[dict], keep: Callable[[dict], bool]) -> list[dict]:
    """A partial run keeps rows of an earlier run: those that ``keep`` accepts, then this run's rows."""
    return [r for r in old if keep(r)] + new


# ---- Markdown -------------------------------------------------------------------------------------
def md_row(cells: Iterable[Any]) -> str:
    return "| " + " | ".join(str(c) for c in cells) + " |"


def md_table(header: Sequence[Any], rows: Iterable[Iterable[Any]] = ()) -> list[str]:
    """The lines of a Markdown table: header, separator, one line per row (cells as given)."""
    return [md_row(header), "|" + "---|" * len(header), *(md_row(r) for r in rows)]


def write_readme_section(path: Path, name: str, title: str, body: str) -> None:
    """Replace the text between ``<!-- name:start -->`` and ``<!-- name:end -->`` in ``path`` (or append
    a ``## title`` section holding them)."""
    text = path.read_text() if path.exists() else "# Benchmarks\n"
    start, end = f"<!-- {name}:start -->", f"<!-- {name}:end -->"
    block = f"{start}\n{body}{end}"
    if start in text and end in text:
        text = text[: text.index(start)] + block + text[text.index(end) + len(end):]
    else:
        text = text.rstrip("\n") + f"\n\n## {title}\n\n{block}\n"
    path.write_text(text)


# ---- scenes ---------------------------------------------------------------------------------------
#: the throughput scenes (``throughput.py``, ``stage_profile.py``): mpm3d's n_grid per particle count,
#: 3D and 2D (the same particle counts), and the elastic cube's
N_GRID_3D = {"8k": 32, "65k": 64, "524k": 128}
N_GRID_2D = {"8k": 181, "65k": 512, "524k": 1448}
CUBE_N_GRID = {3: 64, 2: 512}


def throughput_scene(name: str, dim: int, n_grid: int, **kw):
    """``mpm3d``: Taichi mpm3d's fluid (``mpmlab.scenes.mpm3d.mpm3d_fluid``); ``cube``: the
    fixed-corotated elastic cube (``elastic_cube``); ``kw`` go to the builder (``law``, ...)."""
    from mpmlab.scenes.mpm3d import elastic_cube, mpm3d_fluid

    return (mpm3d_fluid if name == "mpm3d" else elastic_cube)(n_grid, dim, **kw)
