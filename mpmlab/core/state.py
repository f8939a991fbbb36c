"""Trajectory: frames of a rollout as NumPy arrays, plus the static particle data that explain them."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass
class Trajectory:
    """Frames ``[T, N, ...]`` of one rollout.

    Attributes:
        x: positions [T, N, D] m.  v: velocities [T, N, D] m/s.
        time: [T] s.  step: [T] step index of each frame.
        fields: other per-particle frames by name (``F``, ``C``, ``J``, ``sigma``, ``eps_p``); a field
            is present only where the scene's laws/transfer carry it (``F`` [T, N_F, D, D] covers the
            particles of laws with an F state, see ``field_particles``).
        field_particles: for each entry of ``fields``, the particle indices it covers.
        mass, volume, material_id, body_id: [N] static particle data.
        materials: per material group: ``{"law": name, "param_names": [...], "start": i, "stop": j}``;
            ``params`` [N, P_max] (NaN-padded) holds each particle's law parameters.
        meta: dim, dt, dx, grid origin/shape, backend, transfer, precision, scene name, ...
    """

    x: np.ndarray
    v: np.ndarray
    time: np.ndarray
    step: np.ndarray
    mass: np.ndarray
    volume: np.ndarray
    material_id: np.ndarray
    body_id: np.ndarray
    materials: list[dict]
    params: np.ndarray
    meta: dict[str, Any]
    fields: dict[str, np.ndarray] = field(default_factory=dict)
    field_particles: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def frame_count(self) -> int:
        return len(self.x)

    @property
    def particle_count(self) -> int:
        return self.x.shape[1]

    def truncated(self, frames: int) -> "Trajectory":
        """The first ``frames`` frames (used to keep what was produced before a divergence)."""
        return Trajectory(self.x[:frames], self.v[:frames], self.time[:frames], self.step[:frames], self.mass,
                          self.volume, self.material_id, self.body_id, self.materials, self.params, dict(self.meta),
                          {k: a[:frames] for k, a in self.fields.items()}, dict(self.field_particles))
