"""JAX NCLaw (Ma et al. 2023, App. C Alg. 4): per particle, vmapped by the stepper; the weights arrive
un-batched (one copy per material group)."""
from __future__ import annotations

import math
from types import SimpleNamespace

import jax
import jax.numpy as jnp
from jax.scipy.special import erf

from ...backends.jax.linalg import polar_rotation, singular_values

_SQRT1_2 = 1.0 / math.sqrt(2.0)


def gelu(x):
    """Exact (erf) GELU (jax.nn.gelu's default is the tanh approximation)."""
    return 0.5 * x * (1.0 + erf(x * _SQRT1_2))


def make(law, dim: int) -> SimpleNamespace:
    biases = bool(law.no_undeformed)
    no_rot = bool(law.no_rotation)
    shift = 0.0 if law.no_undeformed else 1.0
    alpha = float(law.alpha)

    def mlp(z, w, net):
        b = (lambda k: w[f"{net}_{k}"]) if biases else (lambda k: 0.0)
        h = gelu(w[f"{net}_W1"] @ z + b("b1"))
        h = gelu(w[f"{net}_W2"] @ h + b("b2"))
        return w[f"{net}_W3"] @ h + b("b3")

    def response(F, w, net):
        """Y = R T, T = sym(T1), T1 = NN(sigma - 1, vec(F^T F - I), det F - 1) (Alg. 4 lines 1-5)."""
        eye = jnp.eye(dim, dtype=F.dtype)
        if no_rot:
            return mlp((F - shift * eye).reshape(-1), w, net).reshape(dim, dim)
        s = singular_values(F)
        C = F.T @ F
        # F^T F = I exactly means sigma = 1 exactly (an SVD may miss it by round-off): the exact value,
        # with the derivative d s kept (as on Warp), so tau(I) = 0 bit for bit on every backend
        s = jnp.where(jnp.all(C == eye), 1.0 + (s - jax.lax.stop_gradient(s)), s)
        z = jnp.concatenate([s - shift, (C - shift * eye).reshape(-1), (jnp.linalg.det(F) - shift)[None]])
        T1 = mlp(z, w, net).reshape(dim, dim)
        return polar_rotation(F) @ (0.5 * (T1 + T1.T))

    def kirchhoff(state, prm, w):
        F = state["F"]
        return response(F, w, "e") @ F.T                      # tau = P F^T, P = R T (Alg. 4 line 6)

    def update(state, grad_v, dt, prm, w):
        F = state["F"]
        Ft = (jnp.eye(dim, dtype=F.dtype) + dt * grad_v) @ F
        return {"F": Ft + alpha * response(Ft, w, "p")}      # Alg. 4 line 9; App. C.3 Eq. 34

    return SimpleNamespace(kirchhoff=kirchhoff, update=update)
