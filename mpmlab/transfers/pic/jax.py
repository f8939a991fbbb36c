"""PIC on JAX (JAX-MPM Eqs. 12, 16, 18)."""
from __future__ import annotations

from types import SimpleNamespace

from ...core.interfaces import G2PResult, P2GTerms
from .._common.jax import gradient_force, momentum


def p2g(p):
    return P2GTerms(q=momentum(p), G=p.dt * gradient_force(p))


def g2p(g):
    return G2PResult(v=g.v_pic, C=None, grad_v=g.grad)


FUNCS = SimpleNamespace(p2g=p2g, g2p=g2p)


def make(transfer, dim):
    return FUNCS
