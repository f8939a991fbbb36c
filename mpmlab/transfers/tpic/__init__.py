"""Taylor PIC (JAX-MPM App. B, Eq. B.2): carries the particle velocity gradient as the affine term."""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from ...core.interfaces import AbstractTransfer
from .._common import builtin_implementations


@dataclass(frozen=True)
class Transfer(AbstractTransfer):
    """TPIC: APIC's P2G with C = sum v_i (grad w)^T, the velocity gradient the law also gets."""

    name: ClassVar[str] = "tpic"
    implementations: ClassVar[dict] = builtin_implementations("tpic")
    shapes: ClassVar[frozenset | None] = None            # reads D^-1 as Dinv where it needs D
    carries_C: ClassVar[bool] = True
    momentum_terms: ClassVar[frozenset] = frozenset({"affine", "gradient"})
    moments: ClassVar[frozenset] = frozenset({"gradient"})
