"""``mpmlab sweep-summary DIR``: every job of a multirun folder in one table and one plot.

    mpmlab sweep-summary multirun/2026-12-06/10-00-00                       # wall_time_s per job
    mpmlab sweep-summary DIR --metric particle_steps_per_second --out report/

Reads each job's ``summary.json`` (its numbers, its status, the overrides that made it), the
sweep's ``jobs.jsonl`` (how every job ended, also the ones that wrote no summary: refused, failed
before their first step) and its ``multirun.yaml`` (every job the sweep made, with its overrides, also
the ones that left nothing), finds the swept keys (the overrides whose value differs between jobs)
and writes, next to the jobs unless ``--out`` says otherwise:

* ``sweep_summary.csv``: one row per job: job, status, the swept keys, the metric, then every number
  and word of its summary (nested entries as ``a.b``), its directory and its error message;
* ``sweep_summary.md``: the same rows, cut to job, status, swept keys, metric and message;
* ``sweep_summary_<metric>.png``: the metric against the swept key with the most numeric values, one
  line per combination of the other swept keys; a job without a value (diverged, failed, never
  ended) is a red cross on the x axis.

A job with neither a summary nor a record is listed as ``no outcome``: still running, killed before
it could record anything (out of memory, SIGKILL at a time limit), or, without a folder, not started.
"""
from __future__ import annotations

import argparse
import csv
import io
import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

from ..core.errors import ConfigError
from ..tasks.common import SUMMARY

JOBS_FILE = "jobs.jsonl"   # every sweep job appends its outcome (mpmlab.cli)
DEFAULT_METRIC = "wall_time_s"   # every task writes it
NO_OUTCOME = "no outcome"
# summary entries that are not a job's results (the overrides are columns of their own)
_SKIPPED = {"overrides", "outputs"}


@dataclass
class Job:
    num: int | None
    dir: Path | None
    status: str
    overrides: dict[str, str] = field(default_factory=dict)   # key -> value, as Hydra gave them to the job
    values: dict[str, object] = field(default_factory=dict)   # the flattened summary.json
    message: str = ""


def read_jobs(sweep_dir: Path) -> list[dict]:
    """The records of ``<sweep_dir>/jobs.jsonl`` by job number; a requeued job's last word counts."""
    path = Path(sweep_dir) / JOBS_FILE
    if not path.is_file():
        return []
    jobs = {}
    for line in path.read_text().splitlines():
        try:
            entry = json.loads(line)
        except ValueError:
            continue
        jobs[entry.get("job")] = entry
    return [jobs[k] for k in sorted(jobs, key=lambda k: (k is None, k))]


def planned_overrides(sweep_dir: Path) -> list[list[str]]:
    """Every job's overrides as Hydra's basic sweeper made them from the sweep's ``multirun.yaml`` (job
    number = position): a job killed before it recorded anything, or never started, keeps its place
    and its swept values. Empty for other sweepers or an unreadable file."""
    try:
        from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
        from hydra.core.override_parser.overrides_parser import OverridesParser
        from omegaconf import OmegaConf

        hydra = OmegaConf.load(Path(sweep_dir) / "multirun.yaml").hydra
        if not str(hydra.sweeper.get("_target_", "")).endswith("BasicSweeper"):
            return []
        params = hydra.sweeper.get("params") or {}
        # what BasicSweeper.sweep does: the sweeper's params, then the command line's overrides
        args = [f"{k}={v}" for k, v in params.items()] + list(hydra.overrides.task)
        batches = BasicSweeper.split_arguments(OverridesParser.create().parse_overrides(args), None)
        return [list(job) for batch in batches for job in batch]
    except Exception:  # noqa: BLE001 - no plan: the jobs' own records still list them
        return []


def _parse_overrides(items) -> dict[str, str]:
    out = {}
    for item in items or ():
        key, sep, value = str(item).partition("=")
        if sep:
            out[key.lstrip("+~")] = value
    return out


def _flatten(summary: dict) -> dict[str, object]:
    """Scalars of a summary, nested dicts as ``a.b``; lists (per-axis drifts, law names) are left out."""
    out: dict[str, object] = {}

    def walk(prefix: str, node) -> None:
        for key, value in node.items():
            name = f"{prefix}{key}"
            if isinstance(value, dict):
                walk(name + ".", value)
            elif value is None or isinstance(value, (bool, int, float, str)):
                out[name] = value

    walk("", {k: v for k, v in summary.items() if k not in _SKIPPED})
    return out


