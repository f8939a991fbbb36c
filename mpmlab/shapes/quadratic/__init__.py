"""Quadratic B-spline (Steffen et al. 2008; JAX-MPM Eq. 9): mpmlab's default shape function."""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from ...core.interfaces import AbstractShape


@dataclass(frozen=True)
class Shape(AbstractShape):
    """C1, support 3 cells; fx = x/dx - base in [0.5, 1.5). D_p = dx^2/4 I (Jiang et al. 2015)."""

    name: ClassVar[str] = "quadratic"
    implementations: ClassVar[dict] = {"jax": "mpmlab.shapes.quadratic.jax:make",
                                       "warp": "mpmlab.shapes.quadratic.warp:make"}
    width: ClassVar[int] = 3
    offset: ClassVar[float] = 0.5
    inv_D_cells: ClassVar[float | None] = 4.0
