"""MLS-MPM on JAX (Hu et al. 2018: f_i = -sum V M^-1 tau (x_i - x_p) w, M^-1 = 4/dx^2)."""
from __future__ import annotations

from types import SimpleNamespace

from ...core.interfaces import G2PResult, P2GTerms
from .._common.jax import apic_C, momentum


def p2g(p):
    S = -(4.0 * p.inv_dx * p.inv_dx * p.dt) * p.V[:, None, None] * p.tau      # Hu et al. 2018
    return P2GTerms(q=momentum(p), A=p.m[:, None, None] * p.C + S)


def g2p(g):
    C = apic_C(g)
    return G2PResult(v=g.v_pic, C=C, grad_v=C)


FUNCS = SimpleNamespace(p2g=p2g, g2p=g2p)


def make(transfer, dim):
    return FUNCS
