"""Small per-particle linear algebra for the JAX laws (vmapped by the stepper)."""
from __future__ import annotations

from functools import partial

import jax
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
    """R of F = R S, with finite derivatives at repeated singular values (F = I included)."""
    return spectral(_ones, False, F, jnp.zeros((), F.dtype))


@jax.custom_jvp
def singular_values(F):
    """The s of ``svd_rotations`` (the last one carries det(F)'s sign) with the derivative
    ds_i = (U^T dF V)_ii, finite at repeated singular values (where the SVD's own JVP divides by
    s_i^2 - s_j^2); the same derivative as Warp's ``singular_values``."""
    return svd_rotations(F)[1]


@singular_values.defjvp
def _singular_values_jvp(primals, tangents):
    (F,), (dF,) = primals, tangents
    U, s, V = svd_rotations(F)
    return s, jnp.einsum("ji,jk,ki->i", U, dF, V)


def _ones(s, p):
    return jnp.ones_like(s) + 0.0 * p


def lame(E, nu):
    return E / (2.0 * (1.0 + nu)), E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))


def hencky_strain(F):
    U, s, V = svd_rotations(F)
    return U, jnp.log(jnp.maximum(s, HENCKY_MIN_STRETCH)), V


# Spectral functions of F with a custom JVP (moved here from the Hencky law so every law shares it):
# the JVP of jnp.linalg.svd divides by s_i^2 - s_j^2 and is NaN at repeated singular values -- at
# F = I, the rest state of every particle -- while the spectral map's derivative is well defined there.
@partial(jax.custom_jvp, nondiff_argnums=(0, 1))
def spectral(g, left, F, p):
    """U diag(g(s, p)) U^T if ``left`` else U diag(g(s, p)) V^T, for F = U diag(s) V^T (``svd_rotations``).

    ``g(s, p) -> [d]`` must be permutation-equivariant in s (isotropic), ``p`` holds its parameters
    (differentiable). Derivatives are finite at repeated singular values.
    """
    U, s, V = svd_rotations(F)
    return (U * g(s, p)[None, :]) @ (U if left else V).T


@spectral.defjvp
def _spectral_jvp(g, left, primals, tangents):
    F, p = primals
    dF, dp = tangents
    U, s, V = svd_rotations(F)
    W = U if left else V
    gs, dg_p = jax.jvp(lambda q: g(s, q), (p,), (dp,))
    Jg = jax.jacfwd(g)(s, p)                              # [d, d], d g_i / d s_j
    dFp = U.T @ dF @ V                                    # dF in the singular bases
    sym, skw = 0.5 * (dFp + dFp.T), 0.5 * (dFp - dFp.T)
    si, sj = s[:, None], s[None, :]
    gi, gj = gs[:, None], gs[None, :]
    diff = si - sj
    # closer than eps^(1/3) (relative): the symmetrised limit below (error O(diff^2)) beats the quotient
    # (round-off error eps / diff); 6e-6 in fp64, 5e-3 in fp32
    close = jnp.abs(diff) <= jnp.finfo(F.dtype).eps ** (1.0 / 3.0) * jnp.maximum(jnp.abs(si), jnp.abs(sj))
    Jd = jnp.diag(Jg)
    limit = 0.5 * (Jd[:, None] - Jg + Jd[None, :] - Jg.T)  # lim (g_i - g_j)/(s_i - s_j) for isotropic g
    dd = jnp.where(close, limit, (gi - gj) / jnp.where(close, 1.0, diff))
    ssum = si + sj
    ok = jnp.abs(ssum) > 0.0
    num = (gj - gi) if left else (gi + gj)
    rot = jnp.where(ok, num / jnp.where(ok, ssum, 1.0), 0.0)
    eye = jnp.eye(s.shape[0], dtype=F.dtype)
    dGp = (1.0 - eye) * (sym * dd + skw * rot) + jnp.diag(Jg @ jnp.diag(dFp) + dg_p)
    return (U * gs[None, :]) @ W.T, U @ dGp @ W.T


def safe_norm(x):
    """|x| with a zero (not NaN) gradient at x = 0."""
    sq = jnp.sum(x * x)
    pos = sq > 0.0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, sq, 1.0)), 0.0)
