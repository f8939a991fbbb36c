"""HDF5 trajectories: schema ``mpmlab.trajectory`` version 1: write, stream, read.

Layout (every array keeps the dtype of the ``Trajectory`` it came from, so a round trip is exact)::

    /                 attrs: schema="mpmlab.trajectory", schema_version=1, dim, dt, substeps_per_frame,
                             backend, transfer, shape_function (the transfer's, mpmlab.shapes; absent
                             in files written before it was a choice: quadratic), precision,
                             mpmlab_version, created_by, config_yaml,
                             metadata_json (Trajectory.meta as JSON), frame_count, complete
                             (+ diverged, diverged_step, ..., error for a stream ended by an exception;
                             + the caller's extra_attrs)
    /grid             attrs: shape, dx, origin
    /particles/       material_id [N] i4, body_id [N] i4, mass [N], volume [N],
                      params [N, P] (NaN-padded; attr names_json: the parameter names of each material)
    /materials        attrs: laws_json (per material: law, param_names, start, stop, provenance)
    /frames/          x [T, N, D], v [T, N, D], time [T], step [T] i8, and every Trajectory field
                      (F [T, N_F, D, D], C, J, sigma, eps_p, ...); chunks (1, N, ...), lzf + shuffle;
                      a field synthesised from another (F = J^(1/d) I for a J-only law,
                      mpmlab.io.derived) has attrs derived_from, derived_formula,
                      derived_particles_json, and the simulate task's root attribute
                      derived_fields (JSON) says the same
    /field_particles/ <field> [N_F] i8: the particles each field covers

A file is written to a temporary file in the target's directory, ``complete`` is set last, and the
file is published with one rename: a target path never holds a half-written file, and an existing
file is replaced only with ``overwrite=True`` (:mod:`mpmlab.io.files`, shared with the rerun writers).
The LagrangeBench export of these files is :mod:`mpmlab.io.lagrangebench`.
"""
from __future__ import annotations

import contextlib
import json
import os
import warnings
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from ..core.errors import ConfigError, SimulationDiverged
from ..core.errors import first_line as _first_line
from ..core.state import Trajectory

SCHEMA = "mpmlab.trajectory"
SCHEMA_VERSION = 1
_FRAME_CORE = ("x", "v", "time", "step")
_RESERVED_ATTRS = {"schema", "schema_version", "dim", "dt", "substeps_per_frame", "backend", "transfer",
                   "shape_function", "precision", "mpmlab_version", "created_by", "config_yaml", "metadata_json",
                   "frame_count",
                   "complete", "diverged", "diverged_step", "diverged_particle", "diverged_field",
                   "diverged_message", "error"}


# ---- atomic publication: mpmlab.io.files (re-exported here for the callers that import it from h5)
from .files import (AtomicWriter, OutputError, OutputExistsError, check_target, discard,  # noqa: E402,F401
                    ensure_space, is_disk_full, publish, temp_path, write_atomically)


# ---- JSON helpers ------------------------------------------------------------------------------
def _json_default(o: Any):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (set, frozenset)):
        return sorted(o)
    if isinstance(o, os.PathLike):
        return os.fspath(o)
    return str(o)


def to_json(obj: Any) -> str:
    return json.dumps(obj, default=_json_default)


def _attr_value(v: Any):
    """An h5py-storable attribute value (scalars, strings, numeric arrays); anything else as JSON."""
    if isinstance(v, (str, bool, int, float, np.generic)):
        return v
    if isinstance(v, np.ndarray) and v.dtype.kind in "biuf":
        return v
    if isinstance(v, (list, tuple)) and v and all(isinstance(e, (int, float)) and not isinstance(e, bool) for e in v):
        return np.asarray(v)
    return to_json(v)


def _py(v: Any):
    """An attribute read back as a plain Python value."""
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, bytes):
        return v.decode()
    return v


