"""rerun (.rrd) recordings of trajectories, written without a viewer and read back for tests.

Layout of a recording (rerun-sdk 0.41, one explicit ``rr.RecordingStream``, never the global one):

* timelines ``frame`` (sequence: the trajectory's frame index) and ``sim_time`` (duration, seconds);
* ``world/particles``: ``Points2D``/``Points3D`` positions per kept frame; radii ``0.5 * volume^(1/D)``
  (static); colours static (``material``, ``body``: a fixed palette) or per frame (a scalar through
  viridis; particles without a value are grey);
* ``world/domain``: the grid's extent as a box (static);
* ``metrics/<name>``: ``rr.Scalars`` per frame (vector metrics split into ``<name>/x``, ``/y``, ``/z``);
* ``scene/metadata``: a markdown ``TextDocument`` (static) with backend, transfer, precision, laws,
  the colour legend and the full ``meta`` as JSON;
* a default blueprint: the spatial view of ``/world`` beside a time series view of ``/metrics``.

The file is written to a temporary file next to the target and published atomically.
"""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from ..core.errors import ConfigError, SimulationDiverged
from ..core.state import Trajectory
from .files import SPACE_MARGIN, OutputError, check_target, discard, ensure_space, free_bytes, publish, temp_path
from .h5 import to_json

#: Material / body colours (Tableau 10), cycled.
PALETTE = np.array([[31, 119, 180], [255, 127, 14], [44, 160, 44], [214, 39, 40], [148, 103, 189],
                    [140, 86, 75], [227, 119, 194], [127, 127, 127], [188, 189, 34], [23, 190, 207]], np.uint8)
MISSING_COLOR = np.array([160, 160, 160], np.uint8)
_AXES = ("x", "y", "z")

_SCALAR_NEEDS = {"speed": "always available", "J": "needs field J or F", "eps_p": "needs field eps_p",
                 "stress": "needs field sigma"}


def color_choices(fields: Sequence[str]) -> list[str]:
    """The ``color_by`` values possible for a trajectory carrying ``fields``."""
    out = ["material", "body", "speed"]
    if "J" in fields or "F" in fields:
        out.append("J")
    if "eps_p" in fields:
        out.append("eps_p")
    if "sigma" in fields:
        out.append("stress")
    return out


def _check_color_by(color_by: str, fields: Sequence[str]) -> None:
    possible = color_choices(fields)
    if color_by not in possible:
        explain = ", ".join(f"{k} ({v})" for k, v in _SCALAR_NEEDS.items() if k not in possible)
        raise ConfigError(f"color_by='{color_by}' is not possible for this trajectory; choose one of "
                          f"{', '.join(possible)}" + (f" (not available here: {explain})." if explain else "."))


def particle_scalar(color_by: str, v: np.ndarray, fields: dict, field_particles: dict, n: int) -> np.ndarray:
    """The per-particle scalar [N] of one frame that ``color_by`` names (NaN where not defined)."""
    if color_by == "speed":
        return np.linalg.norm(np.asarray(v, dtype=np.float64), axis=-1)
    out = np.full(n, np.nan)
    if color_by == "J":
        key = "J" if "J" in fields else "F"
        a = np.asarray(fields[key], dtype=np.float64)
        val = a.reshape(len(a), -1)[:, 0] if key == "J" else np.linalg.det(a)
    elif color_by == "eps_p":
        key = "eps_p"
        a = np.asarray(fields[key], dtype=np.float64)
        a = a.reshape(len(a), -1)
        val = a[:, 0] if a.shape[1] == 1 else np.linalg.norm(a, axis=1)
    elif color_by == "stress":
        key = "sigma"
        a = np.asarray(fields[key], dtype=np.float64)
        val = np.linalg.norm(a.reshape(len(a), -1), axis=1)  # Frobenius norm of the Cauchy stress
    else:
        raise ConfigError(f"color_by='{color_by}' is not a scalar colouring.")
    idx = field_particles.get(key)
    idx = np.arange(len(val)) if idx is None else np.asarray(idx)
    out[idx] = val
    return out