def _read_summary(path: Path) -> dict | None:
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def gather(sweep_dir: str | Path) -> list[Job]:
    """Every job of a multirun folder: the ones ``multirun.yaml`` plans, the ones ``jobs.jsonl`` records
    and every sub-folder with a ``summary.json`` or named by a job number."""
    sweep_dir = Path(sweep_dir)
    if not sweep_dir.is_dir():
        raise ConfigError(f"sweep-summary: '{sweep_dir}' is not a folder; give the multirun folder of a sweep "
                          f"(hydra.sweep.dir, e.g. multirun/<date>/<time>).")
    records = {r.get("job"): r for r in read_jobs(sweep_dir)}
    planned = dict(enumerate(planned_overrides(sweep_dir)))
    dirs: dict[object, Path] = {}
    for num, record in records.items():
        if record.get("dir"):
            folder = Path(record["dir"])
            if not folder.is_dir() and (sweep_dir / folder.name).is_dir():
                folder = sweep_dir / folder.name   # the sweep folder was moved or copied since
            dirs[num] = folder
    known = {d.resolve() for d in dirs.values()}
    for sub in sorted(p for p in sweep_dir.iterdir() if p.is_dir() and not p.name.startswith(".")):
        if sub.resolve() in known or not ((sub / SUMMARY).is_file() or sub.name.isdigit()):
            continue   # recorded already, or not a job folder
        dirs.setdefault(int(sub.name) if sub.name.isdigit() else sub.name, sub)
    jobs = []
    for num in sorted(set(dirs) | set(records) | set(planned),
                      key=lambda k: (0, k, "") if isinstance(k, int) else (1, 0, str(k))):
        record, folder = records.get(num, {}), dirs.get(num)
        summary = (_read_summary(folder / SUMMARY) if folder is not None else None) or {}
        # the record is the job's last word (a refused rerun leaves the earlier run's summary in place)
        status = record.get("status") or summary.get("status") or NO_OUTCOME
        if status == NO_OUTCOME and folder is not None:
            message = f"no {SUMMARY} and no record in {JOBS_FILE}: still running, or killed (out of memory, SIGKILL)"
        elif status == NO_OUTCOME:
            message = "no folder: not started (still queued, or the sweep stopped before it)"
        else:
            message = record.get("message") or (summary.get("error") if status != "ok" else "") or ""
        overrides = _parse_overrides(summary.get("overrides") or record.get("overrides") or planned.get(num))
        jobs.append(Job(num if isinstance(num, int) else None, folder, str(status), overrides, _flatten(summary),
                        str(message)))
    if not jobs and (sweep_dir / SUMMARY).is_file():
        raise ConfigError(f"sweep-summary: '{sweep_dir}' is one run's folder (it holds {SUMMARY}); give the "
                          f"sweep's folder above it, '{sweep_dir.resolve().parent}'.")
    if not jobs:
        raise ConfigError(f"sweep-summary: no jobs in '{sweep_dir}' (no {JOBS_FILE}, no job folder with a "
                          f"{SUMMARY}); give the folder of a multirun (hydra.sweep.dir).")
    return jobs


def swept_keys(jobs: list[Job]) -> list[str]:
    """The override keys whose value is not the same for every job, in command-line order (a job whose
    overrides are unknown, killed before it recorded anything, does not count)."""
    known = [job for job in jobs if job.overrides]
    keys: list[str] = []
    for job in known:
        keys += [k for k in job.overrides if k not in keys]
    return [k for k in keys if len({job.overrides.get(k) for job in known}) > 1]


def _number(value) -> float | None:
    if isinstance(value, bool) or value is None:
        return None
    try:
        x = float(value)
    except (TypeError, ValueError):
        return None
    return x if math.isfinite(x) else None


def check_metric(jobs: list[Job], metric: str) -> None:
    if any(_number(job.values.get(metric)) is not None for job in jobs):
        return
    # top-level entries first: the throughput and timings, before the containment details
    numeric = sorted({k for job in jobs for k, v in job.values.items() if _number(v) is not None},
                     key=lambda k: (k.count("."), k))
    if not numeric:
        raise ConfigError(f"sweep-summary: no job has a number to plot (no job wrote a {SUMMARY}: "
                          f"{', '.join(sorted({j.status for j in jobs}))}).")
    what = "is not a number in any job's" if any(metric in job.values for job in jobs) else "is in no job's"
    shown = ", ".join(numeric[:20]) + (", ..." if len(numeric) > 20 else "")
    raise ConfigError(f"sweep-summary: metric '{metric}' {what} {SUMMARY}; choose one with --metric: {shown}.")


