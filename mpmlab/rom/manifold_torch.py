"""Torch counterparts of ``mpmlab.rom.manifold`` (Chen et al. 2023, Sec. 3) for the Warp reduced stepper,
whose networks run in batched torch (``mpmlab.rom.networks_torch``): the same least-squares fits, the
same Gauss-Newton with Armijo backtracking and the same constants (``manifold.ARMIJO``, ``BACKTRACK``,
``GN_ITERATIONS``, ``MAX_HALVINGS``), so that both backends take the same steps.

Eager torch: the backtracking loops are plain Python loops over batched tensor ops (a reduced step has
at most ``GN_ITERATIONS`` x ``MAX_HALVINGS`` of them, none per point). Least squares: the SVD-based
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


def gauss_newton(params, norm, X, x, z0, iterations: int = GN_ITERATIONS, halvings: int = MAX_HALVINGS):
    """``manifold.gauss_newton``: argmin_z 0.5 sum_p |g(X_p; z) - x_p|^2 from ``z0``; ``(z, misfit)``."""
    z = z0
    for _ in range(int(iterations)):
        xg, _, dxdz = NT.g_jacobians(params, norm, X, z[None, :])
        r = (xg - x).reshape(-1)
        J = dxdz.reshape(-1, dxdz.shape[-1])
        dz = -_lstsq(J, r)
        f0 = 0.5 * torch.sum(r * r)
        slope = torch.dot(J.T @ r, dz)
        t, k = 1.0, 0
        while k < halvings and _misfit(params, norm, X, z + t * dz, x) > f0 + ARMIJO * t * slope:
            t, k = t * BACKTRACK, k + 1
        if _misfit(params, norm, X, z + t * dz, x) < f0:
            z = z + t * dz
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
