"""rerun (.rrd) recordings of trajectories, written without a viewer and read back for tests.

Layout of a recording (rerun-sdk 0.41, one explicit ``rr.RecordingStream``, never the global one):

* timelines ``frame`` (sequence: the trajectory's frame index) and ``sim_time`` (duration, seconds);
* ``world``: in 2D a ``Transform3D`` with scale (1, -1, 1), so that +y (against gravity) is drawn
  upwards (rerun's 2D views draw +y downwards); in 3D ``ViewCoordinates`` with the up axis against
  gravity;
* ``world/particles``: ``Points2D``/``Points3D`` positions per kept frame; radii ``0.5 * volume^(1/D)``
  (static, the particles touch; one value when all particles have the same volume); colours static
  (``material``, ``body``: a fixed palette) or per frame (a scalar through :data:`COLORMAP`; particles
  without a value are grey); beside them, per kept frame, ``Particle:values``: one struct per particle
  with ``speed`` [m/s] and, where the trajectory has them, ``J``, ``eps_p``, ``stress_norm`` [Pa] (NaN
  for a particle without the field), then ``material_id`` and ``particle_id``: what hovering a particle
  shows (rerun's hover card lists at most 3 per-particle components, so everything else stays off this
  entity). With ``color_variants=True`` also ``ParticleColors:colors``, a struct of one colour per
  colouring (``speed``, ``J``, ..., ``material``, ``body``): the viewer then recolours without a rerun
  (selection panel > Points > colors: source ``ParticleColors:colors``, selector ``.J``), at the price
  of 4 bytes per particle and colouring and of the hover values (the card shows only a summary);
* ``world/domain``: the grid's extent as a grey wireframe box (static);
* ``legend/colors``: a colour bar (scalar colourings) or the material / body swatches, a PNG image;
* ``metrics/<name>``: ``rr.Scalars`` per frame (vector metrics split into ``<name>/x``, ``/y``, ``/z``),
  each with a ``SeriesLines`` name that carries its unit; NaN values are not logged;
* ``world/<name>`` line strips given to :func:`write_recording` (``line_strips``), logged at one frame
  each: e.g. ``world/deposit_profile``, a granular deposit's final profile (``task=simulate`` with
  ``task.runout``; its front and wall height are the ``metrics/runout_*`` series);
* ``derived/gravity_potential_energy_rel`` and ``derived/total_energy``: the gravitational energy
  relative to frame 0 and the total energy (kinetic + that + elastic), as in ``energy.png``;
* ``scene/metadata``: a markdown ``TextDocument`` (static) with backend, transfer, precision, laws,
  the colour legend, the per-particle values and the full ``meta`` as JSON;
* a default blueprint: the particle view (2D: framed on the particles' extent over the run; 3D: a
  camera that frames the domain) with its colour legend, and one time series view per quantity
  family (energy, linear momentum, angular momentum, mass, step time, each titled with its unit).

The file is written to a temporary file next to the target and published atomically.
"""
from __future__ import annotations

import json
import math
import os
import uuid
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from ..core.errors import ConfigError, SimulationDiverged
from ..core.state import Trajectory
from .files import (SPACE_MARGIN, AtomicWriter, OutputError, check_target, discard, ensure_space, free_bytes, publish,
                    temp_path)
from .h5 import to_json

#: Material / body colours (Tableau 10), cycled.
PALETTE = np.array([[31, 119, 180], [255, 127, 14], [44, 160, 44], [214, 39, 40], [148, 103, 189],
                    [140, 86, 75], [227, 119, 194], [127, 127, 127], [188, 189, 34], [23, 190, 207]], np.uint8)
MISSING_COLOR = np.array([160, 160, 160], np.uint8)
#: Scalar colourings: viridis from 0.32 on (its darkest third left out), so the lowest value keeps a 3:1 contrast
#: against the viewer's near-black background (viridis(0) has 1.3:1 and vanishes).
COLORMAP = ("viridis", 0.32, 1.0)
DOMAIN_COLOR = np.array([150, 150, 150], np.uint8)
#: line strips drawn over the particles (a deposit profile)
LINE_COLOR = (240, 60, 60)
VIEWER_BACKGROUND = (13, 13, 13)
_AXES = ("x", "y", "z")
_AXIS_COLORS = {"x": [230, 85, 80], "y": [90, 200, 90], "z": [80, 150, 240]}

_SCALAR_NEEDS = {"speed": "always available", "J": "needs field J or F", "eps_p": "needs field eps_p",
                 "stress": "needs field sigma"}
#: per-particle quantities: color_by name -> (component name beside the positions, label, unit)
QUANTITIES = {"speed": ("speed", "speed", "m/s"), "J": ("J", "J = det F (volume ratio)", ""),
              "eps_p": ("eps_p", "plastic strain", ""), "stress": ("stress_norm", "|σ| (Frobenius)", "Pa")}
#: the fields of ``Particle:values`` besides the quantities' (int32)
ID_FIELDS = ("material_id", "particle_id")


def color_choices(fields: Sequence[str]) -> list[str]:
    """The ``color_by`` values possible for a trajectory carrying ``fields``."""
    out = ["material", "body", "speed"]
    if "J" in fields or "F" in fields:
        out.append("J")
    if "eps_p" in fields:
        out.append("eps_p")
    if "sigma" in fields:
        out.append("stress")
    # any other state field a law declares (a hardening variable, a back-stress): coloured by its
    # value, or by its norm when it is not a scalar
    extra = [f for f in fields if f not in _PRESENTED and f not in out]
    for f in extra:          # a declared field becomes a quantity (hover value, colour bar) like the built-ins
        QUANTITIES.setdefault(f, (f, *_declared_label(f)))
    return out + extra


def _declared_label(name: str) -> tuple[str, str]:
    """(label, unit) of a law state field from its declaration (``StateField.doc``/``unit``)."""
    from ..core.interfaces import registered_state_fields

    f = registered_state_fields().get(name)
    return (name, "") if f is None else ((f.doc or name), ("" if f.unit == "-" else f.unit))


#: stored fields with a colouring of their own above (J from F, |sigma| as stress) or none (F, C)
_PRESENTED = ("F", "C", "J", "sigma", "eps_p")


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
    elif color_by == "eps_p" or (color_by in fields and color_by not in _PRESENTED):
        key = color_by
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


def _colormap():
    import matplotlib
    from matplotlib.colors import ListedColormap

    name, a, b = COLORMAP
    return ListedColormap(matplotlib.colormaps[name](np.linspace(a, b, 256)), name=f"{name}_{a:g}_{b:g}")


