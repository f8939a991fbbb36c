"""Affine PIC (Jiang et al. 2015; JAX-MPM Eq. B.1): carries C = B D^-1; F updated with sum v_i grad w."""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from ...core.interfaces import AbstractTransfer
from .._common import builtin_implementations


@dataclass(frozen=True)
class Transfer(AbstractTransfer):
    """APIC: momentum m (v + C (x_i - x_p)) and the gradient force; G2P rebuilds C from the first moment."""

    name: ClassVar[str] = "apic"
    implementations: ClassVar[dict] = builtin_implementations("apic")
    shapes: ClassVar[frozenset | None] = None            # reads D^-1 as Dinv where it needs D
    carries_C: ClassVar[bool] = True
    momentum_terms: ClassVar[frozenset] = frozenset({"affine", "gradient"})
    moments: ClassVar[frozenset] = frozenset({"first", "gradient"})
    conserves: ClassVar[frozenset] = frozenset({"linear_momentum", "angular_momentum"})   # Jiang et al. 2015 Sec. 5.3
