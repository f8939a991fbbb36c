"""CPDI (Sadeghirad, Brannon & Burghardt 2011, "CPDI1"), written once against an array module (NumPy here,
``jnp`` in ``jax.py``; the Warp kernels follow the same formulas).

A particle's domain is the parallelogram (parallelepiped in 3-D) x_p + R xi, xi in [-1, 1]^D: the columns of
``R`` [D, D] are its half domain vectors r_1 .. r_D (physical units). Its 2^D corners are x_c = x_p + R s_c,
s_c in {-1, +1}^D (``signs``). With N_i the grid's multilinear hat functions:

* weight     S_ip      = 2^-D sum_c N_i(x_c)                                 (Sadeghirad et al. 2011, Eq. 23)
* gradient   grad S_ip = 2^-D sum_c N_i(x_c) R^-T s_c                        (Eq. 24 for D = 2, any D)
  -- the average over the domain of the gradient of N_i's multilinear interpolant through the corners:
  in xi, d/dxi_a of sum_c N_c prod_b (1 + s_cb xi_b)/2 averages to 2^-D sum_c N_c s_ca over [-1, 1]^D.
* inertia    D_p = sum_i S_ip (x_i - x_p)(x_i - x_p)^T = 2^-D sum_c dx^2 diag(f_c (1 - f_c)) + R R^T
  (f_c the corner's position in its cell: the hats' own second moment per corner, and the corners' spread
  mean_c (R s_c)(R s_c)^T = R R^T; the cross terms vanish by the hats' linear completeness). Not constant
  and not diagonal, so APIC / MLS read it per particle (``Dinv`` [N, D, D]).
* domain     R <- (I - dt/2 L)^-1 (I + dt/2 L) R, L = sum_i v_i grad S_ip^T, the Cayley (midpoint) form of
  CPDI1's r = F r^0: second order, and an exact rotation when L is skew, so a rigid rotation keeps the
  domain rotated, never stretched (the explicit (I + dt L) R grows it by sqrt(1 + dt^2 w^2) a step).
* start      R^0 = F^0 (V0^(1/D) / 2) I: the particle's cube of its initial volume, deformed by the
  body's initial F (``ParticleSet.volume`` is the reference volume).

Every sum over nodes is a sum over the corners of one linear-hat window (2 nodes per axis from floor(x_c /
dx)), which is how the backends run it: P2G and G2P see 2^D corner pseudo-particles of weight 2^-D each.
The particle's support grows with its domain; only the corners must stay on the grid."""
from __future__ import annotations

import itertools

import numpy as np


def signs(dim: int) -> np.ndarray:
    """s_c [2^D, D] in {-1, +1}, corner c in ``itertools.product`` order (the backends' corner order)."""
    return np.array(list(itertools.product((-1.0, 1.0), repeat=dim)))


def weights_1d(fx, lp=None, xp=np, axis=-1):
    """The linear hat of each corner's window: (w, dw) of shape [..., 2], N(fx - k) = 1 - |fx - k| and dN/dx_p
    (cells) for k = 0, 1; fx = x_c/dx - floor(x_c/dx) in [0, 1)."""
    w = xp.stack([1.0 - fx, fx], axis=axis)
    # -1, +1 written as functions of fx (0 fx): JAX's hand-written P2G / G2P adjoints transpose a linear call
    # whose every operand must carry a tangent; a constant dw would not (its derivative is zero either way)
    zero = 0.0 * fx
    dw = xp.stack([zero - 1.0, zero + 1.0], axis=axis)
    return w, dw


def initial_domain(volume, dim: int, F=None) -> np.ndarray:
    """R^0 [N, D, D]: half the side of each particle's cube of volume V0 on the diagonal, times F^0 if given."""
    h = 0.5 * np.asarray(volume, np.float64) ** (1.0 / dim)
    R = h[:, None, None] * np.eye(dim)[None]
    return R if F is None else np.einsum("nij,njk->nik", np.asarray(F, np.float64), R)


def corners(x, R, xp=np):
    """x_c = x_p + R s_c, [N, 2^D, D] (corner order of ``signs``)."""
    s = xp.asarray(signs(x.shape[-1]), dtype=x.dtype)
    return x[:, None, :] + xp.einsum("nij,cj->nci", R, s)


def node_weights(x, R, dx, origin=0.0):
    """Dense per-node S_ip and grad S_ip of particles x [N, D] with domains R [N, D, D] (fp64, for tests):
    returns ``(nodes [K, D] int, S [N, K], dS [N, K, D])`` over every node some corner reaches."""
    x = np.asarray(x, np.float64)
    R = np.asarray(R, np.float64)
    N, D = x.shape
    s = signs(D)
    xc = (corners(x, R) - origin) / dx                          # [N, 2^D, D] in cells
    base = np.floor(xc).astype(int)
    f = xc - base
    offs = np.array(list(itertools.product((0, 1), repeat=D)))  # the hat window's nodes
    idx = (base[:, :, None, :] + offs[None, None]).reshape(-1, D)
    nodes, inv = np.unique(idx, axis=0, return_inverse=True)
    w = np.prod(np.where(offs[None, None] == 1, f[:, :, None, :], 1.0 - f[:, :, None, :]), axis=-1)  # [N, 2^D, 2^D]
    g = np.einsum("nji,cj->nci", np.linalg.inv(R), s)          # R^-T s_c  [N, 2^D, D]
    S = np.zeros((N, len(nodes)))
    dS = np.zeros((N, len(nodes), D))
    inv = inv.reshape(N, len(s), len(offs))
    for n in range(N):
        np.add.at(S[n], inv[n].ravel(), w[n].ravel() / len(s))
        np.add.at(dS[n], inv[n].ravel(), (w[n][:, :, None] * g[n][:, None, :]).reshape(-1, D) / len(s))
    return nodes, S, dS


def inertia(x, R, dx, origin=0.0, xp=np):
    """D_p [N, D, D] = 2^-D sum_c dx^2 diag(f_c (1 - f_c)) + R R^T."""
    xc = (corners(x, R, xp) - origin) / dx
    f = xc - xp.floor(xc)
    diag = dx * dx * xp.mean(f * (1.0 - f), axis=1)           # [N, D]
    eye = xp.eye(x.shape[-1], dtype=x.dtype)
    return diag[:, :, None] * eye[None] + xp.einsum("nij,nkj->nik", R, R)


def update_domain(R, L, dt, xp=np):
    """R <- (I - dt/2 L)^-1 (I + dt/2 L) R for velocity gradients L [N, D, D]: the Cayley form (module
    docstring)."""
    eye = xp.eye(R.shape[-1], dtype=R.dtype)[None]
    return xp.linalg.solve(eye - 0.5 * dt * L, (eye + 0.5 * dt * L) @ R)
