"""APIC on JAX (Jiang et al. 2015; JAX-MPM Eqs. 12, 18, B.1)."""
from __future__ import annotations

from types import SimpleNamespace

from ...core.interfaces import G2PResult, P2GTerms
from .._common.jax import apic_C, gradient_force, momentum


def p2g(p):
    return P2GTerms(q=momentum(p), A=p.m[:, None, None] * p.C, G=p.dt * gradient_force(p))


def g2p(g):
    return G2PResult(v=g.v_pic, C=apic_C(g), grad_v=g.grad)


FUNCS = SimpleNamespace(p2g=p2g, g2p=g2p)


def make(transfer, dim):
    return FUNCS
