"""JAX pieces shared by the built-in schemes (particle-batched arrays; ``AbstractTransfer`` documents
``p`` and ``g``)."""
from __future__ import annotations


def momentum(p):
    """q_p = m_p v_p."""
    return p.m[:, None] * p.v


def gradient_force(p):
    """The coefficient of grad w in f_i = -sum_p V_p tau_p grad w_ip (JAX-MPM Eq. 12)."""
    return -p.V[:, None, None] * p.tau


def apic_C(g):
    """C = B D^-1 with D = dx^2/4 I for quadratic B-splines (Jiang et al. 2015; JAX-MPM Eq. B.1):
    4/dx (sum_i w v_i o^T - v_pic fx^T), o the node offset and fx the particle position in cells."""
    return (4.0 * g.inv_dx) * (g.first - g.v_pic[:, :, None] * g.fx[:, None, :])
