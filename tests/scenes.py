"""Tiny scenes shared by tests (small sizes: the suite runs on 2 CPU cores)."""
from __future__ import annotations

import numpy as np

import mpmlab
from mpmlab.boundaries import Walls

#: Parameters that make every built-in law deform and (for plastic laws) yield within 50 steps.
LAW_PARAMS = {
    "fixed_corotated": {"E": 2e4, "nu": 0.3},
    "hencky_drucker_prager": {"E": 2e4, "nu": 0.3, "friction_angle": 30.0},
    "hencky_von_mises": {"E": 2e4, "nu": 0.3, "yield_stress": 20.0},
    "weakly_compressible": {"bulk_modulus": 2e4},
    "newtonian_fluid": {"sound_speed": 5.0, "viscosity": 0.1},
    "drucker_prager_jaumann": {"bulk_modulus": 2e4, "nu": 0.3, "friction_angle": 30.0},
}


def all_laws_scene(dim: int, laws=None, dt: float = 1e-3) -> mpmlab.Scene:
    """One small body per law, spinning and moving, falling onto 2-cell walls of a unit box."""
    laws = list(laws or LAW_PARAMS)
    bodies = []
    dx = 0.05
    for k, name in enumerate(laws):
        c = np.full(dim, 0.5)
        c[0] = 0.15 + 0.14 * k
        c[1] = 0.2 + 0.05 * (k % 3)
        h = 0.04
        w = 2.0 if dim == 2 else [0.0, 1.0, 2.0]
        v = np.zeros(dim); v[0] = 0.3 * (-1) ** k; v[1] = -0.5
        bodies.append(mpmlab.Body(shape={"kind": "box", "lo": (c - h).tolist(), "hi": (c + h).tolist()},
                                  material=name, params=LAW_PARAMS.get(name, {}), density=1000.0,
                                  velocity=v.tolist(), angular_velocity=w, particles_per_cell=2**dim, name=name))
    domain = ([0.0] * dim, [1.0] * dim)
    g = np.zeros(dim); g[1] = -9.8
    return mpmlab.Scene(dim=dim, dx=dx, domain=domain, bodies=bodies, gravity=g.tolist(),
                        boundaries=[Walls(default="separate", thickness=2)], dt=dt, name=f"all_laws_{dim}d")
