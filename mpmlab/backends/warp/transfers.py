"""A transfer scheme's Warp functions with its declarations, as the kernel factories' cache key.

The P2G and G2P kernel factories (``kernels.py``) close over the scheme's ``@wp.func``s
(``p2g_momentum``, ``p2g_force``, ``g2p``; ``AbstractTransfer`` documents them) and compile only the
terms the scheme declares. One ``WarpTransfer`` per (functions object, declarations): a factory that
returns the same functions for every instance (runtime numbers go through ``scalars()``) compiles once.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from ...core.errors import ConfigError


@dataclass(frozen=True, eq=False)      # hashed by identity: one per functions object (see _SPECS)
class WarpTransfer:
    funcs: Any
    carries_C: bool
    split_force: bool
    momentum_terms: frozenset
    force_terms: frozenset
    moments: frozenset
    name: str


_SPECS: dict = {}


def _arg_names(func):
    """The argument names of a ``@wp.func`` (None when they cannot be read)."""
    import inspect

    types = getattr(func, "input_types", None)
    if isinstance(types, dict) and types:
        return list(types)
    fn = getattr(func, "func", func)
    try:
        return list(inspect.signature(fn).parameters)
    except (TypeError, ValueError):
        return None


def warp_transfer(transfer, dim: int, precision: str) -> WarpTransfer:
    transfer.check()
    where = transfer.describe()
    funcs = transfer.implementation("warp", "transfer")(transfer, dim, precision)
    needed = ["p2g_momentum", "g2p"] + (["p2g_force"] if transfer.split_force else [])
    for attr in needed:
        if getattr(funcs, attr, None) is None:
            raise ConfigError(f"{where}: its Warp factory gives no {attr} @wp.func (AbstractTransfer documents "
                              f"p2g_momentum, p2g_force for split_force schemes, and g2p).")
    for attr in needed:
        names = _arg_names(getattr(funcs, attr))
        if names is not None and "Dinv" not in names:
            raise ConfigError(f"{where}: its Warp {attr} has no Dinv argument (arguments {', '.join(names)}); since "
                              f"shape functions are a choice, add `Dinv: mat` (the particle's D_p^-1) right "
                              f"before `tp` (AbstractTransfer documents the signatures).")
    decl = (bool(transfer.carries_C), bool(transfer.split_force), frozenset(transfer.momentum_terms),
            frozenset(transfer.force_terms) if transfer.split_force else frozenset(), frozenset(transfer.moments))
    key = (id(funcs), decl)
    if key not in _SPECS:   # the entry keeps funcs alive, so its id is not reused
        _SPECS[key] = WarpTransfer(funcs, *decl, name=getattr(transfer, "name", type(transfer).__name__))
    return _SPECS[key]