# ---- writing -----------------------------------------------------------------------------------
def _compression_kwargs(compression: str | None) -> dict:
    if compression is None:
        return {}
    if compression == "lzf":
        return {"compression": "lzf", "shuffle": True}
    if compression == "gzip":
        return {"compression": "gzip", "compression_opts": 4, "shuffle": True}
    raise ConfigError(f"compression '{compression}' unknown; use 'lzf' (default), 'gzip' or None.")


def _frame_spacing(step: np.ndarray) -> int:
    """Steps between consecutive frames (-1 when the spacing is not uniform, 0 for one frame)."""
    step = np.asarray(step)
    if len(step) < 2:
        return 0
    d = np.diff(step)
    return int(d[0]) if np.all(d == d[0]) else -1


def _check_fields(traj: Trajectory) -> None:
    for name, a in traj.fields.items():
        if not name or "/" in name or name in _FRAME_CORE:
            raise ConfigError(f"trajectory field name '{name}' cannot be stored; rename it (not x, v, time, step, "
                              f"no '/').")
        if len(a) != traj.frame_count:
            raise ConfigError(f"trajectory field '{name}' has {len(a)} frames but x has {traj.frame_count}; "
                              f"every field needs one entry per frame.")


def _write_static(f, traj: Trajectory, config_yaml: str, extra_attrs: dict | None) -> None:
    from .. import __version__

    meta = traj.meta or {}
    a = f.attrs
    a["schema"] = SCHEMA
    a["schema_version"] = SCHEMA_VERSION
    a["dim"] = int(meta.get("dim", traj.x.shape[-1] if traj.x.ndim == 3 else 0))
    a["dt"] = float(meta.get("dt", np.nan))
    a["substeps_per_frame"] = _frame_spacing(traj.step)
    for key in ("backend", "transfer", "precision"):
        a[key] = str(meta.get(key, ""))
    if "transfer" in meta:                       # the shape function the transfer ran with (mpmlab.shapes)
        a["shape_function"] = str(meta.get("shape", "quadratic"))
    a["mpmlab_version"] = __version__
    a["created_by"] = f"mpmlab {__version__}"
    a["config_yaml"] = config_yaml or ""
    a["metadata_json"] = to_json(meta)
    a["complete"] = False
    for k, v in (extra_attrs or {}).items():
        if k in _RESERVED_ATTRS:
            raise ConfigError(f"extra_attrs key '{k}' is reserved by the {SCHEMA} schema; rename it.")
        a[k] = _attr_value(v)

    g = f.create_group("grid")
    if "grid_shape" in meta:
        g.attrs["shape"] = np.asarray(meta["grid_shape"], dtype=np.int64)
    if "dx" in meta:
        g.attrs["dx"] = float(meta["dx"])
    if "grid_origin" in meta:
        g.attrs["origin"] = np.asarray(meta["grid_origin"], dtype=float)

    p = f.create_group("particles")
    p.create_dataset("material_id", data=np.asarray(traj.material_id), dtype="i4")
    p.create_dataset("body_id", data=np.asarray(traj.body_id), dtype="i4")
    p.create_dataset("mass", data=np.asarray(traj.mass))
    p.create_dataset("volume", data=np.asarray(traj.volume))
    p.create_dataset("params", data=np.asarray(traj.params))
    p["params"].attrs["names_json"] = to_json([list(m.get("param_names", [])) for m in traj.materials])

    m = f.create_group("materials")
    m.attrs["laws_json"] = to_json(list(traj.materials))
    f.create_group("frames")
    f.create_group("field_particles")


def _create_frame_dataset(frames, name: str, per_frame_shape: tuple, dtype, comp: dict):
    chunks = (1, *(max(1, s) for s in per_frame_shape)) if per_frame_shape else (4096,)
    return frames.create_dataset(name, shape=(0, *per_frame_shape), maxshape=(None, *per_frame_shape),
                                 chunks=chunks, dtype=dtype, **comp)


def _finish(f, frame_count: int, complete: bool, exc: BaseException | None = None) -> None:
    a = f.attrs
    a["frame_count"] = int(frame_count)
    if isinstance(exc, SimulationDiverged):
        a["diverged"] = True
        a["diverged_step"] = int(exc.step)
        a["diverged_particle"] = int(exc.particle)
        a["diverged_field"] = str(exc.field)
        a["diverged_message"] = str(exc)
    elif exc is not None:
        from ..core.signals import stop_reason

        a["error"] = stop_reason(exc)
    if complete:
        a["complete"] = True  # last: a file with complete=True has everything
    f.flush()


