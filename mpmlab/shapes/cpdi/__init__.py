"""CPDI (Sadeghirad, Brannon & Burghardt 2011): the particle's domain as a parallelogram / parallelepiped
carried by the flow, the weights averaged over its 2^D corners (``reference.py`` has the formulas)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from ...core.interfaces import AbstractShape


@dataclass(frozen=True)
class Shape(AbstractShape):
    """``kind = "corners"``: P2G and G2P run over the corners x_p + R s_c of each particle's domain, each a
    pseudo-particle of weight 2^-D with the linear hat's window (2 nodes per axis from floor(x_c/dx)); the
    domain R [D, D] is transfer state (``state``: "domain", updated in G2P from sum_i v_i grad S_ip^T). D_p
    (APIC / MLS) is per particle and not diagonal: 2^-D sum_c dx^2 diag(f_c(1 - f_c)) + R R^T."""

    name: ClassVar[str] = "cpdi"
    implementations: ClassVar[dict] = {"jax": "mpmlab.shapes.cpdi.jax:make", "warp": "mpmlab.shapes.cpdi.warp:make"}
    kind: ClassVar[str] = "corners"
    width: ClassVar[int] = 2
    offset: ClassVar[float] = 0.0
    inv_D_cells: ClassVar[float | None] = None
    state: ClassVar[tuple] = ("domain",)
