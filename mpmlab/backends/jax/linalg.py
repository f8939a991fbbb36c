"""Small per-particle linear algebra for the JAX laws (vmapped by the stepper)."""
from __future__ import annotations

import jax.numpy as jnp

HENCKY_MIN_STRETCH = 1e-4  # same guard as mpmlab.laws._linalg_np


def svd_rotations(F):
    """F = U diag(s) V^T with U, V proper rotations; the last singular value carries det(F)'s sign."""
    U, s, Vt = jnp.linalg.svd(F)
    V = Vt.T
    du = jnp.sign(jnp.linalg.det(U))
    dv = jnp.sign(jnp.linalg.det(V))
    flip_u = jnp.ones_like(s).at[-1].set(du)
    flip_v = jnp.ones_like(s).at[-1].set(dv)
    return U * flip_u[None, :], s * flip_u * flip_v, V * flip_v[None, :]


def polar_rotation(F):
    U, _, V = svd_rotations(F)
    return U @ V.T


def lame(E, nu):
    return E / (2.0 * (1.0 + nu)), E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))


def hencky_strain(F):
    U, s, V = svd_rotations(F)
    return U, jnp.log(jnp.maximum(s, HENCKY_MIN_STRETCH)), V
