"""Uniform GIMP (Bardenhagen & Kober 2004): the linear hat averaged over the particle's box of half width
lp, lp fixed at its initial value (lp = V0^(1/D) / 2, i.e. dx / (2 ppc) for a regular lattice)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from ...core.interfaces import AbstractShape


@dataclass(frozen=True)
class Shape(AbstractShape):
    """C1 across cells, support 2 (1 + lp) cells inside a window of 3 for lp <= dx/2; fx in [0.5, 1.5).
    D_p varies with the particle's position in its cell, so the backends compute it from its weights."""

    name: ClassVar[str] = "ugimp"
    implementations: ClassVar[dict] = {"jax": "mpmlab.shapes.ugimp.jax:make", "warp": "mpmlab.shapes.ugimp.warp:make"}
    width: ClassVar[int] = 3
    offset: ClassVar[float] = 0.5
    inv_D_cells: ClassVar[float | None] = None
    uses_particle_size: ClassVar[bool] = True
    max_particle_size: ClassVar[float] = 0.5
