"""Particle-in-cell (Harlow 1964; JAX-MPM Eq. 16): v_p = sum w v_i, no C stored; the most dissipative."""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from ...core.interfaces import AbstractTransfer
from .._common import builtin_implementations


@dataclass(frozen=True)
class Transfer(AbstractTransfer):
    """PIC: momentum m v and the gradient force (JAX-MPM Eq. 12); F updated with sum v_i grad w (Eq. 18)."""

    name: ClassVar[str] = "pic"
    implementations: ClassVar[dict] = builtin_implementations("pic")
    shapes: ClassVar[frozenset | None] = None            # reads D^-1 as Dinv where it needs D
    momentum_terms: ClassVar[frozenset] = frozenset({"gradient"})
    moments: ClassVar[frozenset] = frozenset({"gradient"})