def write_trajectory(path: str | os.PathLike, traj: Trajectory, config_yaml: str = "",
                     extra_attrs: dict | None = None, compression: str | None = "lzf",
                     overwrite: bool = False) -> Path:
    """Write ``traj`` as an ``mpmlab.trajectory`` v1 HDF5 file, atomically.

    Args:
        path: target file; parent folders are created.
        traj: the trajectory (arrays keep their dtypes).
        config_yaml: the resolved configuration (e.g. ``OmegaConf.to_yaml(cfg)``), stored verbatim.
        extra_attrs: more root attributes (scalars, strings, numeric arrays; others stored as JSON).
        compression: ``"lzf"`` (default, with shuffle), ``"gzip"`` (level 4, archives) or None.
        overwrite: replace an existing file (otherwise that raises ``ConfigError``).

    Returns:
        The path written.
    """
    import h5py

    comp = _compression_kwargs(compression)
    _check_fields(traj)

    def write(tmp: Path) -> None:
        with h5py.File(tmp, "w") as f:
            _write_static(f, traj, config_yaml, extra_attrs)
            fr = f["frames"]
            T = traj.frame_count
            arrays = {"x": traj.x, "v": traj.v, **traj.fields}
            for name, arr in arrays.items():
                arr = np.asarray(arr)
                ds = _create_frame_dataset(fr, name, arr.shape[1:], arr.dtype, comp)
                ds.resize(T, axis=0)
                if T:
                    ds[...] = arr
            for name, arr, dtype in (("time", traj.time, None), ("step", traj.step, np.int64)):
                arr = np.asarray(arr, dtype=dtype)
                ds = _create_frame_dataset(fr, name, (), arr.dtype, comp)
                ds.resize(T, axis=0)
                if T:
                    ds[...] = arr
            for name in traj.fields:
                idx = traj.field_particles.get(name, np.arange(traj.fields[name].shape[1]))
                f["field_particles"].create_dataset(name, data=np.asarray(idx, dtype=np.int64))
            _finish(f, T, complete=True)

    return write_atomically(path, write, overwrite)


