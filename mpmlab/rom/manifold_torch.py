"""Torch counterparts of ``mpmlab.rom.manifold`` (Chen et al. 2023, Sec. 3) for the Warp reduced stepper,
whose networks run in batched torch (``mpmlab.rom.networks_torch``): the same least-squares fits, the
same Gauss-Newton with Armijo backtracking and the same constants (``manifold.ARMIJO``, ``BACKTRACK``,
``GN_ITERATIONS``, ``MAX_HALVINGS``), so that both backends take the same steps.

Eager torch: the iterations are Python loops over batched tensor ops (none per point). Backtracking
takes the same step lengths as the JAX loops, the first halving that passes the Armijo test, but
evaluates every halving of a failed full step in one batched call (eager torch pays per call, not per
point: a sequential loop of up to 40 halvings cost most of a nonlinear projection). Least squares: the SVD-based
``gelsd`` driver on the CPU (the minimum-norm solution of a rank-deficient sample set, as
``jnp.linalg.lstsq``), the pseudo-inverse elsewhere (CUDA's ``gels`` assumes full rank).
"""
from __future__ import annotations

from typing import NamedTuple

import torch

from . import networks_torch as NT
from .manifold import ARMIJO, BACKTRACK, GN_ITERATIONS, MAX_HALVINGS


def _lstsq(J, r):
    """argmin_y |J y - r|^2 for J [m, k], r [m] (minimum norm when rank-deficient)."""
    if J.device.type == "cpu":
        return torch.linalg.lstsq(J, r[:, None], driver="gelsd").solution[:, 0]
    return torch.linalg.pinv(J) @ r


def project_velocity(params, norm, X, z, v):
    """Eqs. 21/23: v_hat fitting the velocities ``v`` [M, d] of the sample points ``X`` [M, d] at ``z``."""
    _, _, dxdz = NT.g_jacobians(params, norm, X, z[None, :])
    return _lstsq(dxdz.reshape(-1, dxdz.shape[-1]), v.reshape(-1))


def project_linear(z, vhat, dt):
    """Alg. 7: x_hat_{n+1} = x_hat_n + dt v_hat_{n+1}."""
    return z + dt * vhat


def _misfit(params, norm, X, z, x):
    return 0.5 * torch.sum((NT.g_apply(params, norm, X, z[None, :]) - x) ** 2)


def _backtrack(ts, fails):
    """Index of the first step length that passes: ``fails`` [H, ...] for the halvings k = 1 .. H (t =
    BACKTRACK^k) after a failed full step; the first k < H that passes, else H (the sequential loop's
    answer: it stops after H halvings without testing the last one)."""
    passing = ~fails[:-1]
    first = torch.argmax(passing.to(torch.int8), dim=0)
    return torch.where(torch.any(passing, dim=0), first, fails.shape[0] - 1)


def gauss_newton(params, norm, X, x, z0, iterations: int = GN_ITERATIONS, halvings: int = MAX_HALVINGS):
    """``manifold.gauss_newton``: argmin_z 0.5 sum_p |g(X_p; z) - x_p|^2 from ``z0``; ``(z, misfit)``.
    The same Armijo rule; when the full step fails, every halving's misfit is evaluated in one batched
    call (the sequential loop's first passing length, without its up to ``halvings`` round trips)."""
    z = z0
    for _ in range(int(iterations)):
        xg, _, dxdz = NT.g_jacobians(params, norm, X, z[None, :])
        r = (xg - x).reshape(-1)
        J = dxdz.reshape(-1, dxdz.shape[-1])
        dz = -_lstsq(J, r)
        f0 = 0.5 * torch.sum(r * r)
        slope = torch.dot(J.T @ r, dz)
        f = _misfit(params, norm, X, z + dz, x)
        zn = z + dz
        if halvings > 0 and f > f0 + ARMIJO * slope:
            ts = BACKTRACK ** torch.arange(1, int(halvings) + 1, dtype=z.dtype, device=z.device)
            zs = z[None, :] + ts[:, None] * dz[None, :]
            fs = 0.5 * torch.sum((NT.g_apply(params, norm, X, zs[:, None, :]) - x) ** 2, dim=(1, 2))
            k = _backtrack(ts, fs > f0 + ARMIJO * ts * slope)
            zn, f = zs[k], fs[k]
        if f < f0:
            z = zn
    return z, _misfit(params, norm, X, z, x)


