"""Per-frame conservation and energy metrics of a ``Trajectory`` (NumPy, float64).

``compute_metrics(traj)`` returns ``{name: array}`` with one entry per frame:

* ``mass`` [T]: total particle mass, sum m_p.
* ``linear_momentum`` [T, D]: sum m_p v_p.
* ``kinetic_energy`` [T]: 1/2 sum m_p |v_p|^2 (particle velocities; the affine part of APIC is left out).
* ``angular_momentum`` about the origin, [T] in 2D (the z component) or [T, 3] in 3D:
  L = sum_p m_p x_p x v_p, plus, when the affine matrix ``C`` was recorded, the APIC spin term
  sum_p m_p (dx^2/4) eps : C_p^T (Jiang et al. 2015, quadratic B-splines: sum_i w_ip (x_i - x_p)(x_i - x_p)^T
  = dx^2/4 I). With that term L equals the grid angular momentum sum_i x_i x m_i v_i that P2G
  produces (exactly, for every transfer whose P2G momentum is m_p (v_p + C_p (x_i - x_p))); in 2D the
  term is m_p dx^2/4 (C_yx - C_xy), in 3D m_p dx^2/4 (C_zy - C_yz, C_xz - C_zx, C_yx - C_xy).
* ``gravity_potential_energy`` [T]: -sum m_p g . x_p (zero at the origin), when ``meta`` has gravity.
* ``elastic_energy`` [T]: sum_p V0_p psi(F_p) over the material groups whose law's reference module
  defines ``energy(F, params)`` and whose particles all have ``F`` recorded. Absent when no group
  qualifies (nothing is estimated); groups of other laws contribute nothing, and ``elastic_energy()``
  also returns which groups were included.

``METRIC_INFO`` / ``metric_info(name, dim)`` give each metric's family (the plot it belongs to in a
recording), its label and its unit; in 2D masses are per unit depth, so every unit gains a ``/m``.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from ..core.state import Trajectory


#: name -> (family, label, unit in 3D); ``step_time_ms`` is added by ``task=simulate`` (wall time per step of
#: the chunk ending at each frame; NaN where it is not a steady-state step: frame 0 and the compile chunk).
METRIC_INFO: dict[str, tuple[str, str, str]] = {
    "kinetic_energy": ("energy", "kinetic", "J"),
    "gravity_potential_energy": ("energy", "gravitational (zero at the origin)", "J"),
    "elastic_energy": ("energy", "elastic", "J"),
    "linear_momentum": ("linear_momentum", "p", "kg·m/s"),
    "angular_momentum": ("angular_momentum", "L", "kg·m²/s"),
    "mass": ("mass", "mass", "kg"),
    "step_time_ms": ("step_time", "wall time per step", "ms"),
}
#: family -> plot title (without the unit)
FAMILY_TITLES = {"energy": "energy", "linear_momentum": "linear momentum", "angular_momentum": "angular momentum",
                 "mass": "mass", "step_time": "step time"}
#: families whose unit is per unit depth in 2D (all but the wall time)
_PER_DEPTH = {"energy", "linear_momentum", "angular_momentum", "mass"}


def metric_info(name: str, dim: int = 3) -> tuple[str, str, str]:
    """(family, label, unit) of a metric; a name not in ``METRIC_INFO`` is its own family, unit ''.

    In 2D the masses are per unit depth: kg/m, J/m, (kg·m/s)/m, (kg·m²/s)/m.
    """
    family, label, unit = METRIC_INFO.get(name, (name, name.replace("_", " "), ""))
    if dim == 2 and family in _PER_DEPTH and unit:
        unit = f"{unit}/m" if "·" not in unit else f"({unit})/m"
    return family, label, unit


def _cross(x: np.ndarray, v: np.ndarray) -> np.ndarray:
    if x.shape[-1] == 2:
        return x[..., 0] * v[..., 1] - x[..., 1] * v[..., 0]
    return np.cross(x, v)


def _spin(C: np.ndarray) -> np.ndarray:
    """eps : C^T per particle: [..., ] in 2D (z), [..., 3] in 3D."""
    if C.shape[-1] == 2:
        return C[..., 1, 0] - C[..., 0, 1]
    return np.stack([C[..., 2, 1] - C[..., 1, 2], C[..., 0, 2] - C[..., 2, 0], C[..., 1, 0] - C[..., 0, 1]], axis=-1)


def _law_energy(law_name: str):
    """The law's ``reference.energy`` function, or None (unknown law, or a law without an energy).

    By name: a trajectory's material record (possibly read from a file) names its law, not its
    options, so there is no configured instance here; ``reference`` is a class attribute that every
    instance of the law shares (a ``phase_change`` pair inherits the registered class's, which has no
    energy)."""
    from ..core import registry
    from ..core.errors import MpmlabError

    try:
        law = registry.laws.get(law_name)
    except (MpmlabError, ImportError):
        return None
    return getattr(getattr(law, "reference", None), "energy", None)


def _energy_density(fn, F: np.ndarray, prm: np.ndarray) -> np.ndarray:
    """psi for a batch F [M, D, D], prm [M, P]; falls back to a loop for non-vectorised energies."""
    try:
        out = np.asarray(fn(F, prm), dtype=np.float64)
        if out.shape == (len(F),):
            return out
    except Exception:
        pass
    return np.array([float(fn(F[i], prm[i])) for i in range(len(F))])


def elastic_energy(F: np.ndarray, F_particles: np.ndarray, volume: np.ndarray, materials: list[dict],
                   params: np.ndarray) -> tuple[np.ndarray, list[int]] | None:
    """(sum_p V0_p psi(F_p) per frame [T], indices of the material groups included), or None.

    ``F`` is [T, N_F, D, D] over the particles ``F_particles``.
    """
    F = np.asarray(F, dtype=np.float64)
    F_particles = np.asarray(F_particles)
    T = F.shape[0]
    total = np.zeros(T)
    used = []
    for k, m in enumerate(materials):
        start, stop = int(m["start"]), int(m["stop"])
        sel = np.nonzero((F_particles >= start) & (F_particles < stop))[0]
        if len(sel) != stop - start or len(sel) == 0:
            continue
        fn = _law_energy(m.get("law", ""))
        if fn is None:
            continue
        pid = F_particles[sel]
        prm = np.asarray(params[pid, : len(m.get("param_names", []))], dtype=np.float64)
        Fg = F[:, sel].reshape(-1, *F.shape[2:])
        psi = _energy_density(fn, Fg, np.tile(prm, (T, 1))).reshape(T, len(sel))
        total += psi @ np.asarray(volume, dtype=np.float64)[pid]
        used.append(k)
    return (total, used) if used else None


def frame_metrics(x: np.ndarray, v: np.ndarray, mass: np.ndarray, *, volume: np.ndarray | None = None,
                  dx: float | None = None, gravity: Any = None, C: np.ndarray | None = None,
                  C_particles: np.ndarray | None = None, F: np.ndarray | None = None,
                  F_particles: np.ndarray | None = None, materials: list[dict] | None = None,
                  params: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """The metrics of frames ``x``, ``v`` [T, N, D] (see the module docstring); C and F are [T, n, D, D]."""
    x = np.asarray(x, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    m = np.asarray(mass, dtype=np.float64)
    out: dict[str, np.ndarray] = {
        "mass": np.full(x.shape[0], m.sum()),
        "linear_momentum": np.einsum("p,tpd->td", m, v),
        "kinetic_energy": 0.5 * np.einsum("p,tpd,tpd->t", m, v, v),
    }
    L = np.einsum("p,tp...->t...", m, _cross(x, v))
    if C is not None and dx is not None:
        C = np.asarray(C, dtype=np.float64)
        idx = np.arange(C.shape[1]) if C_particles is None else np.asarray(C_particles)
        L = L + (dx * dx / 4.0) * np.einsum("p,tp...->t...", m[idx], _spin(C))
    out["angular_momentum"] = L
    if gravity is not None:
        g = np.asarray(gravity, dtype=np.float64)
        if g.shape == (x.shape[-1],):
            out["gravity_potential_energy"] = -np.einsum("p,tpd,d->t", m, x, g)
    if F is not None and volume is not None and materials and params is not None:
        idx = np.arange(np.asarray(F).shape[1]) if F_particles is None else F_particles
        e = elastic_energy(F, idx, volume, materials, params)
        if e is not None:
            out["elastic_energy"] = e[0]
    return out


def compute_metrics(traj: Trajectory, elastic: bool = True) -> dict[str, np.ndarray]:
    """Per-frame metrics of ``traj``: mass, linear_momentum, kinetic_energy, angular_momentum,
    gravity_potential_energy and (when available, see the module docstring) elastic_energy."""
    meta = traj.meta or {}
    use_F = elastic and "F" in traj.fields
    return frame_metrics(
        traj.x, traj.v, traj.mass, volume=traj.volume, dx=meta.get("dx"), gravity=meta.get("gravity"),
        C=traj.fields.get("C"), C_particles=traj.field_particles.get("C"),
        F=traj.fields["F"] if use_F else None, F_particles=traj.field_particles.get("F"),
        materials=traj.materials, params=traj.params,
    )


def state_metrics(static: Trajectory, npstate: dict) -> dict[str, np.ndarray]:
    """Metrics of one rollout state (an ``on_frame`` NumPy state), each with a leading axis of 1."""
    meta = static.meta or {}
    one = lambda k: None if k not in npstate else np.asarray(npstate[k])[None]
    return frame_metrics(
        one("x"), one("v"), static.mass, volume=static.volume, dx=meta.get("dx"), gravity=meta.get("gravity"),
        C=one("C"), C_particles=npstate.get("C_particles"), F=one("F"), F_particles=npstate.get("F_particles"),
        materials=static.materials, params=static.params,
    )


class MetricSeries:
    """Rollout ``on_frame`` companion: the metrics of each kept frame as it is produced, so a run that
    streams its frames to disk never holds them (``result()``: ``{name: array [T, ...]}``, as
    ``compute_metrics`` of the whole trajectory)."""

    def __init__(self, static: Trajectory):
        self.static = static
        self._rows: list[dict[str, np.ndarray]] = []

    def __call__(self, frame_index: int, npstate: dict) -> None:
        self._rows.append(state_metrics(self.static, npstate))

    def __len__(self) -> int:
        return len(self._rows)

    def result(self) -> dict[str, np.ndarray]:
        if not self._rows:
            return {}
        keys = [k for k in self._rows[0] if all(k in r for r in self._rows)]
        return {k: np.concatenate([r[k] for r in self._rows]) for k in keys}