def scalar_colors(values: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """RGB u8 [N, 3] of ``values`` through :data:`COLORMAP` over [lo, hi]; NaN -> grey."""
    span = hi - lo if np.isfinite(hi - lo) and hi > lo else 1.0
    t = np.clip((np.asarray(values, dtype=np.float64) - lo) / span, 0.0, 1.0)
    rgb = (np.asarray(_colormap()(np.nan_to_num(t)))[:, :3] * 255.0 + 0.5).astype(np.uint8)
    rgb[~np.isfinite(values)] = MISSING_COLOR
    return rgb


def quantities_for(fields: Sequence[str]) -> list[str]:
    """The per-particle quantities (``QUANTITIES`` keys) a trajectory carrying ``fields`` has."""
    return [q for q in color_choices(fields) if q in QUANTITIES]


def quantity_label(q: str) -> str:
    """``'speed [m/s]'``: the label and unit of a per-particle quantity (or of ``material``/``body``)."""
    if q not in QUANTITIES:
        return q
    _, label, unit = QUANTITIES[q]
    return f"{label} [{unit}]" if unit else label


def unique_recording_id(*parts: Any) -> str:
    """A readable recording id that no other recording shares: ``'-'.join(parts)`` plus 8 random hex
    digits (two recordings with one id merge when the viewer opens both)."""
    head = "-".join(str(p) for p in parts if p not in (None, ""))
    return f"{head}-{uuid.uuid4().hex[:8]}" if head else uuid.uuid4().hex


def _md_escape(s: str) -> str:
    return str(s).replace("|", "\\|")


def _rgb_image(fig) -> np.ndarray:
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[..., :3].copy()


def legend_image(color_by: str, *, color_range: tuple[float, float] | None = None,
                 entries: Sequence[tuple[str, Sequence[int]]] = (), width: int = 760) -> np.ndarray:
    """An RGB u8 image [H, W, 3] of the colour legend: a colour bar with ticks and the quantity's unit
    for a scalar colouring (``color_range`` None: each frame's own min..max), swatches and names
    (``entries``: (label, rgb)) for ``material`` / ``body``. Drawn on the viewer's background."""
    from matplotlib.figure import Figure

    bg = np.array(VIEWER_BACKGROUND) / 255.0
    fg = (0.86, 0.86, 0.86)
    dpi = 100
    fig = Figure(figsize=(width / dpi, 0.9), dpi=dpi, facecolor=bg)
    if color_by in QUANTITIES:
        from matplotlib.cm import ScalarMappable
        from matplotlib.colors import Normalize

        ax = fig.add_axes((0.02, 0.62, 0.96, 0.3))
        lo, hi = color_range if color_range is not None else (0.0, 1.0)
        if not (np.isfinite(lo) and np.isfinite(hi) and hi > lo):
            lo, hi = (lo, lo + 1.0) if np.isfinite(lo) else (0.0, 1.0)
        cb = fig.colorbar(ScalarMappable(norm=Normalize(lo, hi), cmap=_colormap()), cax=ax, orientation="horizontal")
        label = quantity_label(color_by) + ("  (each frame's own min .. max)" if color_range is None else "") + \
            "   grey: no value"
        if color_range is None:
            cb.set_ticks([lo, hi], labels=["frame min", "frame max"])
        cb.set_label(label, color=fg, fontsize=14)
        cb.ax.tick_params(colors=fg, labelsize=13)
        cb.outline.set_edgecolor(fg)
    else:
        ax = fig.add_axes((0, 0, 1, 1))
        ax.set_axis_off()
        ax.set_xlim(0, 1)
        ax.set_ylim(0, 1)
        fs = 14 if len(entries) <= 4 else 11
        char = 0.6 * fs * dpi / 72.0             # a character's width in pixels, about
        place, x, row = [], 14.0, 0
        for label, _ in entries:
            w = 26.0 + char * len(label) + 30.0
            if x + w > width and x > 14.0:
                x, row = 14.0, row + 1
            place.append((x, row))
            x += w
        rows = row + 1
        for (label, rgb), (x, row) in zip(entries, place):
            y = 0.5 if rows == 1 else 0.8 - 0.6 * row / (rows - 1)
            ax.scatter([x / width], [y], s=200 if rows <= 2 else 90, color=np.asarray(rgb[:3]) / 255.0,
                       edgecolors=fg, linewidths=0.6)
            ax.text((x + 16.0) / width, y, label, color=fg, fontsize=fs if rows <= 2 else 9, va="center")
    return _rgb_image(fig)


def _png(img: np.ndarray) -> bytes:
    """PNG bytes of an RGB u8 image (a legend: a few kB instead of width x height x 3 bytes)."""
    import io

    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.asarray(img, dtype=np.uint8)).save(buf, format="PNG", optimize=True)
    return buf.getvalue()


def _up_axis(gravity, dim: int) -> int | None:
    g = np.asarray(gravity if gravity is not None else [], dtype=np.float64).reshape(-1)
    if g.shape != (dim,) or not np.any(g):
        return None
    k = int(np.argmax(np.abs(g)))
    return k if g[k] < 0 else None