class TrajectoryWriter(AtomicWriter):
    """Stream frames into an ``mpmlab.trajectory`` file as a rollout produces them.

    Usable as the rollout's ``on_frame`` callback::

        stepper = mpmlab.build_stepper(scene, "jax", precision="fp64")
        with TrajectoryWriter("run.h5", stepper=stepper, fields=("F",), every=10) as w:
            stepper.rollout(steps=1000, every=10, fields=("F",), on_frame=w)

    Frames go to a temporary file next to ``path``; leaving the ``with`` block publishes it atomically
    with ``complete=True``. If an exception ends the block (e.g. ``SimulationDiverged``), the frames
    already written are kept: the file is still published, with ``complete=False`` and the reason
    (``diverged``, ``diverged_step``, ``diverged_particle``, ``diverged_field``, ``diverged_message``,
    or ``error``) in the root attributes; if no frame was written, nothing is published.

    Args:
        path: target file.
        static: a ``Trajectory`` supplying the static data (mass, volume, ids, materials, params, meta);
            its frames are ignored. Give this or ``stepper``.
        stepper: a built stepper to take the static data from.
        fields: per-particle fields to store besides x and v (``F``, ``C``, ``J``, ``sigma``, ``eps_p``).
        every: the rollout's frame spacing in steps, used only for a state that does not say its
            step (``rollout`` states carry ``step`` and ``time``: the last frame of a rollout whose
            ``steps`` is not a multiple of ``every`` is labelled with its real step). Without either,
            the step is ``round(t / dt)`` from the state's time.

    Each frame is flushed to disk as it is written, so that even a run killed with SIGKILL leaves a
    readable temporary file (``mpmlab.io.files.handle_stale_temps`` recovers it), and each frame first
    checks that it fits on the disk: a full disk ends the stream with ``OutputError`` ("no space
    left on device") and the frames before it published, marked incomplete.
        field_attrs: attributes of the frame datasets, ``{field: {name: value}}`` (e.g. ``frames/F``
            of a field synthesised from another: :mod:`mpmlab.io.derived`).
        config_yaml, extra_attrs, compression, overwrite: as for ``write_trajectory``.
    """

    def __init__(self, path: str | os.PathLike, static: Trajectory | None = None, *, stepper=None,
                 fields: Sequence[str] = (), every: int | None = None, config_yaml: str = "",
                 extra_attrs: dict | None = None, compression: str | None = "lzf", overwrite: bool = False,
                 field_attrs: dict | None = None):
        if (static is None) == (stepper is None):
            raise ConfigError("TrajectoryWriter needs exactly one of static= (a Trajectory) or stepper=.")
        if static is None:
            static = stepper._trajectory([], [], ())
        if every is not None and every < 1:
            raise ConfigError(f"TrajectoryWriter: every must be >= 1 (got {every}).")
        AtomicWriter.__init__(self, path, overwrite)
        self.static = static
        self.fields = tuple(fields)
        for name in self.fields:
            if not name or "/" in name or name in _FRAME_CORE:
                raise ConfigError(f"field name '{name}' cannot be stored; rename it (not x, v, time, step, no '/').")
        self.every = every
        self.config_yaml = config_yaml
        self.extra_attrs = extra_attrs
        self.field_attrs = dict(field_attrs or {})
        self.comp = _compression_kwargs(compression)
        self.dt = float((static.meta or {}).get("dt", np.nan))
        self.frame_count = 0
        self._f = None
        self._steps: list[int] = []

    # ---- lifecycle (mpmlab.io.files.AtomicWriter: open, with, close) -------------------------
    def _is_open(self) -> bool:
        return self._f is not None

    def _start(self, tmp: Path) -> None:
        import h5py

        self._f = h5py.File(tmp, "w")
        _write_static(self._f, self.static, self.config_yaml, self.extra_attrs)

    def _abort_start(self) -> None:
        if self._f is not None:
            self._f.close()

    def _finish(self, exc: BaseException | None) -> Path | None:
        """Finalise and publish (``complete`` unless ``exc`` is given); returns the path, or None if
        an exception ended a stream that had no frame (then nothing is written)."""
        f, tmp = self._f, self._tmp
        try:
            if exc is not None and self.frame_count == 0:
                f.close()
                discard(tmp)
                return None
            fr = f["frames"]
            for name in ("x", "v", "time", "step", *self.fields):
                if name in fr and fr[name].shape[0] != self.frame_count:
                    fr[name].resize(self.frame_count, axis=0)  # drop a frame interrupted mid-write
            if "x" not in fr:  # no frame at all: empty datasets of unknown particle shape
                N, D = len(self.static.mass), int((self.static.meta or {}).get("dim", 0))
                for name in ("x", "v"):
                    _create_frame_dataset(fr, name, (N, D), np.float64, self.comp)
                _create_frame_dataset(fr, "time", (), np.float64, self.comp)
                _create_frame_dataset(fr, "step", (), np.int64, self.comp)
            f.attrs["substeps_per_frame"] = _frame_spacing(np.asarray(self._steps))
            _finish(f, self.frame_count, complete=exc is None, exc=exc)
            f.close()
            self._publish()
        except BaseException as err:
            self._f = f
            self._abandon()
            if is_disk_full(err):
                raise OutputError(self.path, "no space left on device", "while closing it; the partial file "
                                  "was removed") from None
            raise
        return self.path

    # ---- frames ----------------------------------------------------------------------------
    def __call__(self, frame_index: int, npstate: dict) -> None:
        """The rollout ``on_frame`` callback: store the kept frame ``npstate``."""
        if "step" in npstate:                    # a rollout says which step this is
            step = int(npstate["step"])
        elif self.every is not None:
            step = int(frame_index) * self.every
        elif "t" in npstate and np.isfinite(self.dt):
            step = int(round(float(npstate["t"]) / self.dt))
        else:
            step = int(frame_index)
        if "time" in npstate:                    # a rollout's time: the sum of the steps taken (adaptive dt too)
            time = float(npstate["time"])
        else:
            time = step * self.dt if np.isfinite(self.dt) else float(npstate.get("t", np.nan))
        missing = [k for k in self.fields if k not in npstate]
        if missing:
            have = sorted(k for k in npstate if k not in ("x", "v", "t") and not k.endswith("_particles"))
            raise ConfigError(f"TrajectoryWriter: the state has no field {missing}; it has {have or 'none'} "
                              f"(fields depend on the laws and the transfer).")
        fields = {k: npstate[k] for k in self.fields}
        particles = {k: npstate[k + "_particles"] for k in self.fields if k + "_particles" in npstate}
        self.add_frame(npstate["x"], npstate["v"], time, step, fields, particles)

    def add_frame(self, x, v, time: float, step: int, fields: dict | None = None,
                  field_particles: dict | None = None) -> None:
        """Append one frame: ``x``, ``v`` [N, D], its time and step, and the writer's ``fields``."""
        if self._closed:
            raise ConfigError("TrajectoryWriter is closed; open a new writer to write more frames.")
        self.open()
        fields = fields or {}
        missing = [k for k in self.fields if k not in fields]
        if missing:
            raise ConfigError(f"TrajectoryWriter: frame {self.frame_count} lacks field(s) {missing} "
                              f"that the writer was asked to store.")
        fr = self._f["frames"]
        arrays = {"x": np.asarray(x), "v": np.asarray(v), **{k: np.asarray(fields[k]) for k in self.fields}}
        if self.frame_count == 0:
            for name, arr in arrays.items():
                ds = _create_frame_dataset(fr, name, arr.shape, arr.dtype, self.comp)
                for k, v in self.field_attrs.get(name, {}).items():
                    ds.attrs[k] = _attr_value(v)
            _create_frame_dataset(fr, "time", (), np.float64, self.comp)
            _create_frame_dataset(fr, "step", (), np.int64, self.comp)
            fp = self._f["field_particles"]
            for name in self.fields:
                idx = (field_particles or {}).get(name)
                if idx is None:
                    idx = self.static.field_particles.get(name, np.arange(arrays[name].shape[0]))
                fp.create_dataset(name, data=np.asarray(idx, dtype=np.int64))
        k = self.frame_count
        row = {**arrays, "time": np.float64(time), "step": np.int64(step)}
        for name, arr in row.items():
            if arr.shape != fr[name].shape[1:]:
                raise ConfigError(f"TrajectoryWriter: frame {k} has {name} of shape {arr.shape}, "
                                  f"earlier frames {fr[name].shape[1:]}; the particle set cannot change.")
        # HDF5 cannot recover from a failed write: refuse the frame while the disk still has room
        ensure_space(self.path, 2 * sum(a.nbytes for a in row.values()), f"frame {k}")
        try:
            for name, arr in row.items():
                ds = fr[name]
                ds.resize(k + 1, axis=0)
                ds[k] = arr
            self._f.flush()    # on disk now: a SIGKILL later leaves a readable file
        except (OSError, RuntimeError) as exc:
            if is_disk_full(exc):
                self._abandon()
                raise OutputError(self.path, "no space left on device",
                                  f"at frame {k}; the partial file was removed") from None
            raise
        self._steps.append(int(step))
        self.frame_count = k + 1

    def _abandon(self) -> None:
        """Drop the stream after a failed write: free the disk first (truncating the temporary file),
        so that HDF5's closing flush succeeds instead of failing over and over, then remove it."""
        f, tmp = self._f, self._tmp
        self._f, self._closed = None, True
        try:
            os.truncate(tmp, 0)
        except OSError:
            pass
        try:
            f.close()
        except Exception:
            pass
        discard(tmp)


