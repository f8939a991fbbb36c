"""Run-out of a granular deposit from particle positions (NumPy; 2D and 3D), and when it has stopped.

Geometry (:class:`RunoutGeometry`): the material flows away from a wall at ``wall`` along ``axis``
(``direction`` +1: towards larger coordinates) on a floor at ``base`` along the ``up`` axis (against
gravity); with ``center`` instead of a wall the flow is radial (a cylinder collapse) and distances are
measured in the horizontal plane from that point. Distances and heights are those of the particles'
*extents*: half the particle size (``particle_size / 2``, the size being ``V_p^(1/D)``, the edge of
the particle's initial cell share) is added to a particle's distance and height, so that the initial
column of length L0 and height H0 measures exactly L0 and H0.

**The deposit** is the largest group of particles connected through occupied cells: particles are
binned into cubes of edge ``cell`` (the simulation's dx), two occupied cubes are connected when they
touch (share a face, an edge or a corner: 3^D - 1 neighbours), and the connected component holding
the most particles is the deposit. A particle (or a clump) separated from it by at least one empty cube
in every direction, i.e. more than one to two cells away, is left out however far it was flung, and
counted in ``particles_left_out``; a particle within one cell of the deposit belongs to it, so a
genuine thin front (one particle layer, or particles spread up to a cell apart) is part of it. No
grid over the bounding box is made (gaps between occupied cells are shrunk first), so a particle flung
a kilometre away costs nothing; 2M particles take about 3 s per frame on one CPU core.

* **run-out** ``L_f``: the largest distance from the wall (or centre) over the deposit's particles;
  with the wall at 0, the position of the front. d_n = (L_f - L0) / L0.
* **height at the wall** ``H_wall``: the highest deposit particle within one bin (``cell``) of the
  wall (radial: of the centre).
* **deposit profile**: on bins of width ``bin`` (default ``cell``) from the wall, the height of the
  highest deposit particle in each bin (0 where it has none); in 3D the maximum across the width.

:class:`RunoutMonitor` is fed every output frame and says when the deposit has come to rest: the front
and the height at the wall each moved less than ``tol_cells`` cells over the last ``window_s``
seconds (the range of their values over the frames in that window, so a front oscillating back and
forth is not still) *and* the kinetic energy is below ``ke_fraction`` of its peak so far. A front that
creeps at more than ``tol_cells`` per ``window_s`` (0.1 cell per 0.1 s by default, 1 cell/s) is
never called settled, whatever its kinetic energy; a deposit whose kinetic energy fell below 1e-4 of
its peak can still creep several cells (issue 18), which an energy threshold alone cannot see.
"""
from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from ..core.errors import ConfigError

_AXES = "xyz"
#: per-frame series the simulate task records (name -> (family, label, unit)); see register_metrics
METRICS = {
    "runout_front": ("runout", "front L(t)", "m"),
    "runout_height_at_wall": ("runout", "height at the wall (radial: the centre) H(t)", "m"),
}
FAMILY_TITLE = "run-out"


def register_metrics() -> None:
    """Name the run-out series in :mod:`mpmlab.io.metrics` (their recording plot and its unit):
    one plot, "run-out [m]", with the front and the height at the wall. Idempotent."""
    from ..io import metrics

    for name, info in METRICS.items():
        metrics.METRIC_INFO.setdefault(name, info)
    metrics.FAMILY_TITLES.setdefault("runout", FAMILY_TITLE)


def axis_index(value: Any, dim: int, what: str) -> int:
    """``x``/``y``/``z`` or an index 0..dim-1 -> the index; anything else is a one-line ConfigError."""
    s = str(value).strip().lower()
    if s in _AXES[:dim]:
        return _AXES.index(s)
    if s.lstrip("-").isdigit() and 0 <= int(s) < dim:
        return int(s)
    raise ConfigError(f"{what} = {value!r} is not an axis of this {dim}D scene; use one of "
                      f"{', '.join(_AXES[:dim])} (or 0..{dim - 1}).")