def scalar_colors(values: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """RGB u8 [N, 3] of ``values`` through viridis over [lo, hi]; NaN -> grey."""
    import matplotlib

    cmap = matplotlib.colormaps["viridis"]
    span = hi - lo if np.isfinite(hi - lo) and hi > lo else 1.0
    t = np.clip((np.asarray(values, dtype=np.float64) - lo) / span, 0.0, 1.0)
    rgb = (np.asarray(cmap(np.nan_to_num(t)))[:, :3] * 255.0 + 0.5).astype(np.uint8)
    rgb[~np.isfinite(values)] = MISSING_COLOR
    return rgb


def _md_escape(s: str) -> str:
    return str(s).replace("|", "\\|")


class RecordingWriter:
    """Stream frames into an .rrd recording; also the rollout ``on_frame`` callback.

        with RecordingWriter("run.rrd", stepper=stepper, color_by="speed", color_range=(0, 2)) as rec:
            stepper.rollout(steps=1000, every=10, on_frame=rec)

    Args:
        path: target .rrd file (published atomically when the writer closes; an exception that ends
            a ``with`` block still publishes the frames so far, with the reason in ``scene/status``).
        static: a ``Trajectory`` supplying static data (its frames are ignored); or ``stepper``.
        color_by: ``material`` (default), ``body``, ``speed``, ``J``, ``eps_p`` or ``stress``.
        color_range: (lo, hi) of a scalar colouring; None: each frame's own min..max.
        every: log particles of every ``every``-th frame this writer receives (metrics of all).
        metrics: log ``mpmlab.io.metrics`` per frame (``__call__`` only; ``add_frame`` takes them).
        app_id, recording_id: rerun application and recording ids.
        overwrite: replace an existing file (otherwise that raises ``ConfigError``).
    """

    def __init__(self, path: str | os.PathLike, static: Trajectory | None = None, *, stepper=None,
                 color_by: str = "material", color_range: tuple[float, float] | None = None, every: int = 1,
                 metrics: bool = True, app_id: str = "mpmlab", recording_id: str | None = None,
                 overwrite: bool = False):
        if (static is None) == (stepper is None):
            raise ConfigError("RecordingWriter needs exactly one of static= (a Trajectory) or stepper=.")
        if static is None:
            static = stepper._trajectory([], [], ())
        if int(every) < 1:
            raise ConfigError(f"RecordingWriter: every must be >= 1 (got {every}).")
        if color_by not in ("material", "body", *_SCALAR_NEEDS):
            _check_color_by(color_by, ())
        self.path = check_target(path, overwrite)
        self.static = static
        self.color_by = color_by
        self.color_range = color_range
        self.every = int(every)
        self.metrics = metrics
        self.app_id = app_id
        self.recording_id = recording_id
        self.overwrite = overwrite
        meta = static.meta or {}
        self.dim = int(meta.get("dim", static.x.shape[-1] if np.ndim(static.x) == 3 else 0))
        if self.dim not in (2, 3):
            raise ConfigError(f"RecordingWriter: dim must be 2 or 3 (got {self.dim}).")
        self.frames_logged: list[int] = []
        self._rec = None
        self._tmp: Path | None = None
        self._closed = False
        self._fields_checked = False
        self._logged_bytes = 0

    # ---- lifecycle -------------------------------------------------------------------------
    def _points(self):
        import rerun as rr

        return rr.Points2D if self.dim == 2 else rr.Points3D

    def open(self) -> "RecordingWriter":
        import rerun as rr
        import rerun.blueprint as rrb

        if self._rec is not None:
            return self
        self._tmp = temp_path(self.path)
        try:
            rec = rr.RecordingStream(self.app_id, recording_id=self.recording_id)
            spatial = rrb.Spatial2DView(origin="/world", name="particles") if self.dim == 2 else \
                rrb.Spatial3DView(origin="/world", name="particles")
            blueprint = rrb.Blueprint(rrb.Horizontal(
                spatial,
                rrb.Vertical(rrb.TimeSeriesView(origin="/metrics", name="metrics"),
                             rrb.TextDocumentView(origin="/scene", name="scene"), row_shares=[3, 1]),
                column_shares=[2, 1]))
            rec.save(self._tmp, default_blueprint=blueprint)
            self._rec = rec
            self._log_static()
        except BaseException:
            self._shutdown()
            discard(self._tmp)
            raise
        return self

    def __enter__(self) -> "RecordingWriter":
        return self.open()

    def __exit__(self, exc_type, exc, tb) -> bool:
        self.close(exc)
        return False

    def _shutdown(self) -> None:
        if self._rec is not None:
            self._rec.flush()
            self._rec.disconnect()
            self._rec = None

    def close(self, exc: BaseException | None = None) -> Path | None:
        """Flush and publish the recording; with ``exc`` and no frame logged (or a full disk, which
        ``OutputError`` reports), nothing is published: the recording can be made again from the
        trajectory with ``task=replay``."""
        import rerun as rr

        if self._closed:
            return self.path
        self._closed = True
        if self._rec is None:
            if exc is not None:
                return None
            self.open()
        try:
            if exc is not None:
                if not self.frames_logged or isinstance(exc, OutputError):  # a full disk: keep nothing
                    self._shutdown()
                    discard(self._tmp)
                    return None
                from ..core.signals import stop_reason

                what = "diverged" if isinstance(exc, SimulationDiverged) else stop_reason(exc)
                self._rec.log("scene/status", rr.TextDocument(f"**Run {what}** after frame {self.frames_logged[-1]}: "
                                                              f"{exc}", media_type=rr.MediaType.MARKDOWN),
                              static=True)
            self._shutdown()
            publish(self._tmp, self.path, self.overwrite)
        except BaseException as err:
            self._rec = None
            full = self._disk_full(err)
            discard(self._tmp)
            if full:
                raise OutputError(self.path, "no space left on device", "the partial recording was removed") from None
            raise
        return self.path

    def _disk_full(self, err: BaseException) -> bool:
        """rerun's file sink reports a full disk only as "File-writer thread shut down prematurely"."""
        return isinstance(err, (OSError, RuntimeError)) and not isinstance(err, OutputError) \
            and free_bytes(self.path) < SPACE_MARGIN

    # ---- static data -----------------------------------------------------------------------
    def _static_colors(self) -> np.ndarray | None:
        s = self.static
        if self.color_by == "material":
            return PALETTE[np.asarray(s.material_id) % len(PALETTE)]
        if self.color_by == "body":
            return PALETTE[np.asarray(s.body_id) % len(PALETTE)]
        return None

    def _describe(self) -> str:
        s, meta = self.static, self.static.meta or {}
        lines = ["# mpmlab scene", "",
                 f"scene **{_md_escape(meta.get('scene', '?'))}**, dim {self.dim}, backend "
                 f"**{_md_escape(meta.get('backend', '?'))}**, transfer **{_md_escape(meta.get('transfer', '?'))}**, "
                 f"precision **{_md_escape(meta.get('precision', '?'))}**, dt {meta.get('dt', '?')} s, "
                 f"dx {meta.get('dx', '?')} m, {len(s.mass)} particles", "",
                 "| id | law | parameters | particles | provenance |", "|---|---|---|---|---|"]
        for k, m in enumerate(s.materials):
            names = list(m.get("param_names", []))
            start, stop = int(m.get("start", 0)), int(m.get("stop", 0))
            vals = s.params[start, : len(names)] if stop > start and len(s.params) else []
            prm = ", ".join(f"{n}={float(val):.4g}" for n, val in zip(names, vals))
            lines.append(f"| {k} | {_md_escape(m.get('law', '?'))} | {_md_escape(prm)} | {start}..{stop} | "
                         f"{_md_escape(m.get('provenance', ''))} |")
        lines += ["", f"colour: **{self.color_by}**"]
        if self.color_by in ("material", "body"):
            ids = np.unique(s.material_id if self.color_by == "material" else s.body_id)
            lines.append(", ".join("{} #{:02x}{:02x}{:02x}".format(int(i), *PALETTE[int(i) % len(PALETTE)])
                                   for i in ids))
        elif self.color_range is not None:
            lines.append(f"viridis over [{self.color_range[0]:.4g}, {self.color_range[1]:.4g}]")
        else:
            lines.append("viridis over each frame's min..max")
        lines += ["", "```json", json.dumps(json.loads(to_json(meta)), indent=2), "```"]
        return "\n".join(lines)

    def _log_static(self) -> None:
        import rerun as rr

        rec, s, meta = self._rec, self.static, self.static.meta or {}
        rec.log("scene/metadata", rr.TextDocument(self._describe(), media_type=rr.MediaType.MARKDOWN), static=True)
        radii = (0.5 * np.asarray(s.volume, dtype=np.float64) ** (1.0 / self.dim)).astype(np.float32)
        colors = self._static_colors()
        kw = {"radii": radii}
        if colors is not None:
            kw["colors"] = colors
        rec.log("world/particles", self._points().from_fields(**kw), static=True)
        if "grid_origin" in meta and "grid_shape" in meta and "dx" in meta:
            lo = np.asarray(meta["grid_origin"], dtype=np.float64)
            size = (np.asarray(meta["grid_shape"], dtype=np.float64) - 1.0) * float(meta["dx"])
            box = rr.Boxes2D(mins=[lo], sizes=[size]) if self.dim == 2 else \
                rr.Boxes3D(mins=[lo], sizes=[size])
            rec.log("world/domain", box, static=True)

    # ---- frames ----------------------------------------------------------------------------
    def __call__(self, frame_index: int, npstate: dict) -> None:
        """The rollout ``on_frame`` callback."""
        from .metrics import state_metrics

        # "time"/"step": added by an adaptive-dt rollout (the float64 sum of the steps taken)
        names = [k for k in npstate if k not in ("x", "v", "t", "time", "step") and not k.endswith("_particles")]
        fields = {k: npstate[k] for k in names}
        fp = {k: npstate[k + "_particles"] for k in names if k + "_particles" in npstate}
        m = state_metrics(self.static, npstate) if self.metrics else None
        m = {k: a[0] for k, a in m.items()} if m else None
        t = float(npstate["time"]) if "time" in npstate else float(npstate.get("t", np.nan))
        self.add_frame(frame_index, npstate["x"], npstate["v"], t, fields, fp, m)

    def add_frame(self, frame_index: int, x, v, time: float, fields: dict | None = None,
                  field_particles: dict | None = None, metrics: dict | None = None, force: bool = False) -> None:
        """Log one frame: particles if ``frame_index % every == 0`` (or ``force``), metrics always.

        ``metrics`` maps a name to a scalar or a vector (one entry per component) for this frame.
        """
        if self._closed:
            raise ConfigError("RecordingWriter is closed; open a new writer to log more frames.")
        self.open()
        fields = fields or {}
        if not self._fields_checked and self.color_by not in ("material", "body"):
            _check_color_by(self.color_by, list(fields))
            self._fields_checked = True
        rec = self._rec
        log_particles = force or int(frame_index) % self.every == 0
        # what this frame adds to the file, uncompressed: positions f32, colours u8x4 (rerun compresses)
        nbytes = (np.size(x) * 4 + (len(x) * 4 if self.color_by not in ("material", "body") else 0)) \
            if log_particles else 0
        # rerun writes from a background thread, in batches: what was logged may not be on disk yet
        self._logged_bytes += nbytes + 64 * len(metrics or {})
        ensure_space(self.path, self._logged_bytes - os.path.getsize(self._tmp), f"frame {frame_index}")
        try:
            self._log_frame(rec, frame_index, x, v, time, fields, field_particles, metrics, log_particles)
        except BaseException as err:
            if self._disk_full(err):
                raise OutputError(self.path, "no space left on device", f"at frame {frame_index}") from None
            raise

    def _log_frame(self, rec, frame_index, x, v, time, fields, field_particles, metrics, log_particles) -> None:
        import rerun as rr

        rec.set_time("frame", sequence=int(frame_index))
        if np.isfinite(time):
            rec.set_time("sim_time", duration=float(time))
        if log_particles:
            P = self._points()
            x = np.asarray(x)
            if self.color_by in ("material", "body"):
                rec.log("world/particles", P(x))
            else:
                val = particle_scalar(self.color_by, v, fields, field_particles or {}, len(x))
                if self.color_range is not None:
                    lo, hi = self.color_range
                else:
                    fin = val[np.isfinite(val)]
                    lo, hi = (float(fin.min()), float(fin.max())) if fin.size else (0.0, 1.0)
                rec.log("world/particles", P(x), P.from_fields(colors=scalar_colors(val, lo, hi)))
            self.frames_logged.append(int(frame_index))
        for name, value in (metrics or {}).items():
            value = np.asarray(value, dtype=np.float64)
            if value.ndim == 0:
                rec.log(f"metrics/{name}", rr.Scalars(float(value)))
            else:
                for k, c in enumerate(value.reshape(-1)):
                    label = _AXES[k] if value.size <= 3 else str(k)
                    rec.log(f"metrics/{name}/{label}", rr.Scalars(float(c)))


def write_recording(path: str | os.PathLike, traj: Trajectory, color_by: str = "material", every: int = 1,
                    metrics: dict | bool | None = None, app_id: str = "mpmlab", recording_id: str | None = None,
                    overwrite: bool = False, color_range: tuple[float, float] | None = None) -> Path:
    """Write ``traj`` as a rerun .rrd recording with a default blueprint (no viewer needed).

    Args:
        path: target .rrd file (written atomically).
        traj: the trajectory.
        color_by: ``material`` (default), ``body``, ``speed``, or, where the trajectory has the field,
            ``J`` (from J or F), ``eps_p``, ``stress`` (Frobenius norm of sigma). Others raise
            ``ConfigError`` listing the possible ones.
        every: log the particles of frames 0, every, 2 every, ... and the last frame; metrics are
            logged for all frames.
        metrics: None or True: ``mpmlab.io.metrics.compute_metrics(traj)``; False: none; a dict
            ``{name: array [T] or [T, k]}``: those.
        app_id, recording_id: rerun ids.
        overwrite: replace an existing file (otherwise that raises ``ConfigError``).
        color_range: (lo, hi) of a scalar colouring; default: min..max over the logged frames.

    Returns:
        The path written.
    """
    from .metrics import compute_metrics

    if int(every) < 1:
        raise ConfigError(f"write_recording: every must be >= 1 (got {every}).")
    _check_color_by(color_by, list(traj.fields))
    T = traj.frame_count
    if metrics is None or metrics is True:
        metrics = compute_metrics(traj)
    elif metrics is False:
        metrics = {}
    metrics = {k: np.asarray(a) for k, a in metrics.items()}
    for k, a in metrics.items():
        if len(a) != T:
            raise ConfigError(f"write_recording: metric '{k}' has {len(a)} entries but the trajectory has {T} frames.")
    kept = sorted(set(range(0, T, int(every))) | ({T - 1} if T else set()))

    def frame_fields(i):
        return {k: a[i] for k, a in traj.fields.items()}

    if color_by not in ("material", "body") and color_range is None and kept:
        vals = np.concatenate([particle_scalar(color_by, traj.v[i], frame_fields(i), traj.field_particles,
                                               traj.particle_count) for i in kept])
        fin = vals[np.isfinite(vals)]
        color_range = (float(fin.min()), float(fin.max())) if fin.size else (0.0, 1.0)
    w = RecordingWriter(path, traj, color_by=color_by, color_range=color_range, every=every, metrics=False,
                        app_id=app_id, recording_id=recording_id, overwrite=overwrite)
    with w:
        kept_set = set(kept)
        for i in range(T):
            w.add_frame(i, traj.x[i], traj.v[i], float(traj.time[i]), frame_fields(i), traj.field_particles,
                        {k: a[i] for k, a in metrics.items()}, force=i in kept_set)
    return w.path


# ---- reading back ------------------------------------------------------------------------------
def _entity(entity: str) -> str:
    return "/" + entity.strip("/")


def read_recording_component(path: str | os.PathLike, entity: str, component: str,
                             index: str = "frame") -> dict[Any, list]:
    """``{index value (None for static): [row values as NumPy arrays]}`` of one component of an entity,
    e.g. ``read_recording_component(p, "world/particles", "Points2D:colors")``."""
    from rerun.chunk import RrdReader

    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"recording '{path}' does not exist; check the path.")
    out: dict[Any, list] = {}
    for ch in RrdReader(str(path)).stream().filter(content=_entity(entity), components=component):
        rb = ch.to_record_batch()
        if component not in rb.schema.names:
            continue
        col = rb.column(component)
        keys = rb.column(index).to_numpy() if index in rb.schema.names else [None] * rb.num_rows
        for key, row in zip(keys, col):
            if not row.is_valid:
                continue
            vals = row.values
            arr = vals.flatten().to_numpy(zero_copy_only=False) if hasattr(vals, "flatten") else \
                vals.to_numpy(zero_copy_only=False)
            if hasattr(vals.type, "list_size"):
                arr = arr.reshape(len(vals), vals.type.list_size)
            out.setdefault(None if key is None else int(key), []).append(np.asarray(arr))
    return out


