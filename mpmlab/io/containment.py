"""Containment of particles by the scene's walls and obstacles: who crossed a face, how far.

Grid boundaries (``mpmlab.boundaries``) constrain grid *nodes*; a particle moves with the velocity
interpolated from its 3 x 3 (x 3) quadratic B-spline stencil, which reaches free interior nodes, so it
may end a fraction of a cell beyond a wall face before the material pushes it back. Nothing stops a
run for that (the stability guard only stops one whose particle leaves ``scene.inner_bounds``). This
module measures it, frame by frame, without keeping the frames:

    acc = WallPenetration(scene)
    acc.update(x0, 0)                    # once per kept frame: positions [N, D], step index
    ...
    acc.summary()                        # plain-Python dict (JSON-serialisable)

**Faces.** A ``walls`` boundary of ``thickness`` t constrains the nodes with index < t on a '-' face and
index > cells - t on a '+' face (``mpmlab.backends.boundary_geometry.wall_masks``); the face a particle
should not cross is the innermost constrained node layer, ``origin + (t - 1) dx`` ('-') and
``origin + (cells - t + 1) dx`` ('+'). With ``domain.pad_cells = t - 1`` (the packaged scenes) that is
the configured tank face ``scene.domain.lo`` / ``hi``. Faces of kind ``none`` are no wall.
``friction_walls`` add their face the same way (the innermost face wins where both act). A ``plane``
counts as a wall face at the plane itself (depth = distance behind it). A ``box_obstacle`` counts a
particle strictly inside the box, at depth = distance to the nearest box face that lies inside the
tank (a face at or beyond a wall face, e.g. the floor end of a full-height column, cannot be reached
from outside and is not used). Face labels: ``"x-"`` ... ``"z+"`` for domain faces,
``"plane[k]"`` and ``"box_obstacle[k]:y+"`` with k the boundary's index in ``scene.boundaries``.

**Domain interior.** Independently of the walls, a particle outside ``scene.inner_bounds`` (``x < lo``
or ``x >= hi``, the stability guard's test) is counted as ``particles_beyond_interior``.

Non-finite positions compare false and are not counted (the stability guard reports those).
Cost per ``update``: a few vectorised passes over x, O(N) time and memory, no per-particle Python.
"""
from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["WallPenetration", "wall_faces", "trajectory_penetration"]


def wall_faces(scene) -> dict[str, dict[str, Any]]:
    """The wall faces of a scene: ``{face: {"axis", "side" (-1/+1), "position" [m], "kind", "thickness"}}``.

    From its ``walls`` (faces of kind ``none`` left out) and ``friction_walls`` boundaries; where two
    act on one face the thicker (the one whose innermost constrained node lies further in) wins.
    Empty when the scene has no wall.
    """
    from ..boundaries import FrictionWalls, Walls, _faces

    cells = np.asarray(scene.cells)
    out: dict[str, dict[str, Any]] = {}

    def add(face: str, kind: str, t: int) -> None:
        a = "xyz".index(face[0])
        side = -1 if face[1] == "-" else 1
        pos = float(scene.origin[a] + ((t - 1) if side < 0 else (cells[a] - t + 1)) * scene.dx)
        old = out.get(face)
        if old is None or side * (old["position"] - pos) > 0:  # keep the innermost face
            out[face] = {"axis": a, "side": side, "position": pos, "kind": kind, "thickness": int(t)}

    for b in scene.boundaries:
        if isinstance(b, Walls):
            for face, kind in zip(_faces(scene.dim), b.face_kinds(scene.dim)):
                if kind != "none":
                    add(face, kind, b.thickness)
        elif isinstance(b, FrictionWalls):
            add(b.face, "friction", b.thickness)
    return {f: out[f] for f in _faces(scene.dim) if f in out}


