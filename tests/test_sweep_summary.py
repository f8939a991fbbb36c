"""``mpmlab sweep-summary DIR``: a multirun folder's jobs in one table (CSV, Markdown) and one plot.

The folder is made here as a sweep leaves it (``multirun.yaml``, ``<job>/summary.json``, the sweep's
``jobs.jsonl``), with every way a job can end: ok, diverged (no throughput), refused before writing a
summary (a record only), requeued (two records: the last counts), killed (a folder, nothing else),
never started (nothing at all). Real sweeps' folders are read in tests/test_scaleout_*.py.
"""
from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest

from mpmlab.cli import EXIT_CONFIG, main
from mpmlab.io import sweep_summary

from .test_cli import error_lines

E_VALUES = ("100", "1000", "10000", "100000")   # as Hydra writes them back
MULTIRUN_YAML = """hydra:
  sweeper:
    _target_: hydra._internal.core_plugins.basic_sweeper.BasicSweeper
    max_batch_size: null
    params: null
  overrides:
    task:
    - backend=jax,warp
    - material.params.E=100,1000,10000,100000
    - steps=20
"""


def _job(sweep: Path, num: int, backend: str, E: str, status: str = "ok", rate: float | None = None) -> dict:
    overrides = [f"backend={backend}", f"material.params.E={E}", "steps=20"]
    run = sweep / str(num)
    run.mkdir(parents=True)
    summary = {"task": "simulate", "status": status, "backend": backend, "steps": 20, "particles": 250,
               "wall_time_s": 1.0 + num, "particle_steps_per_second": rate, "last_frame": {"step": 20, "time": 0.004},
               "momentum_drift": [0.0, 0.1], "outputs": {"summary": "summary.json"}, "overrides": overrides}
    if status != "ok":
        summary["error"] = "simulation diverged at step 4: J < 0 | see the log"
    (run / "summary.json").write_text(json.dumps(summary))
    return {"job": num, "overrides": overrides, "dir": str(run), "status": status,
            "exit_code": 0 if status == "ok" else 3, **({"message": summary["error"]} if status != "ok" else {})}


