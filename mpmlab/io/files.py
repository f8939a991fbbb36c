"""Output files that never lie: atomic publication, a disk-space guard, and what killed runs leave.

* Every output is written to a temporary file next to its target, ``.<name>.<pid>.<random>.tmp``
  (same file system, so the final rename is atomic), and published in one step: a target path never
  holds a half-written file, and an existing one is replaced only with ``overwrite=True``.
* :class:`AtomicWriter` is that lifecycle for the writers that stream into a file (HDF5
  trajectories, rerun recordings): open on a temporary file, publish or discard it on close.
* :func:`ensure_space` refuses a write that would not fit on the target's file system *before* the
  library writing it hits ``ENOSPC``: HDF5 cannot recover from a failed write (it floods stderr from
  finalisers and can segfault), rerun's file sink stops with "File-writer thread shut down".
* A run killed with SIGKILL (or out of memory, or by a crash) cannot clean up. Its temporary files
  carry its pid, and :func:`handle_stale_temps`, called at the start of the next run into the same
  folder, says what it found: a streamed trajectory with readable frames is published as the target
  (marked incomplete, the reason recorded) when no target exists yet; every other leftover is removed.
"""
from __future__ import annotations

import errno
import os
import re
import tempfile
from pathlib import Path
from typing import Any, Callable

from ..core.budget import free_disk, human_bytes
from ..core.errors import ConfigError, MpmlabError

#: Room kept free besides a write's own size (file-system metadata, HDF5 headers, rerun's buffers).
SPACE_MARGIN = 1 << 20

_TEMP_RE = re.compile(r"^\.(?P<name>.+?)\.(?:(?P<pid>\d+)\.)?[^.]+\.tmp$")


class OutputExistsError(ConfigError):
    """An output would replace an existing file and overwriting was not asked for."""

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        super().__init__(f"'{self.path}' already exists; pass overwrite=True to replace it, or choose another path.")


class OutputError(MpmlabError):
    """An output cannot be written (full disk, no permission, ...); ``reason`` is the OS's words."""

    def __init__(self, path: str | os.PathLike, reason: str, detail: str = ""):
        self.path, self.reason, self.detail = Path(path), reason, detail
        super().__init__(f"cannot write '{self.path}': {reason}" + (f" ({detail})" if detail else ""))


def _reason(exc: OSError) -> str:
    return (exc.strerror or type(exc).__name__).lower() if exc.errno != errno.ENOSPC else "no space left on device"


def is_disk_full(exc: BaseException) -> bool:
    """True for ENOSPC/EDQUOT, also when a library wraps it in its own error text."""
    if isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT):
        return True
    text = str(exc)
    return "errno = 28" in text or "os error 28" in text or "No space left on device" in text


def free_bytes(path: str | os.PathLike) -> int:
    """Free bytes on the file system holding ``path`` or its nearest existing parent."""
    return free_disk(path)[0]


def ensure_space(path: str | os.PathLike, nbytes: int, what: str = "") -> None:
    """Raise ``OutputError`` ("no space left on device") unless ``nbytes`` plus a margin fit next to
    ``path`` (the published name is reported, not the temporary file)."""
    free = free_bytes(path)
    if nbytes + SPACE_MARGIN > free:
        raise OutputError(path, "no space left on device",
                          f"{what + ' ' if what else ''}needs {human_bytes(nbytes)} plus a {human_bytes(SPACE_MARGIN)} "
                          f"margin; {human_bytes(free)} free")


