"""CPDI (Sadeghirad et al. 2011): the particle's domain as a parallelogram / parallelepiped carried by its
deformation, the weights averaged over its corners. Declared so that asking for it gives a clear
answer; mpmlab's kernels do not carry it yet (issue 19 item 1: it needs the per-particle domain
vectors as declared transfer state and a corner P2G / G2P)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from ...core.interfaces import AbstractShape


@dataclass(frozen=True)
class Shape(AbstractShape):
    name: ClassVar[str] = "cpdi"
    implementations: ClassVar[dict] = {}
    kind: ClassVar[str] = "corners"
    width: ClassVar[int] = 2
    offset: ClassVar[float] = 0.0