@pytest.fixture
def sweep(tmp_path) -> Path:
    """Jobs 0-7: backend (jax, warp) x E (100 ... 100000). 3 refused before its summary, 4 requeued then ok,
    5 diverged, 6 killed (its folder only), 7 never started (nothing)."""
    sweep = tmp_path / "multirun"
    records = [_job(sweep, num, "jax", E, rate=1e5 * (num + 1)) for num, E in enumerate(E_VALUES[:3])]
    records.append({"job": 3, "overrides": ["backend=jax", "material.params.E=100000", "steps=20"],
                    "dir": str(sweep / "3"), "status": "refused", "exit_code": 2, "message": "CFL number 3 > 0.5"})
    requeued = _job(sweep, 4, "warp", "100", rate=5e5)
    records += [{**requeued, "status": "interrupted", "exit_code": 140, "message": "stopped by SIGUSR2"}, requeued]
    records.append(_job(sweep, 5, "warp", "1000", "diverged"))
    (sweep / "6").mkdir()
    (sweep / ".submitit").mkdir()          # launcher folders are not jobs
    (sweep / "jobs.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records) + "not json\n")
    (sweep / "multirun.yaml").write_text(MULTIRUN_YAML)
    return sweep


def test_every_job_is_one_row_with_its_status_and_swept_keys(sweep, capsys):
    assert main(["sweep-summary", str(sweep), "--metric", "particle_steps_per_second"]) == 0
    out = capsys.readouterr().out.strip()
    assert out.startswith(f"mpmlab: sweep {sweep}: 8 jobs (1 diverged, 2 no outcome, 4 ok, 1 refused); "
                          f"swept: backend, material.params.E -> {sweep / 'sweep_summary.csv'}, "), out
    rows = list(csv.DictReader((sweep / "sweep_summary.csv").open()))
    head = list(rows[0])
    assert head[:5] == ["job", "status", "backend", "material.params.E", "particle_steps_per_second"]
    assert head[-2:] == ["dir", "message"] and "last_frame.step" in head   # nested entries as a.b
    assert "momentum_drift" not in head and "outputs.summary" not in head and "steps" in head  # steps: not swept
    assert [(r["job"], r["status"], r["backend"], r["material.params.E"]) for r in rows] == [
        ("0", "ok", "jax", "100"), ("1", "ok", "jax", "1000"), ("2", "ok", "jax", "10000"),
        ("3", "refused", "jax", "100000"), ("4", "ok", "warp", "100"),   # 4 requeued: its last record counts
        ("5", "diverged", "warp", "1000"),
        ("6", "no outcome", "warp", "10000"), ("7", "no outcome", "warp", "100000")]   # overrides: multirun.yaml's plan   # overrides: multirun.yaml's plan
    assert [r["particle_steps_per_second"] for r in rows] == ["100000.0", "200000.0", "300000.0", "", "500000.0", "",
                                                              "", ""]
    assert rows[3]["message"] == "CFL number 3 > 0.5" and rows[5]["message"].startswith("simulation diverged")
    assert "killed" in rows[6]["message"] and rows[6]["dir"] == str(sweep / "6")
    assert "not started" in rows[7]["message"] and rows[7]["dir"] == ""


def test_the_markdown_table(sweep):
    res = sweep_summary.summarize(sweep, "particle_steps_per_second")
    md = res["markdown"].read_text().splitlines()
    assert md[0] == f"Sweep `{sweep}`: 8 jobs (1 diverged, 2 no outcome, 4 ok, 1 refused); swept: backend, material.params.E."
    assert md[2] == "| job | status | backend | material.params.E | particle_steps_per_second | message |"
    assert md[4] == "| 0 | ok | jax | 100 | 1e+05 |  |"
    assert md[9] == "| 5 | diverged | warp | 1000 |  | simulation diverged at step 4: J < 0 \\| see the log |"
    assert len(md) == 4 + 8


def test_the_plot_has_a_line_per_other_key_and_marks_jobs_without_a_value(sweep):
    jobs = sweep_summary.gather(sweep)
    keys = sweep_summary.swept_keys(jobs)
    xlabel, lines, missing = sweep_summary.series(jobs, keys, "particle_steps_per_second")
    assert xlabel == "material.params.E"           # the numeric key with the most values is the x axis
    assert {k: [(x, y) for x, y, _ in pts] for k, pts in lines.items()} == {
        "backend=jax": [(1e2, 1e5), (1e3, 2e5), (1e4, 3e5)], "backend=warp": [(1e2, 5e5)]}
    assert [(x, j.status) for x, j in missing] == [(1e5, "refused"), (1e3, "diverged"), (1e4, "no outcome"),
                                                   (1e5, "no outcome")]
    png = sweep_summary.summarize(sweep, "particle_steps_per_second")["plot"]
    assert png == sweep / "sweep_summary_particle_steps_per_second.png"
    from PIL import Image

    assert Image.open(png).text["Title"].startswith("particle_steps_per_second: multirun (8 jobs: ")


def test_text_values_are_categories_and_a_rerun_replaces_the_files(tmp_path, capsys):
    sweep = tmp_path / "sweep"
    (sweep / "jobs.jsonl").parent.mkdir()
    records = [_job(sweep, i, b, "1000", rate=r) for i, (b, r) in enumerate([("jax", 5.0), ("warp", 7.0)])]
    (sweep / "jobs.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))
    jobs = sweep_summary.gather(sweep)
    xlabel, lines, _ = sweep_summary.series(jobs, sweep_summary.swept_keys(jobs), "wall_time_s")
    assert xlabel == "backend" and [(x, y) for x, y, _ in lines["wall_time_s"]] == [("jax", 1.0), ("warp", 2.0)]
    out = tmp_path / "report"
    for _ in range(2):   # the files are derived: a second call (more jobs ended since) replaces them
        assert main(["sweep-summary", str(sweep), "--out", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["sweep_summary.csv", "sweep_summary.md",
                                                     "sweep_summary_wall_time_s.png"]
    assert not (sweep / "sweep_summary.csv").exists()
    assert "swept: backend" in capsys.readouterr().out
    assert (out / "sweep_summary.md").read_text().splitlines()[2] == "| job | status | backend | wall_time_s |"  # no messages


def test_hydra_never_sees_the_command(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert main(["sweep-summary", "--help"]) == 0
    assert "usage: mpmlab sweep-summary [-h] [--metric KEY] [--out FOLDER] DIR" in capsys.readouterr().out
    assert list(tmp_path.iterdir()) == []   # no outputs/ or multirun/ folder


BAD = [
    ([], "the following arguments are required: DIR"),
    (["{sweep}", "--bogus"], "unrecognized arguments: --bogus"),
    (["{tmp}/missing"], "is not a folder"),
    (["{tmp}/a_file"], "is not a folder"),
    (["{tmp}/empty"], "no jobs in"),
    (["{sweep}/0"], "is one run's folder (it holds summary.json); give the sweep's folder above it"),
    (["{sweep}", "--metric", "rate"], "metric 'rate' is in no job's summary.json; choose one with --metric: "
                                      "particle_steps_per_second, particles, steps, wall_time_s, last_frame.step"),
    (["{sweep}", "--metric", "backend"], "metric 'backend' is not a number in any job's summary.json"),
    (["{sweep}", "--out", "{tmp}/a_file"], "--out '"),
]


@pytest.mark.parametrize("args, needle", BAD, ids=[" ".join(a) or "no args" for a, _ in BAD])
def test_bad_input_one_line_exit_2(sweep, tmp_path, capsys, args, needle):
    (tmp_path / "a_file").write_text("not a folder")
    (tmp_path / "empty").mkdir()
    code = main(["sweep-summary", *[a.format(tmp=tmp_path, sweep=sweep) for a in args]])
    lines = error_lines(capsys.readouterr().err)
    assert code == EXIT_CONFIG
    assert len(lines) == 1 and lines[0].startswith("mpmlab: error: sweep-summary: ") and needle in lines[0], lines
    assert not (sweep / "sweep_summary.csv").exists()
