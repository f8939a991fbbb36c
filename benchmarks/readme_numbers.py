"""The numbers the README quotes about the default run, measured, not typed.

    python benchmarks/readme_numbers.py            # measure (3 runs of `mpmlab`), write the results file
    python benchmarks/readme_numbers.py --update   # ... and rewrite the README's marked spans
    python benchmarks/readme_numbers.py --check    # exit 1 when the README differs from the results file

Each run is the README's own command, `mpmlab`, in a fresh run directory, timed from process start to
exit (start-up, JIT compilation and all outputs included). The results file,
``benchmarks/results/readme_numbers.json``, records the machine, the commit and every run; the README
spans between ``<!-- readme-numbers:NAME -->`` and ``<!-- /readme-numbers -->`` are rendered from it
(``tests/test_readme.py`` checks they agree, and that the quoted output line has the CLI's format).
"""
from __future__ import annotations

import json
import os
import platform
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _harness as H  # noqa: E402

ROOT = H.ROOT
README = ROOT / "README.md"
RESULTS = H.RESULTS / "readme_numbers.json"
SPAN = re.compile(r"<!-- readme-numbers:(?P<name>[\w-]+) -->(?P<body>.*?)<!-- /readme-numbers -->", re.S)


def measure(runs: int = 3) -> dict:
    exe = [shutil.which("mpmlab")] if shutil.which("mpmlab") else [sys.executable, "-m", "mpmlab"]
    rows = []
    for k in range(runs):
        with tempfile.TemporaryDirectory() as d:
            t0 = time.perf_counter()
            p = subprocess.run(exe + [f"hydra.run.dir={d}/run"], cwd=d, capture_output=True, text=True)
            wall = time.perf_counter() - t0
        if p.returncode:
            raise SystemExit(f"readme_numbers: `mpmlab` failed ({p.returncode}): {p.stderr.strip()[-500:]}")
        line = p.stdout.strip().splitlines()[-1]
        rows.append({"wall_s": wall, "line": line})
        print(f"run {k + 1}: {wall:.2f} s  {line}", flush=True)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout.strip()
    median = statistics.median(r["wall_s"] for r in rows)
    typical = min(rows, key=lambda r: abs(r["wall_s"] - median))
    return {"command": "mpmlab", "runs": rows, "median_wall_s": median, "cores": os.cpu_count(),
            "machine": platform.machine(), "commit": commit, "date": time.strftime("%Y-%m-%d"),
            "line": re.sub(r"-> \S+$", "-> outputs/<date>/<time>", typical["line"])}


def spans(results: dict) -> dict[str, str]:
    """What each README span says, from the results."""
    return {"default-run": f"about {results['median_wall_s']:.0f} s on a {results['cores']}-core CPU "
                           f"(measured by `benchmarks/readme_numbers.py`, {results['date']})",
            "default-line": f"\n```\n{results['line']}\n```\n"}


def render(text: str, results: dict) -> str:
    want = spans(results)
    return SPAN.sub(lambda m: f"<!-- readme-numbers:{m['name']} -->{want.get(m['name'], m['body'])}"
                              f"<!-- /readme-numbers -->", text)


def main() -> int:
    ap = H.parser(__doc__, raw=True)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--update", action="store_true", help="measure, then rewrite README.md's spans")
    ap.add_argument("--check", action="store_true", help="compare README.md with the results file only")
    a = ap.parse_args()
    if a.check:
        results = json.loads(RESULTS.read_text())
        ok = render(README.read_text(), results) == README.read_text()
        print("README numbers match" if ok else "README numbers are stale: run benchmarks/readme_numbers.py --update")
        return 0 if ok else 1
    results = measure(a.runs)
    H.write_json(RESULTS, results, indent=2, newline=True)
    print(f"median {results['median_wall_s']:.2f} s -> {RESULTS}")
    if a.update:
        README.write_text(render(README.read_text(), results))
        print(f"updated {README}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