class WallPenetration:
    """Streaming accumulator: particles beyond the wall faces / inside obstacles / outside the interior.

    Args:
        scene: the ``Scene`` (its walls, friction walls, planes and box obstacles; ``dx``; ``inner_bounds``).
        obstacles: also count penetration into ``box_obstacle`` boundaries.
        planes: also count particles behind ``plane`` boundaries.

    Call ``update(x, step)`` once per kept frame (any float dtype, [N, D]); ``summary()`` at any time.
    """

    def __init__(self, scene, obstacles: bool = True, planes: bool = True):
        from ..boundaries import BoxObstacle, Plane

        self.dim = int(scene.dim)
        self.dx = float(scene.dx)
        self.faces = wall_faces(scene)
        lo, hi = scene.inner_bounds
        self._inner = (np.asarray(lo, float), np.asarray(hi, float))
        # wall-like half-spaces: (label, axis or None, sign/normal, position/point)
        self._labels: list[str] = []
        self._axis_faces: list[tuple[int, int, float]] = []     # (axis, side, position)
        for f, d in self.faces.items():
            self._labels.append(f)
            self._axis_faces.append((d["axis"], d["side"], d["position"]))
        self._planes: list[tuple[np.ndarray, float]] = []       # (unit normal into the free side, n . point)
        if planes:
            for k, b in enumerate(scene.boundaries):
                if isinstance(b, Plane):
                    n = b.unit_normal()
                    self._labels.append(f"plane[{k}]")
                    self._planes.append((n, float(n @ np.asarray(b.point, float))))
        # the tank extent per axis: wall faces where there are walls, else the grid edges
        tank_lo = np.asarray(scene.origin, float).copy()
        tank_hi = tank_lo + np.asarray(scene.cells) * self.dx
        for d in self.faces.values():
            (tank_lo if d["side"] < 0 else tank_hi)[d["axis"]] = d["position"]
        self._boxes: list[tuple[np.ndarray, np.ndarray, list[tuple[int, int, str]]]] = []
        self._box_labels: list[list[str]] = []
        if obstacles:
            for k, b in enumerate(scene.boundaries):
                if not isinstance(b, BoxObstacle):
                    continue
                blo, bhi = np.asarray(b.lo, float), np.asarray(b.hi, float)
                usable = []
                for a in range(self.dim):
                    if blo[a] > tank_lo[a]:
                        usable.append((a, -1, f"{'xyz'[a]}-"))
                    if bhi[a] < tank_hi[a]:
                        usable.append((a, 1, f"{'xyz'[a]}+"))
                if not usable:   # a box covering the whole tank: every face counts
                    usable = [(a, s, f"{'xyz'[a]}{'-' if s < 0 else '+'}") for a in range(self.dim) for s in (-1, 1)]
                self._boxes.append((blo, bhi, usable))
                self._box_labels.append([f"box_obstacle[{k}]:{u[2]}" for u in usable])
        self.reset()

    # ---- accumulation -------------------------------------------------------------------------
    def reset(self) -> None:
        self.frames = 0
        self.last_step: int | None = None
        self._ever_wall: np.ndarray | None = None
        self._ever_obst: np.ndarray | None = None
        self.max_wall = self.final_wall = 0
        self.max_obst = self.final_obst = 0
        self.max_interior = self.final_interior = 0
        self._ever_int: np.ndarray | None = None
        self.worst = {"depth": 0.0, "step": None, "particle": None, "face": None}
        self.final_worst = 0.0
        self.by_face: dict[str, float] = {}

    def update(self, x: np.ndarray, step: int) -> int:
        """Account for one frame; returns how many particles are beyond a wall face or inside an obstacle now."""
        x = np.asarray(x)
        if x.ndim != 2 or x.shape[1] != self.dim:
            raise ValueError(f"WallPenetration.update: x must be [N, {self.dim}], got shape {x.shape}.")
        n = len(x)
        if self._ever_wall is None:
            self._ever_wall = np.zeros(n, bool)
            self._ever_obst = np.zeros(n, bool)
            self._ever_int = np.zeros(n, bool)
        elif len(self._ever_wall) != n:
            raise ValueError(f"WallPenetration.update: {n} particles, earlier frames had {len(self._ever_wall)}.")
        self.frames += 1
        self.last_step = int(step)
        frame_worst = 0.0

        # wall faces and planes: signed depth beyond the face (float64), the deepest per particle; the
        # face of the deepest is looked up only for the (few) particles beyond one
        cnt = 0
        if self._labels:
            depth = None
            for a, side, pos in self._axis_faces:
                d = x[:, a].astype(np.float64)
                d -= pos
                if side < 0:
                    np.negative(d, out=d)
                depth = d if depth is None else np.maximum(depth, d, out=depth)
            for nrm, c in self._planes:
                d = np.float64(c) - x @ nrm
                depth = d if depth is None else np.maximum(depth, d, out=depth)
            beyond = depth > 0
            idx = np.nonzero(beyond)[0]
            cnt = len(idx)
            self._ever_wall |= beyond
            if cnt:
                frame_worst = self._record(idx, self._face_depths(x[idx]), self._labels, int(step), frame_worst)
        self.final_wall = cnt
        self.max_wall = max(self.max_wall, cnt)

        # box obstacles: strictly inside, depth to the nearest usable face
        inside_any = np.zeros(n, bool)
        for (blo, bhi, usable), labels in zip(self._boxes, self._box_labels):
            inside = np.ones(n, bool)
            for a in range(self.dim):
                inside &= (x[:, a] > blo[a]) & (x[:, a] < bhi[a])
            idx = np.nonzero(inside)[0]
            if len(idx) == 0:
                continue
            inside_any[idx] = True
            xi = x[idx].astype(np.float64)
            # depth inside = distance to the nearest usable face, as minus the largest signed "beyond" distance
            dist = np.stack([(xi[:, a] - blo[a]) if s < 0 else (bhi[a] - xi[:, a]) for a, s, _ in usable], axis=1)
            frame_worst = self._record(idx, -dist, labels, int(step), frame_worst, nearest=True)
        cnt_o = int(np.count_nonzero(inside_any))
        self._ever_obst |= inside_any
        self.final_obst = cnt_o
        self.max_obst = max(self.max_obst, cnt_o)

        # the domain interior of the stability guard
        lo, hi = self._inner
        out = np.zeros(n, bool)
        for a in range(self.dim):
            out |= (x[:, a] < lo[a]) | (x[:, a] >= hi[a])
        ci = int(np.count_nonzero(out))
        self._ever_int |= out
        self.final_interior = ci
        self.max_interior = max(self.max_interior, ci)

        self.final_worst = frame_worst
        return cnt + cnt_o

    def _face_depths(self, xs: np.ndarray) -> np.ndarray:
        """Signed distance beyond each wall face / plane, float64 [n, faces] (positive: beyond)."""
        xs = xs.astype(np.float64)
        cols = [side * (xs[:, a] - pos) for a, side, pos in self._axis_faces]
        cols += [c - xs @ nrm for nrm, c in self._planes]
        return np.stack(cols, axis=1)

    def _record(self, idx, signed, labels, step, frame_worst, nearest=False) -> float:
        """Update the running worst and the per-face maxima from the particles ``idx`` and their signed
        distances ``signed`` [n, faces]: the depth is the largest (walls: beyond the deepest face) or,
        with ``nearest`` (obstacles: ``signed`` = minus the distance to each face), minus the largest."""
        k = np.argmax(signed, axis=1)
        d = signed[np.arange(len(idx)), k]
        if nearest:
            d = -d
        j = int(np.argmax(d))
        dp = float(d[j])
        if dp > self.worst["depth"]:
            self.worst = {"depth": dp, "step": step, "particle": int(idx[j]), "face": labels[int(k[j])]}
        for f in np.unique(k):
            m = float(d[k == f].max())
            lab = labels[int(f)]
            if m > self.by_face.get(lab, 0.0):
                self.by_face[lab] = m
        return max(frame_worst, dp)

    # ---- results ------------------------------------------------------------------------------
    def summary(self) -> dict[str, Any]:
        """Plain-Python results (zeros / None when nothing crossed):

        * ``particles_beyond_walls``: the largest number, at any frame, of particles beyond a wall face
          or plane; ``_final``: at the last frame; ``_ever``: distinct particles beyond one at some frame.
        * ``particles_in_obstacles`` (``_final``, ``_ever``): the same for box obstacles.
        * ``particles_beyond_interior`` (``_final``, ``_ever``): outside ``scene.inner_bounds``.
        * ``worst_depth_m`` / ``worst_depth_dx``: the deepest penetration seen (walls, planes, obstacles),
          at ``worst_step`` by particle ``worst_particle`` through ``worst_face`` (None when nothing crossed);
          ``final_depth_m`` / ``final_depth_dx``: the deepest at the last frame.
        * ``depth_by_face_dx``: the deepest penetration per face that was crossed [cells].
        * ``wall_faces``: the wall face positions used [m]; ``frames``: frames seen; ``last_step``.
        """
        dx = self.dx
        ew = int(self._ever_wall.sum()) if self._ever_wall is not None else 0
        eo = int(self._ever_obst.sum()) if self._ever_obst is not None else 0
        ei = int(self._ever_int.sum()) if self._ever_int is not None else 0
        return {
            "particles_beyond_walls": int(self.max_wall),
            "particles_beyond_walls_final": int(self.final_wall),
            "particles_beyond_walls_ever": ew,
            "particles_in_obstacles": int(self.max_obst),
            "particles_in_obstacles_final": int(self.final_obst),
            "particles_in_obstacles_ever": eo,
            "particles_beyond_interior": int(self.max_interior),
            "particles_beyond_interior_final": int(self.final_interior),
            "particles_beyond_interior_ever": ei,
            "worst_depth_m": float(self.worst["depth"]),
            "worst_depth_dx": float(self.worst["depth"] / dx),
            "worst_step": self.worst["step"],
            "worst_particle": self.worst["particle"],
            "worst_face": self.worst["face"],
            "final_depth_m": float(self.final_worst),
            "final_depth_dx": float(self.final_worst / dx),
            "depth_by_face_dx": {k: float(v / dx) for k, v in self.by_face.items()},
            "wall_faces": {f: float(d["position"]) for f, d in self.faces.items()},
            "frames": int(self.frames),
            "last_step": self.last_step,
        }


def trajectory_penetration(scene, traj, **kw) -> dict[str, Any]:
    """``WallPenetration(scene, **kw)`` fed with every frame of a ``Trajectory``; returns its summary."""
    acc = WallPenetration(scene, **kw)
    for x, s in zip(traj.x, traj.step):
        acc.update(x, int(s))
    return acc.summary()
