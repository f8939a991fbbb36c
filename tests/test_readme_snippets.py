"""Every fenced ```python block of README.md runs (issue #13), so the README cannot drift from the code.

Each block is one test (its id: the README heading it stands under) and runs on its own, the way a
reader pastes it: a fresh namespace, a temporary working directory, nothing from the blocks before
it. The code is the README's, with only the size substitutions of ``SHRINK`` applied (fewer steps;
each substitution must still match the README, see ``test_every_shrink_still_applies``). It is
compiled under the file name ``README.md`` with the block's own line numbers, so a traceback points
at the README line that failed, and a failing block says which block it is: a block that cannot run
as written (a fragment, a stale name) fails, it is never skipped.

``KNOWN_BROKEN`` lists the blocks that do not run as written today, each with the one exception it
raises and why; they are ``xfail(strict=True)``, so fixing the README turns them into failures here
until the entry is removed. ``tests/test_readme.py`` runs the blocks at full size, one after another
in one namespace (twice, warnings as errors).
"""
from __future__ import annotations

import re
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[1] / "README.md"

#: (pattern, replacement, why): applied to every block before it runs
SHRINK = [
    (r"steps=400, every=20", "steps=40, every=20", "Python API: 40 steps instead of 400 (2 frames kept)"),
    (r"steps=\[100, 200\]", "steps=[10, 20]", "gradients: observe after 10 and 20 steps instead of 100 and 200"),
    (r"segment=50", "segment=10", "gradients: recomputed segments of 10 steps (of the 20 observed)"),
]

#: block id -> (the exception it raises as written, why); fix the README, then remove the entry
KNOWN_BROKEN: dict = {}


def _slug(text: str) -> str:
    return re.sub(r"[^a-z0-9]+", "-", text.lower()).strip("-") or "readme"


def readme_blocks(text: str | None = None) -> list[tuple[str, int, str]]:
    """``(id, first code line (1-based), code)`` of every ```python block, in README order."""
    lines = (README.read_text() if text is None else text).splitlines()
    out, heading, seen, i = [], "readme", {}, 0
    while i < len(lines):
        line = lines[i]
        if line.startswith("#"):
            heading = _slug(line.lstrip("#"))
        if line.strip().startswith("```python"):
            start, j = i + 1, i + 1
            while j < len(lines) and not lines[j].strip().startswith("```"):
                j += 1
            if j == len(lines):
                raise AssertionError(f"README.md line {i + 1}: a ```python block is never closed")
            seen[heading] = seen.get(heading, 0) + 1
            bid = heading if seen[heading] == 1 else f"{heading}-{seen[heading]}"
            out.append((bid, start + 1, "\n".join(lines[start:j]) + "\n"))
            i = j
        i += 1
    return out


def shrink(code: str) -> str:
    for pattern, repl, _ in SHRINK:
        code = re.sub(pattern, repl, code)
    return code


BLOCKS = readme_blocks()


def _param(bid: str, line: int, code: str):
    marks = []
    if bid in KNOWN_BROKEN:
        exc, why = KNOWN_BROKEN[bid]
        marks.append(pytest.mark.xfail(raises=exc, strict=True, reason=f"README.md line {line}: {why}"))
    return pytest.param(bid, line, code, id=bid, marks=marks)


def test_the_readme_has_python_blocks():
    assert BLOCKS, "README.md has no ```python block (did the fence style change?)"
    assert set(KNOWN_BROKEN) <= {b for b, _, _ in BLOCKS}, "KNOWN_BROKEN names a block the README no longer has"


def test_every_shrink_still_applies():
    """A substitution that matches nothing means the README changed: update SHRINK with it."""
    code = "".join(c for _, _, c in BLOCKS)
    stale = [why for pattern, _, why in SHRINK if not re.search(pattern, code)]
    assert not stale, f"SHRINK entries that no README block matches any more: {stale}"


@pytest.mark.parametrize("bid, line, code", [_param(*b) for b in BLOCKS])
def test_readme_block_runs(bid, line, code, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    try:
        # README line numbers in tracebacks: pad the block to where it stands in README.md
        compiled = compile("\n" * (line - 1) + shrink(code), str(README), "exec")
        exec(compiled, {"__name__": f"readme_{bid.replace('-', '_')}"})
    except BaseException as exc:
        exc.add_note(f"README.md python block '{bid}' (from line {line}) does not run as written "
                     f"(sizes shrunk by tests/test_readme_snippets.py SHRINK).")
        raise