@dataclass(frozen=True)
class RunoutGeometry:
    """Where the deposit is measured from (see the module docstring).

    Args:
        dim: 2 or 3.
        up: the axis against gravity (index).
        axis: the flow axis (index), for a wall; None with ``center``.
        wall: the wall's position along ``axis`` [m].
        direction: +1 (flow towards larger ``axis`` coordinates) or -1.
        base: the floor's position along ``up`` [m].
        center: radial flow: the point (all ``dim`` coordinates, or the ``dim - 1`` horizontal ones)
            from which horizontal distances are measured; ``axis``, ``wall`` and ``direction`` unused.
    """

    dim: int
    up: int
    axis: int | None = None
    wall: float = 0.0
    direction: int = 1
    base: float = 0.0
    center: tuple[float, ...] | None = None

    def __post_init__(self):
        if self.dim not in (2, 3):
            raise ConfigError(f"run-out geometry: dim must be 2 or 3 (got {self.dim}).")
        if not 0 <= self.up < self.dim:
            raise ConfigError(f"run-out geometry: up axis {self.up} is not an axis of a {self.dim}D scene.")
        if self.center is None:
            if self.axis is None or not 0 <= self.axis < self.dim:
                raise ConfigError("run-out geometry: give the flow axis (axis: x|y|z) and the wall position, "
                                  "or a center for a radial flow.")
            if self.axis == self.up:
                raise ConfigError(f"run-out geometry: the flow axis and the up axis are both "
                                  f"'{_AXES[self.up]}'; the flow runs along the floor.")
            if self.direction not in (1, -1):
                raise ConfigError(f"run-out geometry: direction must be +1 or -1 (got {self.direction}).")
        else:
            c = tuple(float(v) for v in self.center)
            if len(c) not in (self.dim, self.dim - 1):
                raise ConfigError(f"run-out geometry: center {list(c)} needs {self.dim} coordinates (or the "
                                  f"{self.dim - 1} horizontal ones).")
            if len(c) == self.dim - 1:   # the horizontal coordinates only: put a 0 for the up axis
                c = c[: self.up] + (0.0,) + c[self.up:]
            object.__setattr__(self, "center", c)
        for name in ("wall", "base"):
            if not math.isfinite(float(getattr(self, name))):
                raise ConfigError(f"run-out geometry: {name} = {getattr(self, name)} is not a finite number.")

    @property
    def radial(self) -> bool:
        return self.center is not None

    @property
    def horizontal(self) -> list[int]:
        return [a for a in range(self.dim) if a != self.up]

    def distance(self, x: np.ndarray) -> np.ndarray:
        """Distance of each position from the wall along the flow (radial: from the centre, horizontally)."""
        x = np.asarray(x, dtype=np.float64)
        if self.radial:
            h = self.horizontal
            d = x[:, h] - np.asarray(self.center, dtype=np.float64)[h]
            return np.sqrt(np.sum(d * d, axis=1))
        return self.direction * (x[:, self.axis] - self.wall)

    def height(self, x: np.ndarray) -> np.ndarray:
        """Height of each position above the floor."""
        return np.asarray(x, dtype=np.float64)[:, self.up] - self.base

    def point(self, distance: np.ndarray, height: np.ndarray, lateral: Sequence[float]) -> np.ndarray:
        """World positions [K, dim] of (distance, height) pairs: along the flow axis (radial: along the
        first horizontal axis from the centre), at the ``lateral`` coordinates of the other axes."""
        distance, height = np.asarray(distance, np.float64), np.asarray(height, np.float64)
        p = np.tile(np.asarray(lateral, dtype=np.float64), (len(distance), 1))
        if self.radial:
            a = self.horizontal[0]
            p[:, a] = self.center[a] + distance
        else:
            p[:, self.axis] = self.wall + self.direction * distance
        p[:, self.up] = self.base + height
        return p

    def describe(self) -> dict:
        d = {"up": _AXES[self.up], "base": float(self.base)}
        if self.radial:
            d["center"] = [float(c) for k, c in enumerate(self.center) if k != self.up]
        else:
            d.update(axis=_AXES[self.axis], wall=float(self.wall), direction=int(self.direction))
        return d


# ------------------------------------------------------------------------------------------------
# the deposit: the largest cluster of particles connected through occupied cells
# ------------------------------------------------------------------------------------------------
#: largest index range labelled through a dense lookup table instead of a sort (4 bytes per entry)
DENSE_LIMIT = 1 << 25


