"""Cubic B-spline (Steffen et al. 2008): C2, support 4 cells, smoother cell crossing than quadratic."""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from ...core.interfaces import AbstractShape


@dataclass(frozen=True)
class Shape(AbstractShape):
    """fx = x/dx - base in [1, 2); D_p = dx^2/3 I (sum_i N(r_i) r_i^2 = 1/3 for the cubic B-spline)."""

    name: ClassVar[str] = "cubic"
    implementations: ClassVar[dict] = {"jax": "mpmlab.shapes.cubic.jax:make", "warp": "mpmlab.shapes.cubic.warp:make"}
    width: ClassVar[int] = 4
    offset: ClassVar[float] = 1.0
    inv_D_cells: ClassVar[float | None] = 3.0