def recover_stream(tmp: Path, target: Path, reason: str) -> int | None:
    """Publish the streamed temporary file ``tmp`` of a killed writer as ``target``, marked incomplete
    with ``reason``, keeping the frames that all frame datasets hold; None (nothing published) when it
    is not a readable ``mpmlab.trajectory`` stream with at least one frame."""
    import h5py

    try:
        with h5py.File(tmp, "r+") as f:
            if _py(f.attrs.get("schema", None)) != SCHEMA or "frames" not in f:
                return None
            fr = f["frames"]
            if any(k not in fr for k in _FRAME_CORE):
                return None
            T = min(fr[k].shape[0] for k in fr)
            if T == 0:
                return None
            for k in fr:
                if fr[k].shape[0] != T:
                    fr[k].resize(T, axis=0)
            f.attrs["frame_count"] = int(T)
            f.attrs["complete"] = False
            f.attrs["error"] = reason
        publish(tmp, target, overwrite=False)
    except Exception:
        return None
    return int(T)


# ---- reading -----------------------------------------------------------------------------------
def _unreadable(path: Path, what: str) -> ConfigError:
    return ConfigError(f"trajectory file '{path}' is damaged: {what}; it may have been truncated or partly overwritten "
                       f"(rewrite it with the run that made it, or give another file).")