def read_recording_positions(path: str | os.PathLike, entity: str = "world/particles") -> dict[int, np.ndarray]:
    """``{frame: positions [N, D] float32}`` of the particles logged in a recording."""
    for comp in ("Points3D:positions", "Points2D:positions"):
        rows = read_recording_component(path, entity, comp)
        if rows:
            return {k: v[-1] for k, v in rows.items() if k is not None}
    return {}


def unpack_colors(packed: np.ndarray) -> np.ndarray:
    """rerun's packed 0xRRGGBBAA u32 colours -> [n, 4] u8."""
    p = np.asarray(packed, dtype=np.uint32)
    return np.stack([(p >> 24) & 255, (p >> 16) & 255, (p >> 8) & 255, p & 255], axis=-1).astype(np.uint8)


def read_recording_metrics(path: str | os.PathLike, timeline: str = "frame") -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """``{name: (frames, values)}`` of every ``rr.Scalars`` series under ``metrics/`` (``timeline``:
    ``frame`` for simulation recordings, ``epoch`` for ``task=inverse``)."""
    from rerun.chunk import RrdReader

    if not Path(path).is_file():
        raise ConfigError(f"recording '{path}' does not exist; check the path.")
    out: dict[str, dict[int, float]] = {}
    for ch in RrdReader(str(path)).stream().filter(content="/metrics/**", is_static=False,
                                                   components="Scalars:scalars"):
        rb = ch.to_record_batch()
        name = str(ch.entity_path).strip("/").removeprefix("metrics/")
        frames = rb.column(timeline).to_numpy()
        for f, row in zip(frames, rb.column("Scalars:scalars")):
            out.setdefault(name, {})[int(f)] = float(row.values.to_numpy()[0])
    return {k: (np.array(sorted(d)), np.array([d[f] for f in sorted(d)])) for k, d in out.items()}
