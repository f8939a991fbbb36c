"""The reduced model's maps between full space and the latent space (Chen et al. 2023, Sec. 3; JAX),
the pieces a reduced step is built from, each a fixed-iteration, batched JAX function (one compiled
program, no per-point Python loop):

* ``initial_state`` (Eq. 19): x_hat(0) = argmin sum_p |g(X_p; x_hat) - x_p(0)|^2 by Gauss-Newton, and
  v_hat(0) = argmin sum_p |dg/dx_hat v_hat - v_p(0)|^2 (linear least squares);
* ``project_velocity`` (Eqs. 21 and 23): v_hat = argmin sum_{p in M} |dg/dx_hat(X_p; x_hat) v_hat - v_p|^2;
* ``project_linear`` (Alg. 7): x_hat_{n+1} = x_hat_n + dt v_hat_{n+1};
* ``project_nonlinear`` (Alg. 6, Eq. 22): x_hat_{n+1} = argmin sum_{p in M} |g(X_p; x_hat) - x_p^trial|^2
  by Gauss-Newton with Armijo backtracking from 2 x_hat_n - x_hat_{n-1} (the paper: "typically 2-3
  iterations"; the constants, alpha = 0.25, beta = 0.5, at most 5 iterations and 40 halvings, follow
  the same author's released CROM solver, notes/nclaw-rom.md 2.3);
* ``inverse_map`` (Alg. 4): the reference position X_q with g(X_q; x_hat) = x_q of each Eulerian
  quadrature point, by Newton's method with backtracking on |g - x_q| (F = dg/dX is the Newton
  matrix); a point that does not converge, or whose X_q lies outside the reference body, is flagged
  (the paper does not say how such points are found: the reduced step gives them zero mass).

Least squares are solved by ``jnp.linalg.lstsq`` on the stacked [|M| d, d_hat] Jacobian (an SVD:
rank-deficient sample sets give the minimum-norm solution instead of failing).
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from . import networks as N

#: Armijo sufficient-decrease factor and backtracking ratio (CROM's released solver; notes 2.3)
ARMIJO, BACKTRACK = 0.25, 0.5
GN_ITERATIONS, MAX_HALVINGS = 5, 40


def _lstsq(J, r):
    """argmin_y |J y - r|^2 for J [m, k], r [m] (minimum norm when rank-deficient)."""
    return jnp.linalg.lstsq(J, r)[0]


def project_velocity(params, norm, X, z, v):
    """Eqs. 21/23: v_hat fitting the full-space velocities ``v`` [M, d] of the sample points ``X`` [M, d]
    at latent ``z`` [d_hat] in least squares."""
    _, _, dxdz = N.g_jacobians(params, norm, X, z[None, :])          # [M, d, d_hat]
    return _lstsq(dxdz.reshape(-1, dxdz.shape[-1]), v.reshape(-1))


def project_linear(z, vhat, dt):
    """Alg. 7: x_hat_{n+1} = x_hat_n + dt v_hat_{n+1}."""
    return z + dt * vhat


def _misfit(params, norm, X, z, x):
    return 0.5 * jnp.sum((N.g_apply(params, norm, X, z[None, :]) - x) ** 2)


def gauss_newton(params, norm, X, x, z0, iterations: int = GN_ITERATIONS, halvings: int = MAX_HALVINGS):
    """argmin_z 0.5 sum_p |g(X_p; z) - x_p|^2 from ``z0`` by Gauss-Newton with Armijo backtracking (a
    fixed number of iterations; a step that decreases nothing is not taken). Returns ``(z, misfit)``."""
    def gn_step(z, _):
        xg, _, dxdz = N.g_jacobians(params, norm, X, z[None, :])
        r = (xg - x).reshape(-1)
        J = dxdz.reshape(-1, dxdz.shape[-1])
        dz = -_lstsq(J, r)
        f0 = 0.5 * jnp.sum(r * r)
        slope = jnp.dot(J.T @ r, dz)                                   # directional derivative (< 0)

        def cond(c):
            t, k = c
            return (k < halvings) & (_misfit(params, norm, X, z + t * dz, x) > f0 + ARMIJO * t * slope)

        t, k = jax.lax.while_loop(cond, lambda c: (c[0] * BACKTRACK, c[1] + 1), (jnp.ones((), z.dtype), 0))
        ok = _misfit(params, norm, X, z + t * dz, x) < f0
        return jnp.where(ok, z + t * dz, z), None

    z, _ = jax.lax.scan(gn_step, z0, None, length=iterations)
    return z, _misfit(params, norm, X, z, x)


def project_nonlinear(params, norm, X, x_trial, z_n, z_prev, iterations: int = GN_ITERATIONS):
    """Alg. 6, Eq. 22: the latent whose map fits the trial positions ``x_trial`` of the sample points
    ``X`` best, from the extrapolation 2 z_n - z_prev."""
    return gauss_newton(params, norm, X, x_trial, 2.0 * z_n - z_prev, iterations)[0]


class InitialState(NamedTuple):
    z: jnp.ndarray
    zdot: jnp.ndarray
    misfit: jnp.ndarray


def initial_state(params, norm, X, x0, v0, z_guess, iterations: int = 20):
    """Eq. 19: (x_hat(0), v_hat(0)) fitting the material points' initial positions ``x0`` and
    velocities ``v0`` (each [N, d]) in least squares, from ``z_guess``; ``misfit`` = 0.5 sum |g - x0|^2."""
    z, f = gauss_newton(params, norm, X, x0, z_guess, iterations)
    return InitialState(z, project_velocity(params, norm, X, z, v0), f)


class InverseMap(NamedTuple):
    X: jnp.ndarray          # [Q, d] reference positions
    residual: jnp.ndarray   # [Q] |g(X_q; z) - x_q|
    converged: jnp.ndarray  # [Q] bool: residual <= tol


def inverse_map(params, norm, x, z, X_guess, iterations: int = 20, tol: float = 1e-10, halvings: int = 20,
                bounds=None):
    """Alg. 4's inverse map: X_q with g(X_q; z) = x_q for each point of ``x`` [Q, d], by Newton's method
    (the matrix F = dg/dX) with backtracking on |g - x_q| from ``X_guess`` [Q, d] (e.g. x_q minus the
    mean displacement), per point, at most ``iterations`` Newton steps of at most ``halvings`` halvings
    each. ``tol``: the residual [m] below which a point counts as converged (the caller also checks X_q
    against the reference body). ``bounds`` (lo, hi) [d]: a point whose iterate leaves this box stops
    (it is outside the body: it gets no mass, so its exact X_q does not matter).

    Batched over the points, not vmapped per point: each Newton step is one g_F call on every
    point and each halving one g_apply, and the loops end as soon as every point is done, converged
    or out of bounds (a vmapped per-point loop runs every point as long as its slowest one: off-body
    points, which backtrack longest, set the pace)."""
    z1 = z[None, :]
    tol2 = tol * tol

    def res2(X):
        r = N.g_apply(params, norm, X, z1) - x
        return jnp.sum(r * r, axis=-1)

    def out_of_bounds(X):
        if bounds is None:
            return jnp.zeros(X.shape[0], bool)
        lo, hi = bounds
        return jnp.any((X < lo) | (X > hi), axis=-1)

    def newton(c):
        X, n0, done, k = c
        xg, F = N.g_F(params, norm, X, z1)
        dX = -jnp.linalg.solve(F, (xg - x)[..., None])[..., 0]
        dX = jnp.where(done[:, None], 0.0, dX)

        def more(b):
            t, rt, h = b
            return (h < halvings) & jnp.any(~done & (rt > (1.0 - ARMIJO * t) ** 2 * n0))

        def halve(b):
            t, rt, h = b
            bad = ~done & (rt > (1.0 - ARMIJO * t) ** 2 * n0)
            t = jnp.where(bad, t * BACKTRACK, t)
            return t, jnp.where(bad, res2(X + t[:, None] * dX), rt), h + 1

        t0 = jnp.ones_like(n0)
        t, rt, _ = jax.lax.while_loop(more, halve, (t0, res2(X + dX), 0))
        Xn = X + t[:, None] * dX
        better = ~done & jnp.all(jnp.isfinite(Xn), axis=-1) & (rt < n0)
        X = jnp.where(better[:, None], Xn, X)
        n = jnp.where(better, rt, n0)
        return X, n, done | (n <= tol2) | out_of_bounds(X), k + 1

    n0 = res2(X_guess)
    init = (X_guess, n0, (n0 <= tol2) | out_of_bounds(X_guess), 0)
    X, n, _, _ = jax.lax.while_loop(lambda c: (c[3] < iterations) & jnp.any(~c[2]), newton, init)
    r = jnp.sqrt(n)
    return InverseMap(X, r, r <= tol)
