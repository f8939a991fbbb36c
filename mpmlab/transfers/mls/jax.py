"""MLS-MPM on JAX (Hu et al. 2018: f_i = -sum V tau M^-1 (x_i - x_p) w, M^-1 = D^-1: ``p.Dinv``, 4/dx^2 I
for quadratic B-splines)."""
from __future__ import annotations

from types import SimpleNamespace

import jax.numpy as jnp

from ...core.interfaces import G2PResult, P2GTerms
from .._common.jax import apic_C, momentum, times_Dinv


def p2g(p):
    if jnp.ndim(p.Dinv) == 0:        # M^-1 = Dinv I (B-splines): one scalar factor (Hu et al. 2018)
        S = -(p.Dinv * p.dt) * p.V[:, None, None] * p.tau
    else:                            # per particle (uGIMP)
        S = times_Dinv(-p.dt * p.V[:, None, None] * p.tau, p.Dinv)
    return P2GTerms(q=momentum(p), A=p.m[:, None, None] * p.C + S)


def g2p(g):
    C = apic_C(g)
    return G2PResult(v=g.v_pic, C=C, grad_v=C)


FUNCS = SimpleNamespace(p2g=p2g, g2p=g2p)


def make(transfer, dim):
    return FUNCS
