"""TPIC on JAX (JAX-MPM Eq. B.2): APIC's P2G; C is the gathered velocity gradient (Eq. 18)."""
from __future__ import annotations

from types import SimpleNamespace

from ...core.interfaces import G2PResult
from ..apic.jax import p2g


def g2p(g):
    return G2PResult(v=g.v_pic, C=g.grad, grad_v=g.grad)


FUNCS = SimpleNamespace(p2g=p2g, g2p=g2p)


def make(transfer, dim):
    return FUNCS
