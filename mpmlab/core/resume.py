"""What a resumed training must have in common with the run that wrote its checkpoint.

A checkpoint holds the optimiser's state, not the data or the options that shaped its curve. Rerunning
the same command continues a training (NCLaw's ``nclaw_train``, the ROM's ``rom_train``), so a changed
dataset (a scene edited and its trajectory remade) or a changed option (a learning rate, the teacher
schedule) would otherwise continue it silently, and its summary would describe a curve no single
configuration produced. Each training records an *identity* (a dict of JSON values, with
:func:`array_digest` for the data) beside its checkpoint and checks it on resume
(:func:`check_identity`: one line naming the first difference). A checkpoint that records none (one
written before this check existed) resumes unchecked.
"""
from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

import numpy as np

from .errors import ConfigError


def array_digest(*arrays) -> str:
    """SHA-256 of the arrays' values as contiguous float64 (``None`` hashes as a marker, so a missing field
    differs from an empty one). Shapes are not hashed: the digests ``rom_train`` checkpoints already hold
    were made this way, and a training checks its data's shapes itself."""
    h = hashlib.sha256()
    for a in arrays:
        h.update(b"-" if a is None else np.ascontiguousarray(a, np.float64).tobytes())
    return h.hexdigest()


def _show(v: Any) -> str:
    return f"{v[:12]}..." if isinstance(v, str) and len(v) == 64 else repr(v)   # a digest: its first 12 digits


def check_identity(who: str, checkpoint: str | Path, saved: dict | None, current: dict) -> None:
    """Raise ``ConfigError`` when ``saved`` (what the checkpoint's run recorded; ``None``: nothing) and
    ``current`` differ in a key either has."""
    if saved is None:
        return
    current = _jsonable(current)
    for key in sorted(set(saved) | set(current)):
        old, new = saved.get(key), current.get(key)
        if old != new:
            raise ConfigError(f"{who}: the checkpoint {checkpoint} was made with {key} = {_show(old)}, this run has "
                              f"{_show(new)}; resume with the same {key}, or use another run directory "
                              f"(or task.resume=false to start over).")


def identity_path(checkpoint: str | Path) -> Path:
    """The identity file beside a checkpoint: ``<checkpoint>.identity.json``."""
    checkpoint = Path(checkpoint)
    return checkpoint.with_name(checkpoint.name + ".identity.json")


def read_identity(checkpoint: str | Path) -> dict | None:
    p = identity_path(checkpoint)
    return json.loads(p.read_text()) if p.exists() else None


def write_identity(checkpoint: str | Path, identity: dict) -> None:
    """Atomically (a killed run leaves the old file or the new one, never half of one)."""
    from ..io.files import write_atomically

    text = json.dumps(_jsonable(identity), indent=1, sort_keys=True)
    write_atomically(identity_path(checkpoint), lambda tmp: Path(tmp).write_text(text), overwrite=True)


def _jsonable(v):
    """The identity as JSON would read it back (tuples as lists, numpy scalars as Python ones), so that a
    freshly built identity compares equal to a stored one."""
    return json.loads(json.dumps(v, default=lambda o: o.item() if hasattr(o, "item") else str(o)))
