"""Built-in transfer schemes, one folder per scheme (like ``mpmlab/laws/``).

Each folder holds the backend-neutral declaration (``__init__.py``: what the scheme stores, which P2G
terms and G2P moments it uses; ``AbstractTransfer`` documents the decomposition) and the scheme's math
on each backend (``jax.py``: functions the JAX step composes; ``warp.py``: ``@wp.func``s the Warp
kernel factories close over). The kernels never branch on a scheme's name. Shared pieces (the
gradient force, APIC's C) are in ``_common/``.

A new scheme: a folder of your package like these, registered under ``mpmlab.transfers`` entry
points (``examples/mpmlab-example-plugin/mpmlab_example_plugin/rpic/``).
"""
from __future__ import annotations

from ..core.errors import InvalidParameterError
from ..core.interfaces import AbstractTransfer
from .apic import Transfer as TransferAPIC
from .flip import Transfer as TransferFLIP
from .mls import Transfer as TransferMLS
from .pic import Transfer as TransferPIC
from .tpic import Transfer as TransferTPIC

BUILTIN = {"pic": TransferPIC, "flip": TransferFLIP, "apic": TransferAPIC, "mls": TransferMLS, "tpic": TransferTPIC}

__all__ = ["AbstractTransfer", "BUILTIN", "TransferAPIC", "TransferFLIP", "TransferMLS", "TransferPIC",
           "TransferTPIC", "make_transfer"]


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