def _unique_inverse(a: np.ndarray, dense_limit: int = DENSE_LIMIT) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(a, return_inverse=True)`` for non-negative integers; through a lookup table (no sort,
    several times faster on millions of particles) when ``a.max() < dense_limit``."""
    top = int(a.max()) + 1 if a.size else 0
    if top > dense_limit:
        u, inv = np.unique(a, return_inverse=True)
        return u, inv.reshape(-1)
    occupied = np.zeros(top, dtype=bool)
    occupied[a] = True
    u = np.flatnonzero(occupied)
    lookup = np.empty(top, dtype=np.int64)
    lookup[u] = np.arange(len(u))
    return u.astype(a.dtype, copy=False), lookup[a]


def deposit_mask(x: np.ndarray, cell: float, dense_limit: int = DENSE_LIMIT) -> np.ndarray:
    """Boolean mask [N] of the particles in the deposit: the largest component of occupied cubes of
    edge ``cell`` connected through faces, edges and corners (module docstring). Non-finite positions
    are never part of it. ``dense_limit``: see :func:`_unique_inverse` (the answer does not depend on it)."""
    if not (cell > 0 and math.isfinite(cell)):
        raise ConfigError(f"run-out: the cell size must be a positive number (got {cell}).")
    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 2:
        raise ConfigError(f"run-out: positions must be [N, dim] (got shape {x.shape}).")
    n, dim = x.shape
    mask = np.zeros(n, dtype=bool)
    finite = np.nonzero(np.all(np.isfinite(x), axis=1))[0]
    if finite.size == 0:
        return mask
    c = np.floor(x[finite] / cell).astype(np.int64)
    # per axis, keep a difference of 1 between occupied cube indices (neighbours) and shrink every larger
    # gap to 2 (not neighbours): the neighbour relation is unchanged and the index range stays below 2 N
    # per axis however far apart the particles are. Indices start at 1: the padding stops a -1 offset
    # from wrapping round into the previous row of the flattened index.
    coords = np.empty_like(c)
    spans = []
    for a in range(dim):
        ca = c[:, a] - c[:, a].min()
        u, inv = _unique_inverse(ca, dense_limit)
        pos = np.concatenate([[1], 1 + np.cumsum(np.minimum(np.diff(u), 2))])
        coords[:, a] = pos[inv]
        spans.append(int(pos[-1]) + 2)
    if math.prod(spans) >= 2 ** 62:   # would need > 10^6 separate cube rows along every axis
        raise ConfigError(f"run-out: {n} particles spread over too many separate cells to label ({spans}).")
    key = np.ravel_multi_index(tuple(coords.T), spans).astype(np.int64)
    ukey, vinv = _unique_inverse(key, dense_limit)
    strides = np.array([math.prod(spans[a + 1:]) for a in range(dim)], dtype=np.int64)
    rows, cols = [], []
    for off in itertools.product((-1, 0, 1), repeat=dim):
        if off <= (0,) * dim:            # each undirected pair once: the lexicographically positive half
            continue
        nk = ukey + int(np.dot(off, strides))
        idx = np.minimum(np.searchsorted(ukey, nk), len(ukey) - 1)
        hit = ukey[idx] == nk
        rows.append(np.nonzero(hit)[0])
        cols.append(idx[hit])
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    r, k = np.concatenate(rows), np.concatenate(cols)
    graph = coo_matrix((np.ones(len(r), dtype=np.int8), (r, k)), shape=(len(ukey), len(ukey)))
    _, labels = connected_components(graph, directed=False)
    plabel = labels[vinv]
    main = int(np.argmax(np.bincount(plabel)))
    mask[finite[plabel == main]] = True
    return mask


def _half(particle_size, n: int) -> np.ndarray:
    s = np.broadcast_to(np.asarray(particle_size, dtype=np.float64), (n,))
    if not np.all(np.isfinite(s)) or np.any(s < 0):
        raise ConfigError("run-out: particle_size must be finite and >= 0.")
    return 0.5 * s


def _parts(x, geometry: RunoutGeometry, cell: float, particle_size, mask):
    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != geometry.dim:
        raise ConfigError(f"run-out: positions must be [N, {geometry.dim}] for this geometry (got shape {x.shape}).")
    half = _half(particle_size, len(x))
    mask = deposit_mask(x, cell) if mask is None else np.asarray(mask, dtype=bool)
    return geometry.distance(x[mask]) + half[mask], geometry.height(x[mask]) + half[mask], mask


def runout(x: np.ndarray, geometry: RunoutGeometry, cell: float, particle_size=0.0,
           mask: np.ndarray | None = None) -> float:
    """L_f: the largest distance from the wall (radial: the centre) over the deposit's particles,
    each particle's half size added (NaN when there is no deposit). ``mask``: a deposit already found
    (:func:`deposit_mask`)."""
    d, _, _ = _parts(x, geometry, cell, particle_size, mask)
    return float(d.max()) if d.size else float("nan")


def height_at_wall(x: np.ndarray, geometry: RunoutGeometry, cell: float, particle_size=0.0,
                   mask: np.ndarray | None = None, width: float | None = None) -> float:
    """The height of the highest deposit particle whose centre lies within ``width`` (default
    ``cell``) of the wall (radial: of the centre), its half size added; 0 when none does."""
    x = np.asarray(x, dtype=np.float64)
    width = cell if width is None else float(width)
    half = _half(particle_size, len(x))
    mask = deposit_mask(x, cell) if mask is None else np.asarray(mask, dtype=bool)
    near = mask & (geometry.distance(x) < width)
    return float((geometry.height(x[near]) + half[near]).max()) if near.any() else 0.0


def deposit_profile(x: np.ndarray, geometry: RunoutGeometry, cell: float, particle_size=0.0,
                    bin: float | None = None, mask: np.ndarray | None = None,
                    length: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(bin centres [K], heights [K]): on bins of width ``bin`` (default ``cell``) from the wall out to
    ``length`` (default: the run-out), the height of the highest deposit particle whose centre lies in
    the bin, its half size added; 0 for a bin with none. In 3D the maximum across the width."""
    x = np.asarray(x, dtype=np.float64)
    b = float(cell if bin is None else bin)
    if not (b > 0 and math.isfinite(b)):
        raise ConfigError(f"run-out: the profile's bin width must be a positive number (got {bin}).")
    half = _half(particle_size, len(x))
    mask = deposit_mask(x, cell) if mask is None else np.asarray(mask, dtype=bool)
    d = geometry.distance(x[mask])
    h = geometry.height(x[mask]) + half[mask]
    if length is None:
        length = float((d + half[mask]).max()) if d.size else 0.0
    k = max(1, int(math.ceil(length / b - 1e-9)))
    heights = np.zeros(k)
    inside = (d >= 0) & (d < k * b)
    idx = np.minimum((d[inside] / b).astype(np.int64), k - 1)
    np.maximum.at(heights, idx, h[inside])
    return (np.arange(k) + 0.5) * b, heights


