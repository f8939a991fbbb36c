"""What a resumed training must have in common with the run that wrote its checkpoint.

A checkpoint holds the optimiser's state, not the data or the options that shaped its curve. Rerunning
the same command continues a training (NCLaw's ``nclaw_train``, the ROM's ``rom_train``), so a changed
dataset (a scene edited and its trajectory remade) or a changed option (a learning rate, the teacher
schedule) would otherwise continue it silently, and its summary would describe a curve no single
configuration produced. Each training records an *identity* (a dict of JSON values, with
:func:`array_digest` for the data) beside its checkpoint and checks it on resume
(:func:`check_identity`: one line naming the first difference). A checkpoint that records none (one
written before this check existed) resumes unchecked.

Data made again on another machine differs in its last bits: the same scene run by the same code on
another CPU (its compiler's vector width and fused multiply-adds, its libm) gives another digest, so a
training that spans sessions on different machines could never resume (measured: NCLaw's WATER dataset
remade on an AMD EPYC after an Intel Xeon had another digest, and the first epoch's loss agreed to 5e-8).
An identity may therefore hold, beside a digest ``key``, a ``key + "_fingerprint"`` (:func:`array_fingerprint`:
per-frame means and RMS values). Where the digests differ and both identities have fingerprints that agree
within ``FINGERPRINT_RTOL`` of each array's scale, the resume goes on and says so (the data differ at
round-off); a real change of the data (another scene, material or sampling) moves them far more.
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


#: the identity key that carries, from resume to resume, the round-off differences each resume accepted
NOTES = "resume_notes"
#: how far two fingerprints (:func:`array_fingerprint`) may differ, relative to each array's RMS, for their
#: data to count as the same up to round-off
FINGERPRINT_RTOL = 1e-4
#: frames (first axis) a fingerprint summarises, evenly spaced from the first to the last
FINGERPRINT_FRAMES = 11


def array_fingerprint(*arrays) -> list:
    """A small numeric summary of the arrays that round-off hardly moves: per array, its RMS, then for
    ``FINGERPRINT_FRAMES`` frames (evenly spaced along the first axis) the mean of each component over the
    frame and the frame's RMS (``None`` for a missing array). Compare with :func:`fingerprint_distance`."""
    out = []
    for a in arrays:
        if a is None:
            out.append(None)
            continue
        a = np.asarray(a, np.float64)
        a2 = a.reshape(a.shape[0], -1, int(np.prod(a.shape[2:], dtype=int))) if a.ndim >= 2 else a.reshape(-1, 1, 1)
        frames = np.unique(np.linspace(0, a2.shape[0] - 1, FINGERPRINT_FRAMES).round().astype(int))
        rows = [[*a2[f].mean(axis=0).tolist(), float(np.sqrt(np.mean(a2[f] ** 2)))] for f in frames]
        out.append({"shape": list(a.shape), "rms": float(np.sqrt(np.mean(a ** 2))), "frames": rows})
    return out


def fingerprint_distance(a: list, b: list) -> float:
    """The largest difference between two fingerprints' entries relative to their array's RMS (inf where
    the arrays' number, shapes or frames differ)."""
    if not isinstance(a, list) or not isinstance(b, list) or len(a) != len(b):
        return float("inf")
    worst = 0.0
    for x, y in zip(a, b):
        if x is None or y is None:
            if x is not y:
                return float("inf")
            continue
        if x["shape"] != y["shape"] or len(x["frames"]) != len(y["frames"]):
            return float("inf")
        scale = max(x["rms"], y["rms"], 1e-300)
        fx, fy = np.asarray(x["frames"], float), np.asarray(y["frames"], float)
        worst = max(worst, abs(x["rms"] - y["rms"]) / scale, float(np.max(np.abs(fx - fy))) / scale)
    return worst


def _show(v: Any) -> str:
    return f"{v[:12]}..." if isinstance(v, str) and len(v) == 64 else repr(v)   # a digest: its first 12 digits


def check_identity(who: str, checkpoint: str | Path, saved: dict | None, current: dict) -> list[str]:
    """Raise ``ConfigError`` when ``saved`` (what the checkpoint's run recorded; ``None``: nothing) and
    ``current`` differ in a key either has, except a digest whose fingerprints (``<key>_fingerprint``, in
    both) agree within ``FINGERPRINT_RTOL`` (module doc). Returns one line per such round-off difference."""
    if saved is None:
        return []
    current, notes = _jsonable(current), []
    for key in sorted(set(saved) | set(current)):
        if key.endswith("_fingerprint") or key == NOTES:   # compared with tolerance where a digest differs; a log
            continue
        old, new = saved.get(key), current.get(key)
        if old != new:
            fp = key + "_fingerprint"
            if fp in saved and fp in current:
                dist = fingerprint_distance(saved[fp], current[fp])
                if dist <= FINGERPRINT_RTOL:
                    notes.append(f"{who}: {key} differs from the one the checkpoint {Path(checkpoint).name} was made "
                                 f"with ({_show(old)} -> {_show(new)}) at round-off only (fingerprints agree to "
                                 f"{dist:.1e} of each array's RMS, tolerance {FINGERPRINT_RTOL:g}): resuming")
                    continue
            raise ConfigError(f"{who}: the checkpoint {checkpoint} was made with {key} = {_show(old)}, this run has "
                              f"{_show(new)}; resume with the same {key}, or use another run directory "
                              f"(or task.resume=false to start over).")
    return notes


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
