"""The README tells the truth: its Python snippets run (twice: a rerun must not trip over the files of
the first) without a warning of their own, and its quoted numbers come from the results file of
``benchmarks/readme_numbers.py`` (issue #12 item 15)."""
from __future__ import annotations

import json
import re
import warnings
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()
BLOCKS = re.findall(r"```python\n(.*?)```", README, re.S)


@pytest.mark.slow
def test_python_snippets_run_twice_without_warnings(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    api, gradients = BLOCKS[0], BLOCKS[1]
    assert "write_trajectory(" in api and "jax.grad" in gradients
    ns: dict = {}
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)      # e.g. observe()'s dt: auto note
        exec(compile(api, "README.md: Python API", "exec"), ns)
        exec(compile(api, "README.md: Python API (again)", "exec"), ns)
        exec(compile(gradients, "README.md: gradients", "exec"), ns)
    assert (tmp_path / "box.h5").is_file() and (tmp_path / "box.rrd").is_file()
    assert ns["c"]["v"].grad is not None


def test_quoted_numbers_are_the_measured_ones():
    import importlib.util

    spec = importlib.util.spec_from_file_location("readme_numbers", ROOT / "benchmarks" / "readme_numbers.py")
    rn = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(rn)
    results = json.loads(rn.RESULTS.read_text())
    assert rn.render(README, results) == README, "README numbers are stale: benchmarks/readme_numbers.py --update"
    names = {m["name"] for m in rn.SPAN.finditer(README)}
    assert names == {"default-run", "default-line"}


def test_quoted_output_line_has_the_cli_format():
    """The line the README shows is the format simulate prints (its f-string, checked on a real run in
    test_cli.test_run_writes_outputs_and_one_line_summary)."""
    line = re.search(r"<!-- readme-numbers:default-line -->\n```\n(.*?)\n```", README, re.S)[1]
    fmt = (r"mpmlab: nclaw_jelly jax/mls/fp32: 1000 particles x 1000 steps in \d+\.\d\d s "
           r"\(compile \d+\.\d\d s\), [\d.e+]+ particle-steps/s -> outputs/<date>/<time>")
    assert re.fullmatch(fmt, line), line
    src = (ROOT / "mpmlab" / "tasks" / "simulate.py").read_text()
    # the steps run (a run stopped when its deposit settled runs fewer than planned: task.runout)
    assert "particles x {summary['steps_done']} " in src and 'f"steps in "' in src
    assert "particle-steps/s -> {out}" in src
