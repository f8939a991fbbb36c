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
    # B D^-1: g.Dinv is a float c (D^-1 = c I: B-spline shapes, 4/dx^2 quadratic) or [N, D, D] (uGIMP)
    C = g.Dinv * B if jnp.ndim(g.Dinv) == 0 else jnp.einsum("nij,njk->nik", B, g.Dinv)
    return G2PResult(v=g.v_pic, C=0.5 * (C - jnp.swapaxes(C, 1, 2)), grad_v=g.grad)


def make(transfer, dim):
    return SimpleNamespace(p2g=p2g, g2p=g2p)