def measure(x: np.ndarray, geometry: RunoutGeometry, cell: float, particle_size=0.0,
            profile: bool = False, bin: float | None = None) -> dict:
    """Everything at once from one deposit search: ``front`` (L_f), ``height_at_wall``,
    ``particles_in_deposit``, ``particles_left_out`` (finite positions outside the deposit) and, with
    ``profile``, ``profile_distance`` / ``profile_height``."""
    x = np.asarray(x, dtype=np.float64)
    mask = deposit_mask(x, cell)
    out = {"front": runout(x, geometry, cell, particle_size, mask=mask),
           "height_at_wall": height_at_wall(x, geometry, cell, particle_size, mask=mask),
           "particles_in_deposit": int(mask.sum()),
           "particles_left_out": int(np.all(np.isfinite(x), axis=1).sum() - mask.sum())}
    if profile:
        out["profile_distance"], out["profile_height"] = deposit_profile(x, geometry, cell, particle_size,
                                                                         bin=bin, mask=mask)
    return out


# ------------------------------------------------------------------------------------------------
# when has the deposit stopped?
# ------------------------------------------------------------------------------------------------
@dataclass
class RunoutMonitor:
    """Fed ``update(t, x, v)`` at every output frame; ``settled`` once the deposit has come to rest
    (module docstring: front and wall height each moved less than ``tol_cells`` cells over the last
    ``window_s`` s, and kinetic energy below ``ke_fraction`` of its peak).

    Args:
        geometry, cell, particle_size: as for :func:`measure`.
        mass: particle masses [N] for the kinetic energy from ``v`` (or pass ``kinetic_energy``).
        window_s, tol_cells, ke_fraction: the stop rule.

    ``times``, ``fronts``, ``heights``, ``kinetic`` hold one entry per frame; ``settled_time`` /
    ``settled_index`` the first frame at which the rule held (the rule is not re-armed: a deposit that
    moves again later is seen in :meth:`moved_cells` at the end).
    """

    geometry: RunoutGeometry
    cell: float
    mass: np.ndarray | None = None
    particle_size: Any = 0.0
    window_s: float = 0.1
    tol_cells: float = 0.1
    ke_fraction: float = 1e-3
    times: list = field(default_factory=list)
    fronts: list = field(default_factory=list)
    heights: list = field(default_factory=list)
    kinetic: list = field(default_factory=list)
    left_out: list = field(default_factory=list)
    settled_index: int | None = None
    last_x: np.ndarray | None = None

    def __post_init__(self):
        for name, lo in (("cell", 0.0), ("window_s", 0.0), ("tol_cells", 0.0)):
            v = float(getattr(self, name))
            if not (v > lo and math.isfinite(v)):
                raise ConfigError(f"run-out monitor: {name} = {getattr(self, name)} must be a positive number.")
        if not 0.0 <= float(self.ke_fraction) <= 1.0:
            raise ConfigError(f"run-out monitor: ke_fraction = {self.ke_fraction} must be in [0, 1].")

    @property
    def settled(self) -> bool:
        return self.settled_index is not None

    @property
    def settled_time(self) -> float | None:
        return None if self.settled_index is None else float(self.times[self.settled_index])

    def update(self, t: float, x: np.ndarray, v: np.ndarray | None = None,
               kinetic_energy: float | None = None) -> bool:
        """Measure one frame; True once the deposit has settled (at this frame or an earlier one)."""
        m = measure(x, self.geometry, self.cell, self.particle_size)
        if kinetic_energy is None and v is not None and self.mass is not None:
            v = np.asarray(v, dtype=np.float64)
            kinetic_energy = 0.5 * float(np.sum(np.asarray(self.mass, np.float64) * np.sum(v * v, axis=1)))
        if self.times and not float(t) > self.times[-1]:
            raise ConfigError(f"run-out monitor: frame times must increase (got {t} after {self.times[-1]}).")
        self.times.append(float(t))
        self.fronts.append(m["front"])
        self.heights.append(m["height_at_wall"])
        self.kinetic.append(float("nan") if kinetic_energy is None else float(kinetic_energy))
        self.left_out.append(m["particles_left_out"])
        self.last_x = np.array(x, dtype=np.float64, copy=True)
        if self.settled_index is None and self._still():
            self.settled_index = len(self.times) - 1
        return self.settled

    def _window_start(self) -> int | None:
        """Index of the latest frame at least ``window_s`` before the last one (None: not yet covered)."""
        t = np.asarray(self.times)
        eps = 1e-9 * max(1.0, abs(t[-1]))
        j = np.nonzero(t <= t[-1] - self.window_s + eps)[0]
        return int(j[-1]) if j.size else None

    def moved_cells(self) -> tuple[float, float]:
        """(front, height at the wall): the range of each over the last ``window_s`` s, in cells (NaN
        while the frames do not yet cover a window)."""
        j = self._window_start() if self.times else None
        if j is None:
            return float("nan"), float("nan")
        f, h = np.asarray(self.fronts[j:]), np.asarray(self.heights[j:])
        return float((f.max() - f.min()) / self.cell), float((h.max() - h.min()) / self.cell)

    def front_speed(self) -> float:
        """The front's mean speed over the last ``window_s`` s [cells/s] (NaN while no window is covered):
        how fast a deposit the rule called settled still creeps."""
        j = self._window_start() if self.times else None
        if j is None or j == len(self.times) - 1:
            return float("nan")
        return float((self.fronts[-1] - self.fronts[j]) / self.cell / (self.times[-1] - self.times[j]))

    def _still(self) -> bool:
        df, dh = self.moved_cells()
        if not (df < self.tol_cells and dh < self.tol_cells):   # NaN (no window yet, no deposit): not still
            return False
        ke = np.asarray(self.kinetic)
        if np.all(np.isnan(ke)):
            return True                  # no energy given: the front alone decides
        peak = float(np.nanmax(ke))
        return bool(ke[-1] <= self.ke_fraction * peak)

    def series(self) -> dict[str, np.ndarray]:
        """Per-frame ``runout_front`` and ``runout_height_at_wall`` [m] (the recording's series)."""
        return {"runout_front": np.asarray(self.fronts, dtype=np.float64),
                "runout_height_at_wall": np.asarray(self.heights, dtype=np.float64)}

    def rule(self) -> dict:
        return {"window_s": float(self.window_s), "tol_cells": float(self.tol_cells),
                "ke_fraction": float(self.ke_fraction)}


