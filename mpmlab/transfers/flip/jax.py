"""FLIP on JAX (JAX-MPM Eq. 15; force as in Eq. 12)."""
from __future__ import annotations

from types import SimpleNamespace

from ...core.interfaces import G2PResult, P2GTerms
from .._common.jax import gradient_force, momentum


def p2g(p):
    return P2GTerms(q=momentum(p), force_G=gradient_force(p))


def make(transfer, dim):
    r = transfer.flip_ratio       # a constant of the compiled step, as every other scene number on JAX

    def g2p(g):
        dv = g.v_pic - g.v_old
        return G2PResult(v=r * (g.v + dv) + (1.0 - r) * g.v_pic, C=None, grad_v=g.grad)

    return SimpleNamespace(p2g=p2g, g2p=g2p)