def project_nonlinear(params, norm, X, x_trial, z_n, z_prev, iterations: int = GN_ITERATIONS):
    """Alg. 6, Eq. 22, from the extrapolation 2 z_n - z_prev."""
    return gauss_newton(params, norm, X, x_trial, 2.0 * z_n - z_prev, iterations)[0]


class InitialState(NamedTuple):
    z: torch.Tensor
    zdot: torch.Tensor
    misfit: torch.Tensor


def initial_state(params, norm, X, x0, v0, z_guess, iterations: int = 20):
    """Eq. 19 (``manifold.initial_state``)."""
    z, f = gauss_newton(params, norm, X, x0, z_guess, iterations)
    return InitialState(z, project_velocity(params, norm, X, z, v0), f)


class InverseMap(NamedTuple):
    X: torch.Tensor          # [Q, d] reference positions
    residual: torch.Tensor   # [Q] |g(X_q; z) - x_q|
    converged: torch.Tensor  # [Q] bool: residual <= tol


def inverse_map(params, norm, x, z, X_guess, iterations: int = 20, tol: float = 1e-10, halvings: int = 20,
                bounds=None):
    """``manifold.inverse_map``: X_q with g(X_q; z) = x_q by Newton's method with backtracking on
    |g - x_q|, batched over the points, each loop ending as soon as every point is done."""
    z1 = z[None, :]
    tol2 = tol * tol

    def res2(X):
        r = NT.g_apply(params, norm, X, z1) - x
        return torch.sum(r * r, dim=-1)

    def out_of_bounds(X):
        if bounds is None:
            return torch.zeros(X.shape[0], dtype=torch.bool, device=X.device)
        lo, hi = bounds
        return torch.any((X < lo) | (X > hi), dim=-1)

    X, n = X_guess, res2(X_guess)
    done = (n <= tol2) | out_of_bounds(X)
    for _ in range(int(iterations)):
        if bool(torch.all(done)):
            break
        xg, F = NT.g_F(params, norm, X, z1)
        dX = -torch.linalg.solve_ex(F, (xg - x)[..., None])[0][..., 0]   # singular F: non-finite, not taken
        dX = torch.where(done[:, None], 0.0, dX)
        t = torch.ones_like(n)
        rt = res2(X + dX)
        bad = ~done & (rt > (1.0 - ARMIJO) ** 2 * n)
        if halvings > 0 and bool(torch.any(bad)):
            # every halving of the points whose full step failed, in one batched call (module doc)
            ts = BACKTRACK ** torch.arange(1, int(halvings) + 1, dtype=X.dtype, device=X.device)
            Xb = X[bad][None] + ts[:, None, None] * dX[bad][None]                   # [H, b, d]
            rb = NT.g_apply(params, norm, Xb, z[None, None, :]) - x[bad][None]
            r2 = torch.sum(rb * rb, dim=-1)                                          # [H, b]
            k = _backtrack(ts, r2 > (1.0 - ARMIJO * ts[:, None]) ** 2 * n[bad][None])
            cols = torch.arange(k.shape[0], device=X.device)
            t = t.clone()
            t[bad] = ts[k]
            rt = rt.clone()
            rt[bad] = r2[k, cols]
        Xn = X + t[:, None] * dX
        better = ~done & torch.all(torch.isfinite(Xn), dim=-1) & (rt < n)
        X = torch.where(better[:, None], Xn, X)
        n = torch.where(better, rt, n)
        done = done | (n <= tol2) | out_of_bounds(X)
    r = torch.sqrt(n)
    return InverseMap(X, r, r <= tol)