def summarize(monitor: RunoutMonitor, L0: float | None = None, H0: float | None = None,
              bin: float | None = None) -> dict:
    """The run-out block of ``summary.json`` from a monitor's frames: the final frame's run-out
    ``L_f``, ``d_n`` (with ``L0``), ``H_wall`` (and ``H_wall / H0``), the deposit profile, whether and
    when the deposit settled, and how far the front moved over the last window."""
    if monitor.last_x is None:
        raise ConfigError("run-out: the monitor has seen no frame.")
    g = monitor.geometry
    m = measure(monitor.last_x, g, monitor.cell, monitor.particle_size, profile=True, bin=bin)
    df, dh = monitor.moved_cells()
    out = {
        "L_f": m["front"],
        "L0": None if L0 is None else float(L0),
        "d_n": None if not L0 else (m["front"] - float(L0)) / float(L0),
        "H_wall": m["height_at_wall"],
        "H0": None if H0 is None else float(H0),
        "H_wall_over_H0": None if not H0 else m["height_at_wall"] / float(H0),
        "time": monitor.times[-1],
        "particles_in_deposit": m["particles_in_deposit"],
        "particles_left_out": m["particles_left_out"],
        "settled": monitor.settled,
        "settled_time": monitor.settled_time,
        # the same measure on the first frame: L0 for a box column; a curved one (a cylinder) measures
        # up to half a particle spacing more, its outermost particle centres lying close to the surface
        "L_initial": float(monitor.fronts[0]),
        "L_f_at_settled": None if not monitor.settled else float(monitor.fronts[monitor.settled_index]),
        "front_moved_last_window_cells": None if math.isnan(df) else df,
        "height_moved_last_window_cells": None if math.isnan(dh) else dh,
        "front_speed_cells_per_s": None if math.isnan(monitor.front_speed()) else monitor.front_speed(),
        "kinetic_energy_fraction_of_peak": _ke_fraction(monitor.kinetic),
        "stop_rule": monitor.rule(),
        "geometry": g.describe(),
        "cell": float(monitor.cell),
        "profile": {"bin": float(monitor.cell if bin is None else bin),
                    "distance": [float(v) for v in m["profile_distance"]],
                    "height": [float(v) for v in m["profile_height"]]},
    }
    return out


def _ke_fraction(kinetic: list) -> float | None:
    ke = np.asarray(kinetic, dtype=np.float64)
    if ke.size == 0 or np.all(np.isnan(ke)):
        return None
    peak = float(np.nanmax(ke))
    return float(ke[-1] / peak) if peak > 0 else 0.0


def profile_points(result: dict, geometry: RunoutGeometry, lateral: Sequence[float]) -> np.ndarray:
    """The deposit profile of :func:`summarize`'s result as a polyline in world coordinates [K + 2, dim]:
    from the floor at the wall, over the bin tops, down to the floor at the front."""
    p = result["profile"]
    first = p["height"][0] if p["height"] else 0.0
    # the last bin's centre can lie past the front (the bins end at L_f): the line stops at the front
    centres = np.minimum(p["distance"], result["L_f"]) if np.isfinite(result["L_f"]) else p["distance"]
    d = np.concatenate([[0.0, 0.0], centres, [result["L_f"]]])
    h = np.concatenate([[0.0, first], p["height"], [0.0]])
    if not np.isfinite(result["L_f"]):
        d, h = d[:-1], h[:-1]
    return geometry.point(d, h, lateral)
