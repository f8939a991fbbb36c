"""Pieces every benchmark script uses: the machine description and README section updates.

Imported by the scripts in this folder (run as ``python benchmarks/<name>.py``, so this folder is on
``sys.path``). No heavy imports at module level: ``gradients.py`` keeps JAX/Warp/torch out of its
parent process on purpose (a child inherits the parent's peak RSS).
"""
from __future__ import annotations

import importlib
import os
import platform
from pathlib import Path

import numpy as np


def machine_info(modules=("jax", "warp")) -> dict:
    """CPU, cores, Python, the versions of ``modules`` (imported here) and the load before the run."""
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
    return info


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
