"""Built-in transfer schemes (backend-neutral descriptions; kernels live in the backends).

Each scheme is a final class fixing the four choices of ``AbstractTransfer``. Both backends
implement all five through the same build-time specialisation (``mpmlab.backends.*.transfer``).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from ..core.errors import InvalidParameterError
from ..core.interfaces import AbstractTransfer

_IMPL = {"jax": "mpmlab.backends.jax.stepper:JaxStepper", "warp": "mpmlab.backends.warp.stepper:WarpStepper"}


@dataclass(frozen=True)
class TransferPIC(AbstractTransfer):
    """Particle-in-cell (Harlow 1964; JAX-MPM Eq. 16): v_p = sum w v_i. No C stored."""

    name: ClassVar[str] = "pic"
    implementations: ClassVar[dict] = _IMPL


@dataclass(frozen=True)
class TransferFLIP(AbstractTransfer):
    """FLIP with PIC blend (Brackbill 1986; JAX-MPM Eq. 15): v_p = r (v_p + sum w dv_i) + (1-r) v_pic."""

    name: ClassVar[str] = "flip"
    implementations: ClassVar[dict] = _IMPL
    flip_ratio: float = 0.99

    def __post_init__(self):
        if not 0.0 <= self.flip_ratio <= 1.0:
            raise InvalidParameterError(
                f"transfer 'flip': flip_ratio = {self.flip_ratio} must lie in [0, 1] (1 = pure FLIP, 0 = PIC)."
            )


@dataclass(frozen=True)
class TransferAPIC(AbstractTransfer):
    """Affine PIC (Jiang et al. 2015; JAX-MPM Eq. B.1): carries C = B D^-1; F updated with sum v_i grad w."""

    name: ClassVar[str] = "apic"
    implementations: ClassVar[dict] = _IMPL
    affine: ClassVar[str] = "apic"


@dataclass(frozen=True)
class TransferMLS(AbstractTransfer):
    """MLS-MPM (Hu et al. 2018), the scheme NCLaw uses: APIC affine C, MLS force, C as velocity gradient."""

    name: ClassVar[str] = "mls"
    implementations: ClassVar[dict] = _IMPL
    affine: ClassVar[str] = "apic"
    force: ClassVar[str] = "mls"
    grad_v: ClassVar[str] = "affine"


@dataclass(frozen=True)
class TransferTPIC(AbstractTransfer):
    """Taylor PIC (JAX-MPM App. B, Eq. B.2): carries the particle velocity gradient as the affine term."""

    name: ClassVar[str] = "tpic"
    implementations: ClassVar[dict] = _IMPL
    affine: ClassVar[str] = "velocity_gradient"


def make_transfer(name: str, **options) -> AbstractTransfer:
    """Build a registered transfer scheme by name with its options (e.g. ``flip_ratio``)."""
    from ..core import registry

    cls = registry.transfers.get(name)
    try:
        return cls(**options)
    except TypeError:
        raise InvalidParameterError(
            f"transfer '{name}' does not take options {sorted(options)}; "
            f"it takes {sorted(getattr(cls, '__dataclass_fields__', {}))}."
        ) from None