def _columns(jobs: list[Job], keys: list[str], metric: str) -> list[str]:
    rest: list[str] = []
    for job in jobs:
        rest += [k for k in job.values if k not in rest and k not in ("status", "error", metric)]
    return ["job", "status", *keys, metric, *rest, "dir", "message"]


def _row(job: Job, keys: list[str], metric: str, columns: list[str]) -> dict[str, object]:
    row = {"job": "" if job.num is None else job.num, "status": job.status,
           "dir": "" if job.dir is None else str(job.dir), "message": job.message}
    row.update({k: job.overrides.get(k, "") for k in keys})
    row.update({k: job.values.get(k, "") for k in columns if k not in row})
    return row


def to_csv(jobs: list[Job], keys: list[str], metric: str) -> str:
    columns = _columns(jobs, keys, metric)
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=columns, lineterminator="\n")
    writer.writeheader()
    for job in jobs:
        writer.writerow({k: ("" if v is None else v) for k, v in _row(job, keys, metric, columns).items()})
    return buf.getvalue()


def _cell(value) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    text = "" if value is None else str(value)
    text = text if len(text) <= 120 else text[:117] + "..."
    return text.replace("|", "\\|").replace("\n", " ")


def tally(jobs: list[Job]) -> str:
    counts: dict[str, int] = {}
    for job in jobs:
        counts[job.status] = counts.get(job.status, 0) + 1
    return ", ".join(f"{n} {s}" for s, n in sorted(counts.items()))


def to_markdown(jobs: list[Job], keys: list[str], metric: str, sweep_dir: Path) -> str:
    columns = ["job", "status", *keys, metric] + (["message"] if any(job.message for job in jobs) else [])
    lines = [f"Sweep `{sweep_dir}`: {len(jobs)} jobs ({tally(jobs)}); swept: {', '.join(keys) or 'nothing'}.", "",
             "| " + " | ".join(columns) + " |", "|" + "|".join("---" for _ in columns) + "|"]
    for job in jobs:
        row = _row(job, keys, metric, columns)
        lines.append("| " + " | ".join(_cell(row.get(c, "")) for c in columns) + " |")
    return "\n".join(lines) + "\n"


def _x_key(jobs: list[Job], keys: list[str]) -> tuple[str | None, bool]:
    """The swept key on the x axis: the one with the most distinct values, numeric keys first."""
    def numeric(k):
        return all(_number(job.overrides[k]) is not None for job in jobs if k in job.overrides)
    if not keys:
        return None, True
    best = max(keys, key=lambda k: (numeric(k), len({job.overrides.get(k) for job in jobs})))
    return best, numeric(best)


def series(jobs: list[Job], keys: list[str], metric: str) -> tuple[str, dict[str, list[tuple]], list[tuple]]:
    """(x label, {line label: [(x, y, job), ...]}, [(x, job) of the jobs without a value]): what the plot
    draws. x is the swept key's value (a float when every job's is a number, else the text); with no
    swept key, the job number."""
    xkey, is_num = _x_key(jobs, keys)
    lines: dict[str, list[tuple]] = {}
    missing: list[tuple] = []
    for job in jobs:
        if xkey is None:
            x = job.num
        else:
            raw = job.overrides.get(xkey, "")
            x = _number(raw) if is_num else raw
        label = ", ".join(f"{k}={job.overrides.get(k, '')}" for k in keys if k != xkey) or metric
        y = _number(job.values.get(metric))
        if y is None:
            missing.append((x, job))
        else:
            lines.setdefault(label, []).append((x, y, job))
    for points in lines.values():
        points.sort(key=lambda p: (p[0] is None, p[0]) if is_num else 0)
    return (xkey or "job"), lines, missing