def frame_bounds_2d(lo, hi, radius: float = 0.0, gravity=None, min_aspect: float = 0.5,
                    max_aspect: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """The 2D view's bounds around the particles' extent [lo, hi]: padded by 4 % and a particle
    radius, no flatter than ``min_aspect`` (height / width) and no narrower than ``1 / max_aspect``; the
    added room goes above the particles (against gravity), so particles resting on the floor are drawn
    in the lower part of the view."""
    lo, hi = np.asarray(lo, np.float64).copy(), np.asarray(hi, np.float64).copy()
    span = np.maximum(hi - lo, 1e-9)
    pad = 0.04 * float(span.max()) + 2.0 * float(radius)
    lo, hi = lo - pad, hi + pad
    w, h = hi - lo
    if h < min_aspect * w:
        g = np.asarray(gravity, np.float64).reshape(-1) if gravity is not None else np.zeros(2)
        extra = min_aspect * w - h
        if g.shape == (2,) and g[1] < 0:
            hi[1] += extra
        elif g.shape == (2,) and g[1] > 0:
            lo[1] -= extra
        else:
            lo[1] -= extra / 2
            hi[1] += extra / 2
    elif w * max_aspect < h:
        extra = h / max_aspect - w
        lo[0] -= extra / 2
        hi[0] += extra / 2
    return lo, hi


def eye_for_box(lo, hi, up_axis: int | None, fov_y_deg: float = 55.0) -> dict:
    """``EyeControls3D`` arguments of an orbit camera that sees the whole box [lo, hi] from above and
    in front (the up axis against gravity; +y when unknown)."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    c = 0.5 * (lo + hi)
    r = 0.5 * float(np.linalg.norm(hi - lo))
    up = up_axis if up_axis is not None else 1
    up_vec = np.zeros(3)
    up_vec[up] = 1.0
    # right-handed (right, up, toward the viewer): (x, y, z) for y up, (x, z, -y) for z up, (y, x, -z) for x up
    right = np.zeros(3)
    right[0 if up != 0 else 1] = 1.0
    toward = np.cross(right, up_vec)
    d = 0.55 * right + 0.5 * up_vec + 0.95 * toward
    d /= np.linalg.norm(d)
    dist = 1.08 * r / math.sin(math.radians(fov_y_deg) / 2)
    return {"position": (c + dist * d).tolist(), "look_target": c.tolist(), "eye_up": up_vec.tolist()}


def _series_style(entity: str, family: str, label: str, unit: str, index: int) -> tuple[str, list[int]]:
    comp = entity.rsplit("/", 1)[-1]
    name = f"{label}_{comp}" if comp in _AXES and label in ("p", "L") else label
    if family == "angular_momentum" and comp not in _AXES:
        name = f"{label}_z"
    color = _AXIS_COLORS.get(comp) if comp in _AXES else None
    if color is None:
        color = {"kinetic_energy": [255, 150, 40], "elastic_energy": [70, 190, 90],
                 "gravity_potential_energy": [90, 150, 230], "gravity_potential_energy_rel": [90, 150, 230],
                 "total_energy": [235, 235, 235], "mass": [220, 220, 220],
                 "step_time_ms": [180, 140, 230]}.get(entity.split("/")[1] if "/" in entity else entity)
    if color is None:
        color = PALETTE[index % len(PALETTE)].tolist()
    return (f"{name} [{unit}]" if unit else name), color


class RecordingWriter(AtomicWriter):
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
        app_id, recording_id: rerun application and recording ids (None: a unique one).
        overwrite: replace an existing file (otherwise that raises ``ConfigError``).
        extent: (lo, hi) of the particles over the run, to frame the 2D view on (default: the domain).
        ranges: {quantity: (lo, hi)} of the colour variants of the other quantities (default: each
            frame's own min..max).
        compile_time_s: the compilation time left out of ``step_time_ms`` (named in its plot title).
        particle_values: log ``Particle:values`` (what hovering a particle shows) beside the positions.
        color_variants: also log ``ParticleColors:colors``, one colour per colouring (recolour in the
            viewer; the hover card then shows only a summary).
    """

    def __init__(self, path: str | os.PathLike, static: Trajectory | None = None, *, stepper=None,
                 color_by: str = "material", color_range: tuple[float, float] | None = None, every: int = 1,
                 metrics: bool = True, app_id: str = "mpmlab", recording_id: str | None = None,
                 overwrite: bool = False, extent: tuple[Any, Any] | None = None,
                 ranges: dict[str, tuple[float, float]] | None = None, compile_time_s: float | None = None,
                 particle_values: bool = True, color_variants: bool = False):
        if (static is None) == (stepper is None):
            raise ConfigError("RecordingWriter needs exactly one of static= (a Trajectory) or stepper=.")
        if static is None:
            static = stepper._trajectory([], [], ())
        if int(every) < 1:
            raise ConfigError(f"RecordingWriter: every must be >= 1 (got {every}).")
        from ..core.interfaces import registered_state_fields

        # a law's declared field (a plugin's q) is checked against the first frame's fields (log_frame)
        if color_by not in ("material", "body", *_SCALAR_NEEDS) and color_by not in registered_state_fields():
            _check_color_by(color_by, ())
        AtomicWriter.__init__(self, path, overwrite)
        self.static = static
        self.color_by = color_by
        self.color_range = color_range
        self.every = int(every)
        self.metrics = metrics
        self.app_id = app_id
        self.recording_id = recording_id if recording_id is not None else unique_recording_id(
            (static.meta or {}).get("scene", "mpmlab"), Path(path).absolute().parent.name)
        self.extent = extent
        self.ranges = dict(ranges or {})
        self.compile_time_s = compile_time_s
        self.compile_left_out = False   # step_time_ms has no value at frame 1, the chunk that compiles
        self.particle_values = bool(particle_values)
        self.color_variants = bool(color_variants)
        meta = static.meta or {}
        self.dim = int(meta.get("dim", static.x.shape[-1] if np.ndim(static.x) == 3 else 0))
        if self.dim not in (2, 3):
            raise ConfigError(f"RecordingWriter: dim must be 2 or 3 (got {self.dim}).")
        self.frames_logged: list[int] = []
        self._rec = None
        self._fields_checked = False
        self._logged_bytes = 0
        self._quantities: list[str] | None = None      # per-particle quantities, from the first frame
        self._series: dict[str, tuple[str, str]] = {}   # plotted entity -> (family, series name), in order
        self._named: set[str] = set()                   # entities whose SeriesLines name was logged
        self._g0: float | None = None                   # gravitational energy of the first frame
        self._has_time = True                           # every frame so far had a finite sim_time

    # ---- lifecycle (mpmlab.io.files.AtomicWriter: open, with, close) -------------------------
    def _points(self):
        import rerun as rr

        return rr.Points2D if self.dim == 2 else rr.Points3D

    def _is_open(self) -> bool:
        return self._rec is not None

    def _start(self, tmp: Path) -> None:
        import rerun as rr

        rec = rr.RecordingStream(self.app_id, recording_id=self.recording_id)
        rec.save(tmp)   # the blueprint follows at close(), when the logged series are known
        self._rec = rec
        self._log_static()

    def _abort_start(self) -> None:
        self._shutdown()

    def _shutdown(self) -> None:
        if self._rec is not None:
            self._rec.flush()
            self._rec.disconnect()
            self._rec = None

    def close(self, exc: BaseException | None = None) -> Path | None:
        """Flush and publish the recording; with ``exc`` and no frame logged (or a full disk, which
        ``OutputError`` reports), nothing is published: the recording can be made again from the
        trajectory with ``task=replay``. Closing again returns ``path``."""
        if self._closed:
            return self.path
        return AtomicWriter.close(self, exc)

    def _finish(self, exc: BaseException | None) -> Path | None:
        import rerun as rr

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
            self._rec.send_blueprint(self.blueprint(), make_active=True, make_default=True)
            self._shutdown()
            self._publish()
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

    # ---- blueprint -------------------------------------------------------------------------
    def _domain(self) -> tuple[np.ndarray, np.ndarray] | None:
        meta = self.static.meta or {}
        if "grid_origin" in meta and "grid_shape" in meta and "dx" in meta:
            lo = np.asarray(meta["grid_origin"], dtype=np.float64)
            return lo, lo + (np.asarray(meta["grid_shape"], dtype=np.float64) - 1.0) * float(meta["dx"])
        return None

    def _radius(self) -> float:
        vol = np.asarray(self.static.volume, dtype=np.float64)
        return float(0.5 * vol.max() ** (1.0 / self.dim)) if vol.size else 0.0

    def view_bounds_2d(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The 2D particle view's bounds (in the recording's y-up coordinates)."""
        b = self._bounds_2d()
        return None if b is None else b[0]

    def _bounds_2d(self) -> tuple[tuple[np.ndarray, np.ndarray], bool] | None:
        """(bounds, wide): a scene much wider than tall (a shallow dam break) gets the full window
        width and a flatter view; others a view at least half as tall as wide."""
        box = self.extent if self.extent is not None else self._domain()
        if box is None:
            return None
        g, r = (self.static.meta or {}).get("gravity"), self._radius()
        lo, hi = frame_bounds_2d(box[0], box[1], r, g, min_aspect=0.0)
        wide = bool((hi[0] - lo[0]) > 2.5 * (hi[1] - lo[1]))
        return frame_bounds_2d(box[0], box[1], r, g, min_aspect=0.3 if wide else 0.5), wide

    def _particle_view(self):
        import rerun.blueprint as rrb

        meta = self.static.meta or {}
        if self.dim == 2:
            kw = {}
            b = self.view_bounds_2d()
            if b is not None:   # the view's space is "/", where /world is flipped: y -> -y
                kw["visual_bounds"] = rrb.VisualBounds2D(x_range=[b[0][0], b[1][0]], y_range=[-b[1][1], -b[0][1]])
            return rrb.Spatial2DView(origin="/", contents=["/world/**"], name="particles", **kw)
        box = self._domain()
        kw = {}
        if box is None and self.extent is not None:
            box = self.extent
        if box is not None:
            kw["eye_controls"] = rrb.EyeControls3D(**eye_for_box(box[0], box[1], _up_axis(meta.get("gravity"), 3)))
        return rrb.Spatial3DView(origin="/world", name="particles", **kw)

    def _legend_title(self) -> str:
        return f"colour: {quantity_label(self.color_by)}" if self.color_by in QUANTITIES else f"colour: {self.color_by}"

    def plot_views(self) -> dict:
        """``{family: TimeSeriesView}``: one view per quantity family logged, in a fixed order, each
        titled with its unit."""
        import rerun.blueprint as rrb
        from .metrics import FAMILY_TITLES, metric_info

        families: dict[str, list[str]] = {}
        for entity, (family, _) in self._series.items():
            families.setdefault(family, []).append("/" + entity)
        order = [f for f in FAMILY_TITLES if f in families] + [f for f in families if f not in FAMILY_TITLES]
        views = {}
        for family in order:
            unit = {"energy": metric_info("kinetic_energy", self.dim)[2],
                    "linear_momentum": metric_info("linear_momentum", self.dim)[2],
                    "angular_momentum": metric_info("angular_momentum", self.dim)[2],
                    "mass": metric_info("mass", self.dim)[2], "step_time": "ms/step",
                    "runout": "m"}.get(family, "")
            title = FAMILY_TITLES.get(family, family.replace("_", " "))
            title = f"{title} [{unit}]" if unit else title
            views[family] = rrb.TimeSeriesView(origin="/", contents=families[family], name=title,
                                               plot_legend=rrb.PlotLegend(corner="LeftTop"))
        return views

    def blueprint(self):
        """The default blueprint (see the module docstring)."""
        import rerun.blueprint as rrb

        particles = self._particle_view()
        legend = rrb.Spatial2DView(origin="/legend", name=self._legend_title())
        plots = self.plot_views()
        scene = rrb.TextDocumentView(origin="/scene", name="scene")
        timeline = "sim_time" if self.frames_logged and self._has_time else "frame"
        panels = [rrb.BlueprintPanel(state="collapsed"), rrb.SelectionPanel(state="collapsed"),
                  rrb.TimePanel(state="collapsed", timeline=timeline, play_state="following")]
        bw = self._bounds_2d() if self.dim == 2 else None
        v = dict(plots)
        first = [v.pop(f) for f in ("energy",) if f in v]
        momenta = [v.pop(f) for f in ("linear_momentum", "angular_momentum") if f in v]
        small = [v.pop(f) for f in ("mass", "step_time") if f in v]
        others = list(v.values())
        if bw is not None and bw[1]:
            # a wide, shallow 2D scene (a dam break): the particles across the width, the plots below
            cols = first + [rrb.Vertical(*momenta)] * bool(momenta) + [rrb.Vertical(*small)] * bool(small) + \
                others + [scene]
            return rrb.Blueprint(rrb.Vertical(particles, legend, rrb.Horizontal(*cols), row_shares=[5, 1.1, 4.5]),
                                 *panels)
        rows, shares = [], []
        for view, share in ([(x, 2.0) for x in first] + [(x, 1.25) for x in momenta] +
                            ([(rrb.Horizontal(*small), 1.25)] if small else []) + [(x, 1.25) for x in others]):
            rows.append(view)
            shares.append(share)
        rows.append(scene)
        shares.append(1.0)
        left = rrb.Vertical(particles, legend, row_shares=[9, 1.1])
        return rrb.Blueprint(rrb.Horizontal(left, rrb.Vertical(*rows, row_shares=shares), column_shares=[1.25, 1]),
                             *panels)

    # ---- static data -----------------------------------------------------------------------
    def _static_colors(self, color_by: str | None = None) -> np.ndarray | None:
        s, color_by = self.static, color_by or self.color_by
        if color_by == "material":
            return PALETTE[np.asarray(s.material_id) % len(PALETTE)]
        if color_by == "body":
            return PALETTE[np.asarray(s.body_id) % len(PALETTE)]
        return None

    def _material_names(self) -> dict[int, str]:
        out = {}
        for k, m in enumerate(self.static.materials):
            label = m.get("label") or m.get("name")
            law = m.get("law", "?")
            out[k] = f"{k} {law}" + (f" ({label})" if label and label != law else "")
        return out

    def _legend_entries(self) -> list[tuple[str, Sequence[int]]]:
        s = self.static
        if self.color_by == "material":
            names = self._material_names()
            return [(names.get(int(i), str(int(i))), PALETTE[int(i) % len(PALETTE)]) for i in np.unique(s.material_id)]
        if self.color_by == "body":
            return [(f"body {int(i)}", PALETTE[int(i) % len(PALETTE)]) for i in np.unique(s.body_id)]
        return []

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
            lines.append(f"{COLORMAP[0]} over [{self.color_range[0]:.4g}, {self.color_range[1]:.4g}]")
        else:
            lines.append(f"{COLORMAP[0]} over each frame's min..max")
        if self.particle_values:
            lines += ["", "Hover a particle for its values (Particle:values): speed [m/s]; where recorded, "
                      "J (= det F, the volume ratio), eps_p (the plastic strain), stress_norm (|σ|, the Frobenius "
                      "norm of the Cauchy stress [Pa]); material_id and particle_id (the index in "
                      "world/particles[i])."]
        if self.color_variants:
            lines += ["", "Recolour in the viewer: select the particles; in the selection panel, Points > colors: "
                      "source ParticleColors:colors, selector " + ", ".join(
                          f"`.{q}`" for q in (*QUANTITIES, "material", "body")) + " (those recorded)."]
        lines += ["", "```json", json.dumps(json.loads(to_json(meta)), indent=2), "```"]
        return "\n".join(lines)

    def _log_static(self) -> None:
        import rerun as rr

        rec, s, meta = self._rec, self.static, self.static.meta or {}
        rec.log("scene/metadata", rr.TextDocument(self._describe(), media_type=rr.MediaType.MARKDOWN), static=True)
        if self.dim == 2:
            rec.log("world", rr.Transform3D(scale=[1.0, -1.0, 1.0]), static=True)   # +y up on the screen
        else:
            up = _up_axis(meta.get("gravity"), 3)
            coords = {1: rr.ViewCoordinates.RIGHT_HAND_Y_UP, 2: rr.ViewCoordinates.RIGHT_HAND_Z_UP,
                      0: rr.ViewCoordinates.RIGHT_HAND_X_UP}[up if up is not None else 1]
            rec.log("world", coords, static=True)
        vol = np.asarray(s.volume, dtype=np.float64)
        radii = (0.5 * vol ** (1.0 / self.dim)).astype(np.float32)
        if radii.size and float(radii.max()) <= 1.0001 * float(radii.min()):
            radii = radii[:1]     # one radius for all: not a per-particle component (see the hover card)
        colors = self._static_colors()
        kw = {"radii": radii}
        if colors is not None:
            kw["colors"] = colors
        rec.log("world/particles", self._points().from_fields(**kw), static=True)
        box = self._domain()
        if box is not None:
            lo, size = box[0], box[1] - box[0]
            if self.dim == 2:
                dom = rr.Boxes2D(mins=[lo], sizes=[size], colors=[DOMAIN_COLOR], radii=rr.Radius.ui_points(1.0))
            else:
                dom = rr.Boxes3D(mins=[lo], sizes=[size], colors=[DOMAIN_COLOR], radii=rr.Radius.ui_points(1.0),
                                 fill_mode=rr.components.FillMode.MajorWireframe)
            rec.log("world/domain", dom, static=True)
        bw = self._bounds_2d() if self.dim == 2 else None
        img = legend_image(self.color_by, color_range=self.color_range, entries=self._legend_entries(),
                           width=1700 if bw is not None and bw[1] else 760)
        rec.log("legend/colors", rr.EncodedImage(contents=_png(img), media_type="image/png"), static=True)

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
        if self._quantities is None:
            self._quantities = quantities_for(list(fields)) if (self.particle_values or self.color_variants) else []
        rec = self._rec
        log_particles = force or int(frame_index) % self.every == 0
        # what this frame adds to the file, uncompressed: positions f32, the colours of a scalar colouring
        # u8x4, the per-particle values f32 and ids i32, the colour variants u8x4 (rerun compresses)
        nq = len(self._quantities)
        per_particle = 4 * np.shape(x)[-1] + (4 if self.color_by not in ("material", "body") else 0) + \
            ((4 * nq + 4 * len(ID_FIELDS)) if self.particle_values else 0) + \
            (4 * (nq + 2) if self.color_variants else 0)
        nbytes = len(x) * per_particle if log_particles else 0
        # rerun writes from a background thread, in batches: what was logged may not be on disk yet
        self._logged_bytes += nbytes + 64 * (len(metrics or {}) + 2)
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
        else:
            self._has_time = False
        if log_particles:
            P = self._points()
            x = np.asarray(x)
            n = len(x)
            values = {q: particle_scalar(q, v, fields, field_particles or {}, n) for q in self._quantities}
            if self.color_by in ("material", "body"):
                parts = [P(x)]
            else:
                val = values.get(self.color_by)
                if val is None:
                    val = particle_scalar(self.color_by, v, fields, field_particles or {}, n)
                lo, hi = self.color_range if self.color_range is not None else _finite_range(val)
                parts = [P(x), P.from_fields(colors=scalar_colors(val, lo, hi))]
            if self.particle_values:
                parts.append(rr.DynamicArchetype("Particle", components={"values": self._values_struct(values)}))
            if self.color_variants:
                parts.append(rr.DynamicArchetype("ParticleColors",
                                                 components={"colors": self._variants_struct(values)}))
            rec.log("world/particles", *parts)
            self.frames_logged.append(int(frame_index))
        self._log_metrics(rec, metrics or {})

    def add_line_strip(self, entity: str, points, frame_index: int, time: float = float("nan"),
                       color: Sequence[int] = LINE_COLOR, label: str | None = None) -> None:
        """Log a polyline [K, dim] (world coordinates) at ``frame_index`` as ``entity`` (under ``world/``:
        drawn in the particle view); it shows from that frame on."""
        import rerun as rr

        if self._closed:
            raise ConfigError("RecordingWriter is closed; open a new writer to log more.")
        pts = np.asarray(points, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != self.dim:
            raise ConfigError(f"line strip '{entity}': points must be [K, {self.dim}] (got shape {pts.shape}).")
        self.open()
        rec = self._rec
        rec.set_time("frame", sequence=int(frame_index))
        if np.isfinite(time):
            rec.set_time("sim_time", duration=float(time))
        strips = rr.LineStrips2D if self.dim == 2 else rr.LineStrips3D
        kw = {"labels": [label], "show_labels": False} if label else {}
        rec.log(entity, strips([pts[np.all(np.isfinite(pts), axis=1)]], colors=[list(color)],
                                radii=rr.Radius.ui_points(2.0), **kw))

    def _values_struct(self, values: dict):
        import pyarrow as pa

        s = self.static
        n = len(s.mass)
        arrays = [pa.array(np.asarray(values[q], dtype=np.float32)) for q in values]
        names = [QUANTITIES[q][0] for q in values]
        arrays += [pa.array(np.asarray(s.material_id, dtype=np.int32)), pa.array(np.arange(n, dtype=np.int32))]
        return pa.StructArray.from_arrays(arrays, names=[*names, *ID_FIELDS])

    def _variants_struct(self, values: dict):
        import pyarrow as pa

        cols, names = [], []
        for q, val in values.items():
            lo, hi = (self.color_range if q == self.color_by and self.color_range is not None else
                      self.ranges.get(q) or _finite_range(val))
            cols.append(scalar_colors(val, lo, hi))
            names.append(q)
        for c in ("material", "body"):
            cols.append(self._static_colors(c))
            names.append(c)
        return pa.StructArray.from_arrays([pa.array(_pack_rgba(c)) for c in cols], names=names)

    def _log_metrics(self, rec, metrics: dict) -> None:
        import rerun as rr
        from .metrics import metric_info

        def scalar(entity, value, family, label, unit, plot=True):
            if not np.isfinite(value):
                return          # NaN (e.g. the step time of frame 0): a gap, not a point
            if entity not in self._named:
                name, color = _series_style(entity, family, label, unit, len(self._named))
                rec.log(entity, rr.SeriesLines(names=name, colors=[color]), static=True)
                self._named.add(entity)
                if plot:
                    self._series[entity] = (family, name)
            rec.log(entity, rr.Scalars(float(value)))

        energies = {}
        for name, value in metrics.items():
            value = np.asarray(value, dtype=np.float64)
            family, label, unit = metric_info(name, self.dim)
            if name == "step_time_ms" and (self.compile_left_out or self.compile_time_s is not None):
                label = "per step, compile chunk left out" + (
                    f" ({self.compile_time_s:.3g} s)" if self.compile_time_s is not None else "")
            if value.ndim == 0:
                # the gravitational energy is plotted relative to frame 0 (derived/), beside the total
                scalar(f"metrics/{name}", float(value), family, label, unit, plot=name != "gravity_potential_energy")
                if family == "energy":
                    energies[name] = float(value)
            else:
                for k, c in enumerate(value.reshape(-1)):
                    comp = _AXES[k] if value.size <= 3 else str(k)
                    scalar(f"metrics/{name}/{comp}", float(c), family, label, unit)
        if energies:
            unit = metric_info("kinetic_energy", self.dim)[2]
            total = energies.get("kinetic_energy", 0.0) + energies.get("elastic_energy", 0.0)
            if "gravity_potential_energy" in energies and np.isfinite(energies["gravity_potential_energy"]):
                if self._g0 is None:
                    self._g0 = energies["gravity_potential_energy"]
                rel = energies["gravity_potential_energy"] - self._g0
                scalar("derived/gravity_potential_energy_rel", rel, "energy", "gravity (rel. to frame 0)", unit)
                total += rel
            if len(energies) > 1:
                scalar("derived/total_energy", total, "energy", "total", unit)


def _pack_rgba(rgb: np.ndarray) -> np.ndarray:
    """[N, 3] u8 -> rerun's packed 0xRRGGBBAA u32 (opaque)."""
    c = np.asarray(rgb, dtype=np.uint32)
    return (c[:, 0] << 24) | (c[:, 1] << 16) | (c[:, 2] << 8) | np.uint32(255)


def _finite_range(val: np.ndarray) -> tuple[float, float]:
    fin = np.asarray(val)[np.isfinite(val)]
    return (float(fin.min()), float(fin.max())) if fin.size else (0.0, 1.0)


def trajectory_ranges(traj: Trajectory, frames: Sequence[int], quantities: Sequence[str]
                      ) -> tuple[dict[str, tuple[float, float]], tuple[np.ndarray, np.ndarray] | None]:
    """({quantity: (min, max)} over ``frames``, (lo, hi) of the positions over ``frames``), reading
    one frame at a time (a trajectory's arrays may be lazy HDF5 datasets)."""
    lo = hi = None
    acc = {q: [np.inf, -np.inf] for q in quantities}
    for i in frames:
        x = np.asarray(traj.x[i], dtype=np.float64)
        if x.size:
            lo = x.min(0) if lo is None else np.minimum(lo, x.min(0))
            hi = x.max(0) if hi is None else np.maximum(hi, x.max(0))
        if quantities:
            v = traj.v[i]
            f = {k: a[i] for k, a in traj.fields.items()}
            for q in quantities:
                val = particle_scalar(q, v, f, traj.field_particles, traj.particle_count)
                fin = val[np.isfinite(val)]
                if fin.size:
                    acc[q][0], acc[q][1] = min(acc[q][0], float(fin.min())), max(acc[q][1], float(fin.max()))
    ranges = {q: ((a, b) if a <= b else (0.0, 1.0)) for q, (a, b) in acc.items()}
    return ranges, (None if lo is None else (lo, hi))


def write_recording(path: str | os.PathLike, traj: Trajectory, color_by: str = "material", every: int = 1,
                    metrics: dict | bool | None = None, app_id: str = "mpmlab", recording_id: str | None = None,
                    overwrite: bool = False, color_range: tuple[float, float] | None = None,
                    compile_time_s: float | None = None, particle_values: bool = True,
                    color_variants: bool = False,
                    line_strips: dict[str, tuple[int, Any]] | None = None) -> Path:
    """Write ``traj`` as a rerun .rrd recording with a default blueprint (no viewer needed).

    Args:
        path: target .rrd file (written atomically).
        traj: the trajectory (its arrays may be lazy HDF5 datasets: they are read frame by frame).
        color_by: ``material`` (default), ``body``, ``speed``, or, where the trajectory has the field,
            ``J`` (from J or F), ``eps_p``, ``stress`` (Frobenius norm of sigma). Others raise
            ``ConfigError`` listing the possible ones.
        every: log the particles of frames 0, every, 2 every, ... and the last frame; metrics are
            logged for all frames.
        metrics: None or True: ``mpmlab.io.metrics.compute_metrics(traj)``; False: none; a dict
            ``{name: array [T] or [T, k]}``: those (NaN entries are not logged).
        app_id, recording_id: rerun ids (None: a unique one, see :func:`unique_recording_id`).
        overwrite: replace an existing file (otherwise that raises ``ConfigError``).
        color_range: (lo, hi) of a scalar colouring; default: min..max over the logged frames.
        compile_time_s: compilation time left out of the ``step_time_ms`` metric (named in its plot).
        particle_values: log ``Particle:values`` beside the positions (speed, J, eps_p, stress norm,
            material and particle id: what hovering a particle shows).
        color_variants: also log one colour per colouring (``ParticleColors:colors``), to recolour in
            the viewer without a rerun (the hover card then shows a summary instead of the values).
        line_strips: ``{entity: (frame index, points [K, dim])}``: polylines in world coordinates logged
            at that frame (e.g. ``world/deposit_profile``), drawn over the particles from then on.

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

    quantities = quantities_for(list(traj.fields)) if (particle_values or color_variants) else []
    if color_by in QUANTITIES and color_by not in quantities:
        quantities.append(color_by)
    ranges, extent = trajectory_ranges(traj, kept, quantities)
    if color_by in QUANTITIES and color_range is None and kept:
        color_range = ranges[color_by]
    st = metrics.get("step_time_ms")
    compile_left_out = st is not None and len(st) > 1 and not np.isfinite(st[1])
    w = RecordingWriter(path, traj, color_by=color_by, color_range=color_range, every=every, metrics=False,
                        app_id=app_id, recording_id=recording_id, overwrite=overwrite, extent=extent, ranges=ranges,
                        compile_time_s=compile_time_s, particle_values=particle_values,
                        color_variants=color_variants)
    w.compile_left_out = compile_left_out
    strips: dict[int, list] = {}
    for entity, (frame, pts) in (line_strips or {}).items():
        if not 0 <= int(frame) < T:
            raise ConfigError(f"write_recording: line strip '{entity}' is for frame {frame}, but the trajectory "
                              f"has {T} frames.")
        strips.setdefault(int(frame), []).append((entity, pts))
    with w:
        kept_set = set(kept)
        for i in range(T):
            w.add_frame(i, traj.x[i], traj.v[i], float(traj.time[i]), frame_fields(i), traj.field_particles,
                        {k: a[i] for k, a in metrics.items()}, force=i in kept_set)
            for entity, pts in strips.get(i, ()):
                w.add_line_strip(entity, pts, i, float(traj.time[i]),
                                 label=entity.rsplit("/", 1)[-1].replace("_", " "))
    return w.path


# ---- reading back ------------------------------------------------------------------------------
def _entity(entity: str) -> str:
    return "/" + entity.strip("/")


def read_recording_component(path: str | os.PathLike, entity: str, component: str,
                             index: str = "frame") -> dict[Any, list]:
    """``{index value (None for static): [row values as NumPy arrays]}`` of one component of an entity,
    e.g. ``read_recording_component(p, "world/particles", "Points2D:colors")``; a struct component
    (``Particle:values``) comes back as NumPy structured arrays."""
    import pyarrow as pa
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
            if pa.types.is_struct(vals.type):   # e.g. Particle:values: a NumPy structured array
                fields = [vals.type.field(k).name for k in range(vals.type.num_fields)]
                out.setdefault(None if key is None else int(key), []).append(np.rec.fromarrays(
                    [vals.field(k).to_numpy(zero_copy_only=False) for k in range(len(fields))], names=fields))
                continue
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


def read_particle_values(path: str | os.PathLike, entity: str = "world/particles") -> dict[int, np.ndarray]:
    """``{frame: structured array [N]}`` of ``Particle:values`` (fields ``speed``, ``J``, ``eps_p``,
    ``stress_norm`` where recorded, ``material_id``, ``particle_id``): what hovering a particle shows."""
    rows = read_recording_component(path, entity, "Particle:values")
    return {k: v[-1] for k, v in rows.items() if k is not None}


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


def read_blueprint_views(path: str | os.PathLike) -> list[dict[str, Any]]:
    """The views of a recording's default blueprint: ``[{"kind": "TimeSeries" | "2D" | "3D" | ...,
    "name": title, "origin": space origin, "contents": [entity path filter lines]}]``."""
    from rerun.chunk import RrdReader

    if not Path(path).is_file():
        raise ConfigError(f"recording '{path}' does not exist; check the path.")
    r = RrdReader(str(path))
    views: dict[str, dict[str, Any]] = {}

    def first(rb, col):
        if col not in rb.schema.names:
            return None
        v = rb.column(col)[0]
        if not v.is_valid:
            return None
        v = v.as_py()
        return v[0] if isinstance(v, list) and len(v) == 1 else v

    for bp in r.blueprints():
        for ch in r.stream(store=bp):
            entity = str(ch.entity_path)
            if not entity.startswith("/view/"):
                continue
            key = entity.split("/")[2]
            rb = ch.to_record_batch()
            d = views.setdefault(key, {"kind": None, "name": None, "origin": None, "contents": []})
            for col, field in (("ViewBlueprint:class_identifier", "kind"), ("ViewBlueprint:display_name", "name"),
                               ("ViewBlueprint:space_origin", "origin")):
                val = first(rb, col)
                if val is not None:
                    d[field] = val
            q = first(rb, "ViewContents:query")
            if q is not None:
                d["contents"] = q if isinstance(q, list) else [q]
    return list(views.values())


def read_series_names(path: str | os.PathLike, prefix: str = "") -> dict[str, str]:
    """``{entity: series name}`` of every ``SeriesLines`` name in a recording (entities under ``prefix``)."""
    from rerun.chunk import RrdReader

    out = {}
    for ch in RrdReader(str(path)).stream().filter(components="SeriesLines:names"):
        entity = str(ch.entity_path).strip("/")
        if not entity.startswith(prefix.strip("/")):
            continue
        rb = ch.to_record_batch()
        if "SeriesLines:names" in rb.schema.names:
            for row in rb.column("SeriesLines:names"):
                if row.is_valid:
                    out[entity] = str(row.as_py()[0])
    return out


# ---- other workflows: fits and trainings, reduced versus full order ---------------------------------
class EpochRecorder(AtomicWriter):
    """A recording of an optimisation (an inverse fit, an NCLaw training): scalars per epoch on the
    timeline ``epoch`` (``metrics/loss``, ``metrics/<parameter>[/k]``), ``log10`` of the loss beside it
    (``derived/log10_loss``), and, at chosen epochs, rollouts (``rollouts/epoch_<k>/particles`` on the
    timelines ``epoch`` and ``frame``). Its blueprint, sent when it closes: the loss (log10 and
    linear), one plot per parameter or scalar family, and one particle view per rollout (at most 4).
    Written to a temporary file and published atomically by ``close()``.

        rec = EpochRecorder("fit.rrd", unique_recording_id("inverse", scene), title="inverse fit")
        fit.run(..., on_epoch=rec.log); rec.close()
    """

    def __init__(self, path: str | os.PathLike, recording_id: str | None = None, *, title: str = "fit",
                 app_id: str = "mpmlab", overwrite: bool = True, units: dict[str, str] | None = None):
        AtomicWriter.__init__(self, path, overwrite)
        self.title = title
        self.units = dict(units or {})
        self.app_id = app_id
        self.recording_id = recording_id or unique_recording_id("fit")
        self.rec = None
        self._families: dict[str, list[str]] = {}
        self._named: set[str] = set()
        self._rollouts: list[tuple[int, int]] = []   # (epoch, dim)
        self.open()

    # ---- lifecycle (mpmlab.io.files.AtomicWriter; opened when made) --------------------------
    def _is_open(self) -> bool:
        return self.rec is not None

    def _start(self, tmp: Path) -> None:
        import rerun as rr

        self.rec = rr.RecordingStream(self.app_id, recording_id=self.recording_id)
        self.rec.save(tmp)

    def _abort_start(self) -> None:
        pass

    def _scalar(self, entity: str, value: float, family: str, name: str) -> None:
        import rerun as rr

        if not np.isfinite(value):
            return
        if entity not in self._named:
            self._named.add(entity)
            fam = self._families.setdefault(family, [])
            color = PALETTE[len(fam) % len(PALETTE)].tolist() if family != "loss" else [255, 150, 40]
            self.rec.log(entity, rr.SeriesLines(names=name, colors=[color]), static=True)
            fam.append("/" + entity)
        self.rec.log(entity, rr.Scalars(float(value)))

    def log(self, epoch: int, loss: float, values: dict | None = None) -> None:
        """One epoch: the loss and the current parameter values (scalars or arrays)."""
        self.rec.set_time("epoch", sequence=int(epoch))
        loss = float(loss)
        self._scalar("metrics/loss", loss, "loss", "loss")
        if loss > 0:
            self._scalar("derived/log10_loss", math.log10(loss), "log10_loss", "log₁₀ loss")
        self.log_scalars(epoch, values or {})

    def log_scalars(self, epoch: int, values: dict, family: str | None = None) -> None:
        """Scalars (or arrays, one series per entry) at ``epoch``; each name is its own plot unless a
        ``family`` groups them (e.g. NCLaw's ``λ`` terms)."""
        self.rec.set_time("epoch", sequence=int(epoch))
        for name, v in values.items():
            v = np.asarray(v, float).reshape(-1)
            unit = self.units.get(name, "")
            label = f"{name} [{unit}]" if unit else name
            if v.size == 1:
                self._scalar(f"metrics/{name}", float(v[0]), family or name, label)
            else:
                for k, a in enumerate(v):
                    self._scalar(f"metrics/{name}/{k}", float(a), family or name, f"{label}[{k}]")

    def log_rollout(self, epoch: int, x, time=None, radii=None, colors=None) -> None:
        """A rollout at ``epoch``: positions [T, N, D] (2D drawn +y up), frame by frame."""
        import rerun as rr

        x = np.asarray(x)
        dim = int(x.shape[-1])
        ent = f"rollouts/epoch_{int(epoch):05d}"
        if not self._rollouts or all(e != epoch for e, _ in self._rollouts):
            self._rollouts.append((int(epoch), dim))
            if dim == 2:
                self.rec.log(ent, rr.Transform3D(scale=[1.0, -1.0, 1.0]), static=True)
        P = rr.Points2D if dim == 2 else rr.Points3D
        for f in range(len(x)):
            self.rec.set_time("epoch", sequence=int(epoch))
            self.rec.set_time("frame", sequence=int(f))
            if time is not None:
                self.rec.set_time("sim_time", duration=float(np.asarray(time)[f]))
            kw = {}
            if radii is not None:
                kw["radii"] = radii
            if colors is not None:
                kw["colors"] = colors
            self.rec.log(f"{ent}/particles", P(x[f], **kw))

    def blueprint(self):
        import rerun.blueprint as rrb

        titles = {"loss": "loss (linear)", "log10_loss": "log₁₀ loss"}
        order = (["log10_loss"] if "log10_loss" in self._families else []) + \
            (["loss"] if "loss" in self._families else []) + \
            [f for f in self._families if f not in ("loss", "log10_loss")]
        plots = [rrb.TimeSeriesView(origin="/", contents=self._families[f], name=titles.get(f, f),
                                    plot_legend=rrb.PlotLegend(corner="RightTop")) for f in order]
        views = []
        for epoch, dim in self._rollouts[-4:]:
            ent = f"/rollouts/epoch_{epoch:05d}"
            views.append(rrb.Spatial2DView(origin="/", contents=[f"{ent}/**"], name=f"rollout, epoch {epoch}")
                         if dim == 2 else rrb.Spatial3DView(origin=ent, name=f"rollout, epoch {epoch}"))
        panels = [rrb.BlueprintPanel(state="collapsed"), rrb.SelectionPanel(state="collapsed"),
                  rrb.TimePanel(state="collapsed", timeline="epoch", play_state="following")]
        head = plots[:2]
        rest = plots[2:]
        main = rrb.Horizontal(*head) if len(head) > 1 else (head[0] if head else None)
        rows = ([main] if main is not None else []) + ([rrb.Grid(*rest)] if rest else []) + \
            ([rrb.Horizontal(*views)] if views else [])
        if not rows:
            return rrb.Blueprint(rrb.TimeSeriesView(origin="/metrics", name=self.title), *panels)
        return rrb.Blueprint(rrb.Vertical(*rows, name=self.title) if len(rows) > 1 else rows[0], *panels)

    def close(self, exc: BaseException | None = None) -> Path | None:
        """Send the blueprint, flush and publish (a failed fit publishes the epochs so far)."""
        if self._closed:
            return self.path
        return AtomicWriter.close(self, exc)

    def _finish(self, exc: BaseException | None) -> Path | None:
        try:
            self.rec.send_blueprint(self.blueprint(), make_active=True, make_default=True)
            self.rec.flush()
            self.rec.disconnect()
            self._publish()
        except BaseException:
            discard(self._tmp)
            raise
        return self.path


def write_comparison_recording(path: str | os.PathLike, full: Trajectory, reduced: Trajectory, *,
                               names: tuple[str, str] = ("full order", "reduced"), every: int = 1,
                               recording_id: str | None = None, overwrite: bool = False,
                               app_id: str = "mpmlab") -> Path:
    """A reduced-order rollout beside its full-order reference (the deformation-map ROM): both
    particle sets (``full/particles``, ``reduced/particles``, same colours by material) in two views
    with one camera, and the error per frame: ``metrics/position_rms_error`` [m] and
    ``metrics/relative_error`` (|x_r - x_f| / |x_f - x_f(0)|, from frame 1). Frames are read one at a time."""
    import rerun as rr
    import rerun.blueprint as rrb

    T = min(full.frame_count, reduced.frame_count)
    if full.particle_count != reduced.particle_count:
        raise ConfigError(f"write_comparison_recording: {full.particle_count} full-order particles but "
                          f"{reduced.particle_count} reduced ones; compare the same particles.")
    if int(every) < 1:
        raise ConfigError(f"write_comparison_recording: every must be >= 1 (got {every}).")
    path = check_target(path, overwrite)
    meta = full.meta or {}
    dim = int(meta.get("dim", np.shape(full.x)[-1]))
    tmp = temp_path(path)
    rec = rr.RecordingStream(app_id, recording_id=recording_id or unique_recording_id("rom", meta.get("scene")))
    try:
        rec.save(tmp)
        radii = (0.5 * np.asarray(full.volume, dtype=np.float64) ** (1.0 / dim)).astype(np.float32)
        colors = PALETTE[np.asarray(full.material_id) % len(PALETTE)]
        P = rr.Points2D if dim == 2 else rr.Points3D
        kept = sorted(set(range(0, T, int(every))) | ({T - 1} if T else set()))
        _, ext_f = trajectory_ranges(full, kept, ())
        _, ext_r = trajectory_ranges(reduced, kept, ())
        ext = None if ext_f is None else (np.minimum(ext_f[0], ext_r[0]), np.maximum(ext_f[1], ext_r[1]))
        up = _up_axis(meta.get("gravity"), dim)
        for key in ("full", "reduced"):
            if dim == 2:
                rec.log(key, rr.Transform3D(scale=[1.0, -1.0, 1.0]), static=True)
            else:
                rec.log(key, {1: rr.ViewCoordinates.RIGHT_HAND_Y_UP, 2: rr.ViewCoordinates.RIGHT_HAND_Z_UP,
                              0: rr.ViewCoordinates.RIGHT_HAND_X_UP}[up if up is not None else 1], static=True)
            rec.log(f"{key}/particles", P.from_fields(radii=radii, colors=colors), static=True)
        styles = {"metrics/position_rms_error": ("position RMS error [m]", [255, 150, 40]),
                  "metrics/relative_error": ("relative error |x_r − x_f| / |x_f − x_f(0)|", [90, 150, 230])}
        for ent, (name, color) in styles.items():
            rec.log(ent, rr.SeriesLines(names=name, colors=[color]), static=True)
        x0 = np.asarray(full.x[0], dtype=np.float64) if T else None
        kept_set = set(kept)
        for i in range(T):
            xf, xr = np.asarray(full.x[i], dtype=np.float64), np.asarray(reduced.x[i], dtype=np.float64)
            rec.set_time("frame", sequence=i)
            if np.isfinite(full.time[i]):
                rec.set_time("sim_time", duration=float(full.time[i]))
            if i in kept_set:
                rec.log("full/particles", P(xf))
                rec.log("reduced/particles", P(xr))
            err = xr - xf
            rec.log("metrics/position_rms_error", rr.Scalars(float(np.sqrt(np.mean(np.sum(err * err, axis=-1))))))
            disp = float(np.linalg.norm(xf - x0))
            if i > 0 and disp > 0:
                rec.log("metrics/relative_error", rr.Scalars(float(np.linalg.norm(err)) / disp))

        def view(key, name):
            if dim == 2:
                kw = {}
                if ext is not None:
                    lo, hi = frame_bounds_2d(ext[0], ext[1], float(radii.max()) if radii.size else 0.0,
                                             meta.get("gravity"))
                    kw["visual_bounds"] = rrb.VisualBounds2D(x_range=[lo[0], hi[0]], y_range=[-hi[1], -lo[1]])
                return rrb.Spatial2DView(origin="/", contents=[f"/{key}/**"], name=name, **kw)
            kw = {"eye_controls": rrb.EyeControls3D(**eye_for_box(ext[0], ext[1], up))} if ext is not None else {}
            return rrb.Spatial3DView(origin=f"/{key}", name=name, **kw)

        bp = rrb.Blueprint(
            rrb.Vertical(rrb.Horizontal(view("full", names[0]), view("reduced", names[1])),
                         rrb.Horizontal(rrb.TimeSeriesView(origin="/", contents=["/metrics/position_rms_error"],
                                                           name="position RMS error [m]"),
                                        rrb.TimeSeriesView(origin="/", contents=["/metrics/relative_error"],
                                                           name="relative error")),
                         row_shares=[3, 1.3]),
            rrb.BlueprintPanel(state="collapsed"), rrb.SelectionPanel(state="collapsed"),
            rrb.TimePanel(state="collapsed", play_state="following",
                         timeline="sim_time" if T and np.all(np.isfinite(full.time[:T])) else "frame"))
        rec.send_blueprint(bp, make_active=True, make_default=True)
        rec.flush()
        rec.disconnect()
        publish(tmp, path, overwrite)
    except BaseException:
        try:
            rec.disconnect()
        finally:
            discard(tmp)
        raise
    return path