def _open_checked(path: str | os.PathLike):
    import h5py

    path = Path(path)
    if not path.exists():
        raise ConfigError(f"trajectory file '{path}' does not exist; check the path.")
    if path.is_dir():
        raise ConfigError(f"'{path}' is a directory, not a trajectory file; give the .h5 file inside it.")
    try:
        is_h5 = h5py.is_hdf5(path)
    except OSError as exc:
        raise ConfigError(f"trajectory file '{path}' cannot be read ({(exc.strerror or str(exc)).lower()}); "
                          f"check its permissions.") from None
    if not is_h5:
        raise ConfigError(f"'{path}' is not an HDF5 file, so it cannot be an {SCHEMA} file; "
                          f"give a file written by mpmlab.io.write_trajectory.")
    try:
        f = h5py.File(path, "r")
    except OSError as exc:  # a truncated file: the HDF5 signature is there, its end is not
        raise _unreadable(path, f"HDF5 cannot open it ({_first_line(str(exc))})") from None
    schema = _py(f.attrs.get("schema", None))
    version = _py(f.attrs.get("schema_version", None))
    if schema != SCHEMA:
        found = f"schema '{schema}'" if schema is not None else \
            f"no 'schema' attribute (top-level entries: {', '.join(sorted(f.keys())) or 'none'})"
        f.close()
        raise ConfigError(f"'{path}' is an HDF5 file but not an {SCHEMA} file: it has {found}.")
    if version != SCHEMA_VERSION:
        f.close()
        raise ConfigError(f"'{path}' holds {SCHEMA} version {version}, but this mpmlab reads version "
                          f"{SCHEMA_VERSION}; read it with the mpmlab version that wrote it.")
    return f


def read_attrs(path: str | os.PathLike) -> dict[str, Any]:
    """The root attributes of an ``mpmlab.trajectory`` file as plain Python values."""
    with _open_checked(path) as f:
        return {k: _py(v) for k, v in f.attrs.items()}


def read_trajectory(path: str | os.PathLike, require_complete: bool = False) -> Trajectory:
    """Read an ``mpmlab.trajectory`` v1 file back into a ``Trajectory`` (dtypes as written; the
    ids come back as int64, as a rollout makes them).

    A file that is not complete (a stream ended by a divergence or an error) is read with a warning,
    or refused with ``require_complete=True``. A missing file, a file that is not HDF5, or an HDF5 file
    of another schema or version raises ``ConfigError``.
    """
    path = Path(path)
    with _open_checked(path) as f:
        try:
            return _read(f, path, require_complete)
        except (OSError, RuntimeError, KeyError, ValueError) as exc:   # h5py's errors on damaged data
            if isinstance(exc, ConfigError):
                raise
            raise _unreadable(path, f"reading it failed ({type(exc).__name__}: {_first_line(str(exc))})") from None


