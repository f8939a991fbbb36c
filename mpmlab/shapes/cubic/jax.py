"""Cubic B-spline weights on JAX: ``reference.weights_1d`` with ``xp = jnp`` (AbstractShape documents
``weights``)."""
from __future__ import annotations

from functools import lru_cache
from types import SimpleNamespace

import jax.numpy as jnp

from . import reference


def weights(fx, lp=None):
    """(w, dw) [N, 4, D] for fx = x/dx - base [N, D] (dw = dN/dx_p in cell units); lp is not used."""
    return reference.weights_1d(fx, None, xp=jnp, axis=1)          # [N, 4, D]


@lru_cache(maxsize=None)
def _make(dim):
    return SimpleNamespace(weights=weights)


def make(shape, dim):
    return _make(int(dim))
