"""MLS-MPM (Hu et al. 2018), the scheme NCLaw uses: APIC's C, the MLS force, C as the velocity gradient."""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from ...core.interfaces import AbstractTransfer
from .._common import builtin_implementations


@dataclass(frozen=True)
class Transfer(AbstractTransfer):
    """MLS: the stress enters as an affine momentum term, A = m C - 4 dt V / dx^2 tau (no weight gradient)."""

    name: ClassVar[str] = "mls"
    implementations: ClassVar[dict] = builtin_implementations("mls")
    shapes: ClassVar[frozenset | None] = None            # reads D^-1 as Dinv where it needs D
    carries_C: ClassVar[bool] = True
    momentum_terms: ClassVar[frozenset] = frozenset({"affine"})
    moments: ClassVar[frozenset] = frozenset({"first"})
    conserves: ClassVar[frozenset] = frozenset({"linear_momentum", "angular_momentum"})   # Jiang et al. 2015 Sec. 5.3
