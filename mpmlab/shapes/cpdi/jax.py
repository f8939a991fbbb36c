"""CPDI on JAX: the corner pseudo-particles' linear-hat weights and the domain's inertia and update, the
formulas of ``reference.py`` with ``xp = jnp`` (the stepper's corner P2G / G2P: ``backends/jax/stepper.py``)."""
from __future__ import annotations

from functools import lru_cache
from types import SimpleNamespace

import jax.numpy as jnp
import numpy as np

from . import reference


def weights(fx, lp=None):
    """(w, dw) [M, 2, D] of the linear hat for corner positions fx = x_c/dx - floor(x_c/dx) [M, D]."""
    return reference.weights_1d(fx, None, xp=jnp, axis=1)


def inertia(x, R, dx, origin):
    """D_p [N, D, D] of particles x [N, D] with domains R [N, D, D] (``reference.inertia``)."""
    return reference.inertia(x, R, dx, origin, xp=jnp)


def update_domain(R, L, dt):
    """The Cayley update R <- (I - dt/2 L)^-1 (I + dt/2 L) R (``reference.update_domain``)."""
    return reference.update_domain(R, L, dt, xp=jnp)


@lru_cache(maxsize=None)
def _make(dim):
    return SimpleNamespace(weights=weights, inertia=inertia, update_domain=update_domain,
                           signs=np.asarray(reference.signs(dim)))


def make(shape, dim):
    return _make(int(dim))