# ---- atomic publication --------------------------------------------------------------------------
def check_target(path: str | os.PathLike, overwrite: bool) -> Path:
    """The target as a ``Path`` (parent folders created); refuses an existing file unless ``overwrite``."""
    path = Path(path)
    if path.is_dir():
        raise ConfigError(f"'{path}' is a directory; give a file path to write to.")
    if path.exists() and not overwrite:
        raise OutputExistsError(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(path.parent, _reason(exc)) from None
    return path


def temp_path(path: Path) -> Path:
    """A fresh empty temporary file next to ``path``, named ``.<name>.<pid>.<random>.tmp``."""
    try:
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.{os.getpid()}.", suffix=".tmp")
    except OSError as exc:
        raise OutputError(path, _reason(exc)) from None
    os.close(fd)
    return Path(tmp)


def _umask() -> int:
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    return 0o022


def publish(tmp: Path, path: Path, overwrite: bool) -> None:
    """Move the finished ``tmp`` onto ``path`` in one step; ``tmp`` is gone afterwards in every case.

    Without ``overwrite`` the move is a hard link, which fails atomically if ``path`` appeared meanwhile.
    """
    try:
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp creates 0600
        if overwrite:
            os.replace(tmp, path)
            return
        try:
            os.link(tmp, path)
        except FileExistsError:
            raise OutputExistsError(path) from None
        except OSError:  # a file system without hard links
            if path.exists():
                raise OutputExistsError(path) from None
            os.replace(tmp, path)
    finally:
        discard(tmp)


def discard(tmp: Path | None) -> None:
    if tmp is not None:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass


def write_atomically(path: str | os.PathLike, write: Callable[[Path], None], overwrite: bool = False) -> Path:
    """Call ``write(tmp)`` on a temporary file next to ``path``, then publish it as ``path``.

    An ``OSError`` while writing (a full disk, a lost permission) becomes ``OutputError`` naming
    ``path``, and nothing is left behind."""
    path = check_target(path, overwrite)
    tmp = temp_path(path)
    try:
        write(tmp)
        publish(tmp, path, overwrite)
    except OSError as exc:
        discard(tmp)
        raise OutputError(path, _reason(exc)) from None
    except BaseException:
        discard(tmp)
        raise
    return path


def write_pickle(path: str | os.PathLike, obj: Any) -> Path:
    """``pickle`` ``obj`` to ``path`` atomically, replacing it (a training's checkpoint: a reader sees the
    previous checkpoint or this one, never half of one)."""
    import pickle

    def dump(tmp: Path) -> None:
        with open(tmp, "wb") as f:
            pickle.dump(obj, f)

    return write_atomically(path, dump, overwrite=True)


class AtomicWriter:
    """The lifecycle of a streaming writer (``mpmlab.io.h5.TrajectoryWriter``,
    ``mpmlab.io.rerun.RecordingWriter``, ``mpmlab.io.rerun.EpochRecorder``): the target is checked
    when the writer is made (:func:`check_target`), the format's writer opens on a temporary file
    next to it (:meth:`open`, or entering a ``with`` block), and :meth:`close` (leaving the block,
    with the exception that ended it, if any) finishes that file and publishes it in one step, or
    discards it.

    A subclass implements ``_is_open()``, ``_start(tmp)`` (open the format's writer on ``tmp``),
    ``_abort_start()`` (release what a failed ``_start`` holds; the temporary file is then removed)
    and ``_finish(exc)`` (finish the file, then :meth:`_publish` it or :func:`discard` ``self._tmp``;
    returns the published path or None). ``close`` again returns what the first ``close`` published.
    """

    def __init__(self, path: str | os.PathLike, overwrite: bool = False):
        self.path = check_target(path, overwrite)
        self.overwrite = overwrite
        self._tmp: Path | None = None
        self._closed = False
        self._published: Path | None = None

    # ---- what a format implements --------------------------------------------------------------
    def _is_open(self) -> bool:
        raise NotImplementedError

    def _start(self, tmp: Path) -> None:
        raise NotImplementedError

    def _abort_start(self) -> None:
        raise NotImplementedError

    def _finish(self, exc: BaseException | None) -> Path | None:
        raise NotImplementedError

    # ---- the shared lifecycle ------------------------------------------------------------------
    def open(self):
        """Open the format's writer on a fresh temporary file next to ``path`` (once)."""
        if self._is_open():
            return self
        self._tmp = temp_path(self.path)
        try:
            self._start(self._tmp)
        except BaseException:
            self._abort_start()
            discard(self._tmp)
            raise
        return self

    def __enter__(self):
        return self.open()

    def __exit__(self, exc_type, exc, tb) -> bool:
        self.close(exc)
        return False

    def close(self, exc: BaseException | None = None) -> Path | None:
        """Finish and publish (``exc``: the exception that ended the writing, if any); returns the
        path, or None when nothing was published. A writer that ``exc`` ended before it opened
        publishes nothing; one closed without having opened publishes an empty file."""
        if self._closed:
            return self._published
        self._closed = True
        if not self._is_open():
            if exc is not None:
                return None
            self.open()
        return self._finish(exc)

    def _publish(self) -> Path:
        """Move the finished temporary file onto ``path`` (:func:`publish`)."""
        publish(self._tmp, self.path, self.overwrite)
        self._published = self.path
        return self.path


# ---- what killed runs leave ---------------------------------------------------------------------
def _pid_alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def stale_temps(folder: str | os.PathLike) -> list[tuple[Path, str, int | None]]:
    """``(temp file, target name, writer pid or None)`` of the temporary files in ``folder`` whose
    writer is no longer running (files of mpmlab versions without a pid in the name count as stale)."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    out = []
    for p in sorted(folder.iterdir()):
        m = _TEMP_RE.match(p.name)
        if not m or not p.is_file():
            continue
        pid = int(m["pid"]) if m["pid"] else None
        if pid is not None and _pid_alive(pid):
            continue
        out.append((p, m["name"], pid))
    return out


def handle_stale_temps(folder: str | os.PathLike) -> list[str]:
    """Recover or remove what runs killed before they finished left in ``folder``; returns one line
    per file saying what was found and done (the caller prints them)."""
    lines = []
    for tmp, name, pid in stale_temps(folder):
        who = f"an earlier run (pid {pid}, no longer running)" if pid else "an earlier run"
        size = human_bytes(tmp.stat().st_size)
        target = tmp.parent / name
        recovered = None
        if name.endswith(".h5") and not target.exists():
            from .h5 import recover_stream

            recovered = recover_stream(tmp, target, f"the run that wrote it{f' (pid {pid})' if pid else ''} was "
                                                    f"killed before it finished (SIGKILL, out of memory or a crash); "
                                                    f"recovered by a later run")
        if recovered is not None:
            lines.append(f"found '{tmp.name}' ({size}) left by {who} that was killed before it finished: "
                         f"recovered its {recovered} readable frame(s) as '{name}' (marked incomplete).")
        else:
            discard(tmp)
            lines.append(f"found '{tmp.name}' ({size}) left by {who} that was killed before it finished "
                         f"'{name}'; removed it" + (" (no readable frame)." if name.endswith(".h5") and
                                                     not target.exists() else "."))
    return lines
