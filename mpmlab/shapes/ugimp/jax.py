"""uGIMP weights on JAX: ``reference.weights_1d`` with ``xp = jnp`` (AbstractShape documents ``weights``)."""
from __future__ import annotations

from functools import lru_cache
from types import SimpleNamespace

import jax.numpy as jnp

from . import reference


def weights(fx, lp):
    """(w, dw) [N, 3, D] for fx = x/dx - base [N, D] and the particles' half widths lp [N] in cells
    (dw = dS/dx_p in cell units)."""
    return reference.weights_1d(fx, jnp.asarray(lp, fx.dtype)[:, None], xp=jnp, axis=1)    # [N, 3, D]


@lru_cache(maxsize=None)
def _make(dim):
    return SimpleNamespace(weights=weights)


def make(shape, dim):
    return _make(int(dim))
