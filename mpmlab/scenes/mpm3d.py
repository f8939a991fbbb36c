"""The standard benchmark scene of Taichi's ``mpm3d`` example, rebuilt as an mpmlab ``Scene``.

Unit-cube domain, ``n_grid`` cells per axis, ``n = n_grid^dim / 4`` particles drawn uniformly in
``[0.15, 0.55]^dim`` (NumPy ``default_rng(seed).random(..., dtype=float32) * 0.4 + 0.15``: the same
positions as the peer benchmark's ``init_x``), E = 400, rho = 1, gravity 9.8 along -y, 3-cell
"separate" walls, dt = 4e-4 / 2e-4 / 8e-5 for n_grid = 32 / 64 / 128, and mpm3d's particle volume
quirk ``p_vol = (dx/2)^2`` (kept for parity; it is not a volume in 3D).

The material is a J-based weakly compressible fluid with bulk modulus E (law
``weakly_compressible``). Its Kirchhoff stress is ``tau = K J (J - 1) I``; Taichi's mpm3d uses
``E (J - 1) I``: the two agree to first order in (J - 1) (they differ by the factor J, under 1 %
over the usual runs, where |J - 1| stays below a few per cent). Where ``weakly_compressible`` is not
available, ``law="fixed_corotated"`` (E = 400, nu = 0.2) is a drop-in elastic stand-in of similar
cost class (it carries a full F and an SVD per particle, so it is slower than the J-only fluid).

With the MLS transfer (``transfer="mls"``) the step is the one of mpm3d: quadratic B-spline,
APIC affine C, MLS force, C as the velocity gradient.
"""
from __future__ import annotations

import numpy as np

from ..boundaries import Walls
from ..core.scene import Body, Scene

DT = {32: 4e-4, 64: 2e-4, 128: 8e-5}
E, RHO, GRAVITY, BOUND = 400.0, 1.0, 9.8, 3


def peer_positions(n_grid: int, dim: int = 3, seed: int = 0) -> np.ndarray:
    """mpm3d's initial positions: ``n_grid^dim // 4`` points uniform in [0.15, 0.55]^dim (float32 draw)."""
    n = n_grid**dim // 4
    return (np.random.default_rng(seed).random((n, dim), dtype=np.float32) * 0.4 + 0.15).astype(np.float32)


def mpm3d_fluid(n_grid: int = 64, dim: int = 3, law: str = "weakly_compressible", dt: float | None = None,
                seed: int = 0, boundaries: list | None = None) -> Scene:
    """Taichi mpm3d's scene (``dim=2``: the same recipe in the unit square).

    Args:
        n_grid: cells per axis (3D: 32, 64, 128 take mpm3d's time steps; otherwise dt = 0.0128 / n_grid,
            e.g. 2D n_grid = 512 for 65k particles).
        law: ``weakly_compressible`` (bulk_modulus = E) or an elastic stand-in (``fixed_corotated``).
        dt: time step; default mpm3d's for ``n_grid``.
        seed: NumPy seed of the positions (0 = the peer benchmark's).
        boundaries: extra boundaries appended after the 3-cell separate walls.
    """
    if dt is None:
        dt = DT.get(n_grid, 0.0128 / n_grid) if dim == 3 else 0.0128 / n_grid
    dx = 1.0 / n_grid
    x = peer_positions(n_grid, dim, seed).astype(np.float64)
    params = {"bulk_modulus": E} if law == "weakly_compressible" else {"E": E, "nu": 0.2}
    body = Body(shape={"kind": "box", "lo": [0.15] * dim, "hi": [0.55] * dim}, material=law, params=params,
                density=RHO, sampling="random", count=len(x), particle_volume=(dx * 0.5) ** 2, name="fluid")
    gravity = [0.0] * dim
    gravity[1] = -GRAVITY
    scene = Scene(dim=dim, dx=dx, domain=([0.0] * dim, [1.0] * dim), bodies=[body], gravity=gravity,
                  boundaries=[Walls(default="separate", thickness=BOUND)] + list(boundaries or []), dt=dt,
                  cfl_limit=1.0, name=f"mpm3d_{dim}d_{n_grid}", seed=seed)
    # replace the sampled points by mpm3d's own draw (same count, same box), before anything uses them
    scene.particles().x[:] = x
    return scene


def elastic_cube(n_grid: int = 64, dim: int = 3, E: float = 1e4, nu: float = 0.3, density: float = 1000.0,
                 particles_per_cell: int | None = None, law: str = "fixed_corotated", **law_params) -> Scene:
    """A fixed-corotated elastic cube falling onto the floor of a unit box (3-cell sticky floor, slip sides).

    The cube has side 0.3 (x in [0.35, 0.65], y in [0.2, 0.5]); with ``particles_per_cell = 2^dim``
    (default) it holds about as many particles as ``mpm3d_fluid(n_grid)`` in 3D (0.86 n_grid^3 / 4).
    """
    ppc = particles_per_cell or 2**dim
    lo, hi = [0.35] * dim, [0.65] * dim
    lo[1], hi[1] = 0.2, 0.5
    body = Body(shape={"kind": "box", "lo": lo, "hi": hi}, material=law, params={"E": E, "nu": nu, **law_params},
                density=density, particles_per_cell=ppc, name="cube")
    gravity = [0.0] * dim
    gravity[1] = -GRAVITY
    return Scene(dim=dim, dx=1.0 / n_grid, domain=([0.0] * dim, [1.0] * dim), bodies=[body], gravity=gravity,
                 boundaries=[Walls(default="slip", faces={"y-": "sticky"}, thickness=BOUND)], dt="auto",
                 name=f"elastic_cube_{dim}d_{n_grid}")