def plot(jobs: list[Job], keys: list[str], metric: str, path: Path, title: str) -> dict[str, list[tuple]]:
    """The metric against the swept keys as a PNG (Agg, written atomically); returns the lines drawn."""
    from matplotlib.figure import Figure  # no pyplot: no GUI backend, no global state

    from .files import write_atomically

    xlabel, lines, missing = series(jobs, keys, metric)
    # a job without the x key's override (it recorded nothing) has no place on the axis; the title counts it
    lines = {k: [p for p in pts if p[0] is not None] for k, pts in lines.items()}
    missing = [(x, job) for x, job in missing if x is not None]
    categorical = any(isinstance(p[0], str) for pts in lines.values() for p in pts) or any(
        isinstance(x, str) for x, _ in missing)
    if categorical:   # text values (backend=jax,warp) at positions 0..n-1, in the order the jobs ran
        order: list[str] = []
        for x in [p[0] for pts in lines.values() for p in pts] + [x for x, _ in missing]:
            if x not in order:
                order.append(x)
        pos = {x: i for i, x in enumerate(order)}
    fig = Figure(figsize=(7.5, 4.5), dpi=110)
    ax = fig.subplots()
    for label, pts in lines.items():
        xs = [pos[p[0]] if categorical else p[0] for p in pts]
        ax.plot(xs, [p[1] for p in pts], "o-", ms=4, lw=1.3, label=label)
    for x, job in missing:
        # on the x axis, below the data: a job that gave no value is seen, not silently dropped
        ax.plot(pos[x] if categorical else x, 0.0, "x", color="red", ms=8, mew=2, clip_on=False,
                transform=ax.get_xaxis_transform(), label=f"no value ({job.status})")
    if categorical:
        ax.set_xticks(range(len(order)), order)
    xs = [p[0] for pts in lines.values() for p in pts if p[0] is not None and not categorical]
    if xs and min(xs) > 0 and max(xs) / min(xs) >= 100:
        ax.set_xscale("log")
    ys = [p[1] for pts in lines.values() for p in pts]
    if ys and min(ys) > 0 and max(ys) / min(ys) >= 100:
        ax.set_yscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(metric)
    ax.set_title(title, fontsize=9)
    ax.grid(alpha=0.3)
    handles, labels = ax.get_legend_handles_labels()
    unique = dict(zip(labels, handles))   # one legend entry per kind of missing job
    if len(unique) > 1 or missing:
        ax.legend(unique.values(), unique.keys(), fontsize=7 if len(unique) > 8 else 8)
    fig.tight_layout()
    write_atomically(path, lambda tmp: fig.savefig(tmp, format="png", metadata={"Title": title}), overwrite=True)
    return lines


def summarize(sweep_dir: str | Path, metric: str = DEFAULT_METRIC, out: str | Path | None = None) -> dict:
    """Write the table (CSV, Markdown) and the plot of ``metric`` for the sweep in ``sweep_dir``;
    returns the jobs, the swept keys and the paths ("csv", "markdown", "plot"). Bad input raises
    :class:`ConfigError`."""
    from .files import write_atomically

    sweep_dir = Path(sweep_dir)
    jobs = gather(sweep_dir)
    check_metric(jobs, metric)
    keys = swept_keys(jobs)
    out = Path(out) if out is not None else sweep_dir
    if out.exists() and not out.is_dir():
        raise ConfigError(f"sweep-summary: --out '{out}' is a file; give a folder.")
    out.mkdir(parents=True, exist_ok=True)
    # derived files: a later call (more jobs ended) replaces them
    paths = {"csv": out / "sweep_summary.csv", "markdown": out / "sweep_summary.md",
             "plot": out / f"sweep_summary_{re.sub(r'[^A-Za-z0-9_.-]+', '_', metric)}.png"}
    for key, text in (("csv", to_csv(jobs, keys, metric)), ("markdown", to_markdown(jobs, keys, metric, sweep_dir))):
        write_atomically(paths[key], lambda tmp, text=text: Path(tmp).write_text(text), overwrite=True)
    plot(jobs, keys, metric, paths["plot"], f"{metric}: {sweep_dir.name or sweep_dir} ({len(jobs)} jobs: {tally(jobs)})")
    return {"jobs": jobs, "swept": keys, **paths}


class _Parser(argparse.ArgumentParser):
    def error(self, message):   # one line and exit code 2, like every other bad input of the CLI
        raise ConfigError(f"sweep-summary: {message}; usage: {self.format_usage().strip().removeprefix('usage: ')}")


def cli(args: list[str]) -> int:
    """``mpmlab sweep-summary DIR [--metric KEY] [--out DIR]``; prints where the files went."""
    parser = _Parser(prog="mpmlab sweep-summary",
                     description="Every job of a multirun folder in one table (CSV, Markdown) and one plot.")
    parser.add_argument("sweep_dir", metavar="DIR", help="the multirun folder (hydra.sweep.dir)")
    parser.add_argument("--metric", default=DEFAULT_METRIC, metavar="KEY",
                        help=f"summary.json entry to tabulate and plot (default {DEFAULT_METRIC}; nested ones as a.b)")
    parser.add_argument("--out", default=None, metavar="FOLDER", help="folder for the files (default: DIR)")
    ns = parser.parse_args(args)
    res = summarize(ns.sweep_dir, ns.metric, ns.out)
    print(f"mpmlab: sweep {ns.sweep_dir}: {len(res['jobs'])} jobs ({tally(res['jobs'])}); swept: "
          f"{', '.join(res['swept']) or 'nothing'} -> {res['csv']}, {res['markdown']}, {res['plot']}")
    return 0
