"""CPDI on JAX: the corner pseudo-particles' linear-hat weights and the domain's inertia and update, the
formulas of ``reference.py`` with ``xp = jnp`` (the stepper's corner P2G / G2P: ``backends/jax/stepper.py``)."""
from __future__ import annotations

from functools import lru_cache
from types import SimpleNamespace

import jax.numpy as jnp
import numpy as np

from ...backends.jax.linalg import inv_small
from . import reference


def weights(fx, lp=None):
    """(w, dw) [M, 2, D] of the linear hat for corner positions fx = x_c/dx - floor(x_c/dx) [M, D]."""
    return reference.weights_1d(fx, None, xp=jnp, axis=1)


def inertia(x, R, dx, origin):
    """D_p [N, D, D] of particles x [N, D] with domains R [N, D, D] (``reference.inertia``)."""
    return reference.inertia(x, R, dx, origin, xp=jnp)


def update_domain(R, L, dt):
    """The Cayley update R <- (I - dt/2 L)^-1 (I + dt/2 L) R (``reference.update_domain``), the inverse in
    closed form (``inv_small``: no LAPACK call per particle)."""
    eye = jnp.eye(R.shape[-1], dtype=R.dtype)[None]
    return inv_small(eye - 0.5 * dt * L) @ ((eye + 0.5 * dt * L) @ R)


@lru_cache(maxsize=None)
def _make(dim):
    return SimpleNamespace(weights=weights, inertia=inertia, update_domain=update_domain, inv=inv_small,
                           signs=np.asarray(reference.signs(dim)))


def make(shape, dim):
    return _make(int(dim))