_REQUIRED = ("particles/mass", "particles/volume", "particles/material_id", "particles/body_id", "particles/params",
             "frames/x", "frames/v", "frames/time", "frames/step", "field_particles")


@contextlib.contextmanager
def open_trajectory(path: str | os.PathLike, require_complete: bool = False):
    """A ``Trajectory`` whose frame arrays (``x``, ``v``, ``fields``) are the file's h5py datasets,
    read frame by frame on indexing (``traj.x[i]``): a trajectory of any length in bounded memory.
    Valid inside the ``with`` block only; checks as ``read_trajectory``."""
    path = Path(path)
    with _open_checked(path) as f:
        yield _read(f, path, require_complete, lazy=True)


def _read(f, path: Path, require_complete: bool, lazy: bool = False) -> Trajectory:
    """Check the layout of an opened file against the schema, then read it (``lazy``: frames as the
    h5py datasets; the static data, times and steps are read)."""
    attrs = f.attrs
    missing = [k for k in _REQUIRED if k not in f]
    if "materials" not in f or "laws_json" not in f["materials"].attrs:
        missing.append("materials (attribute laws_json)")
    if "metadata_json" not in attrs:
        missing.append("the root attribute metadata_json")
    if missing:
        raise _unreadable(path, f"the {SCHEMA} dataset(s) {', '.join(missing)} are missing")
    fr, p = f["frames"], f["particles"]
    T, N = fr["x"].shape[0], p["mass"].shape[0]
    for k in fr:
        if fr[k].shape[0] != T:
            raise _unreadable(path, f"frames/{k} has {fr[k].shape[0]} frames but frames/x has {T}")
    for k in ("x", "v"):
        if fr[k].ndim != 3 or fr[k].shape[1] != N:
            raise _unreadable(path, f"frames/{k} has shape {fr[k].shape}, expected [T, {N}, D] for {N} particles")
    for k in ("volume", "material_id", "body_id", "params"):
        if p[k].shape[0] != N:
            raise _unreadable(path, f"particles/{k} has {p[k].shape[0]} entries but particles/mass has {N}")
    fp = f["field_particles"]
    for k in fr:
        if k not in _FRAME_CORE and k in fp and fr[k].shape[1] != fp[k].shape[0]:
            raise _unreadable(path, f"frames/{k} covers {fr[k].shape[1]} particles but field_particles/{k} "
                                    f"lists {fp[k].shape[0]}")
    if not bool(attrs.get("complete", False)):
        why = _py(attrs.get("diverged_message", None)) or _py(attrs.get("error", None)) or "writing stopped early"
        msg = f"'{path}' is incomplete ({why}); it holds the {T} frames written before."
        if require_complete:
            raise ConfigError(msg)
        warnings.warn(msg, stacklevel=3)
    meta = json.loads(_py(attrs["metadata_json"]))
    materials = json.loads(_py(f["materials"].attrs["laws_json"]))

    def load(ds):
        try:
            return ds[()]
        except (OSError, RuntimeError, ValueError) as exc:
            raise _unreadable(path, f"{ds.name.lstrip('/')} cannot be read ({_first_line(str(exc))})") from None

    frames = (lambda k: fr[k]) if lazy else (lambda k: load(fr[k]))
    fields = {k: frames(k) for k in fr if k not in _FRAME_CORE}
    field_particles = {k: load(fp[k]) for k in fields if k in fp}
    return Trajectory(
        x=frames("x"), v=frames("v"), time=load(fr["time"]), step=load(fr["step"]),
        mass=load(p["mass"]), volume=load(p["volume"]),
        material_id=load(p["material_id"]).astype(np.int64), body_id=load(p["body_id"]).astype(np.int64),
        materials=materials, params=load(p["params"]), meta=meta, fields=fields, field_particles=field_particles,
    )


# ---- moved: the LagrangeBench export (mpmlab.io.lagrangebench), found here as before
def __getattr__(name: str):
    if name in ("export_lagrangebench", "_as_trajectories", "_stats"):
        from . import lagrangebench

        return getattr(lagrangebench, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
