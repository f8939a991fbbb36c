"""RPIC on JAX: APIC's P2G terms, and the skew-symmetric part of APIC's C in G2P."""
from __future__ import annotations

from types import SimpleNamespace

import jax.numpy as jnp

from mpmlab.core.interfaces import G2PResult, P2GTerms


def p2g(p):
    q = p.m[:, None] * p.v
    A = p.m[:, None, None] * p.C                               # C is skew: only a rotation about x_p
    G = p.dt * (-p.V[:, None, None] * p.tau)                   # gradient force (JAX-MPM Eq. 12), an impulse
    return P2GTerms(q=q, A=A, G=G)


def g2p(g):
    B = g.dx * (g.first - g.v_pic[:, :, None] * g.fx[:, None, :])     # sum_i w v_i (x_i - x_p)^T
    if jnp.ndim(g.Dinv) == 0:
        # D = I / c (B-spline shapes: c = 4/dx^2 quadratic): C = skew(B D^-1)
        C = g.Dinv * B
        return G2PResult(v=g.v_pic, C=0.5 * (C - jnp.swapaxes(C, 1, 2)), grad_v=g.grad)
    return G2PResult(v=g.v_pic, C=rigid_C(B, g.Dinv), grad_v=g.grad)


def rigid_C(B, Dinv):
    """C = [omega]_x, the rotation whose angular momentum about x_p, K omega with K = tr(D) I - D the
    particle's inertia tensor (Jiang et al. 2015 Sec. 5.3), is B's: omega = K^-1 axial(B). For an isotropic
    D = d I this is skew(B D^-1); for a D_p that is not (uGIMP: per particle, diagonal, anisotropic)
    skew(B D^-1) would not put B's angular momentum back on the grid."""
    D = jnp.linalg.inv(Dinv)                                           # [N, d, d]
    if B.shape[-1] == 2:
        c = (B[:, 1, 0] - B[:, 0, 1]) / (D[:, 0, 0] + D[:, 1, 1])
        z = jnp.zeros_like(c)
        return jnp.stack([jnp.stack([z, -c], -1), jnp.stack([c, z], -1)], -2)
    a = jnp.stack([B[:, 2, 1] - B[:, 1, 2], B[:, 0, 2] - B[:, 2, 0], B[:, 1, 0] - B[:, 0, 1]], -1)
    K = jnp.trace(D, axis1=1, axis2=2)[:, None, None] * jnp.eye(3, dtype=B.dtype) - D
    w = jnp.linalg.solve(K, a[..., None])[..., 0]
    z = jnp.zeros_like(w[:, 0])
    return jnp.stack([jnp.stack([z, -w[:, 2], w[:, 1]], -1), jnp.stack([w[:, 2], z, -w[:, 0]], -1),
                      jnp.stack([-w[:, 1], w[:, 0], z], -1)], -2)


def make(transfer, dim):
    return SimpleNamespace(p2g=p2g, g2p=g2p)
