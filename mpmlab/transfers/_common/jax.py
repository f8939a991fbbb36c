"""JAX pieces shared by the built-in schemes (particle-batched arrays; ``AbstractTransfer`` documents
``p`` and ``g``)."""
from __future__ import annotations

import jax.numpy as jnp


def momentum(p):
    """q_p = m_p v_p."""
    return p.m[:, None] * p.v


def gradient_force(p):
    """The coefficient of grad w in f_i = -sum_p V_p tau_p grad w_ip (JAX-MPM Eq. 12)."""
    return -p.V[:, None, None] * p.tau


def times_Dinv(M, Dinv):
    """M D^-1 for per-particle matrices M [N, D, D], ``Dinv`` as the step gives it (``p.Dinv``, ``g.Dinv``):
    a Python float c (D^-1 = c I, B-spline shapes) or an [N, D, D] array (uGIMP)."""
    if jnp.ndim(Dinv) == 0:
        return Dinv * M
    return jnp.einsum("nij,njk->nik", M, Dinv)


def apic_C(g):
    """C = B D^-1 (Jiang et al. 2015; JAX-MPM Eq. B.1), B = sum_i w v_i (x_i - x_p)^T
    = dx (sum_i w v_i o^T - v_pic fx^T), o the node offset and fx the particle position in cells (both
    from the window's lowest node). D^-1 = 4/dx^2 I for quadratic B-splines, 3/dx^2 I for cubic ones
    (one scalar factor: ``g.Dinv`` is a float), per particle for uGIMP."""
    B = g.first - g.v_pic[:, :, None] * g.fx[:, None, :]          # B / dx
    if jnp.ndim(g.Dinv) == 0:
        return (g.Dinv * g.dx) * B
    return times_Dinv(g.dx * B, g.Dinv)
