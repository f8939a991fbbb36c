"""FLIP with a PIC blend (Brackbill 1986; JAX-MPM Eq. 15): v_p = r (v_p + sum w dv_i) + (1 - r) v_pic."""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from ...core.errors import InvalidParameterError
from ...core.interfaces import AbstractTransfer
from .._common import builtin_implementations


@dataclass(frozen=True)
class Transfer(AbstractTransfer):
    """FLIP: the grid keeps the force apart from the momentum so G2P sees the old grid velocity."""

    name: ClassVar[str] = "flip"
    implementations: ClassVar[dict] = builtin_implementations("flip")
    shapes: ClassVar[frozenset | None] = None            # reads D^-1 as Dinv where it needs D
    split_force: ClassVar[bool] = True
    force_terms: ClassVar[frozenset] = frozenset({"gradient"})
    moments: ClassVar[frozenset] = frozenset({"gradient"})
    flip_ratio: float = 0.99

    def __post_init__(self):
        if not 0.0 <= self.flip_ratio <= 1.0:
            raise InvalidParameterError(
                f"transfer 'flip': flip_ratio = {self.flip_ratio} must lie in [0, 1] (1 = pure FLIP, 0 = PIC)."
            )

    def scalars(self) -> tuple:
        return (float(self.flip_ratio),)
