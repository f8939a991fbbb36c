"""JAX weakly compressible Newtonian fluid (JAX-MPM Eqs. 19-20); per particle, vmapped by the stepper."""
from __future__ import annotations

from types import SimpleNamespace

import jax.numpy as jnp


def make(law, dim: int) -> SimpleNamespace:
    eye = jnp.eye(dim)

    def kirchhoff(state, prm, w):
        return state["J"] * state["sigma"]

    def update(state, grad_v, dt, prm, w):
        c, mu, rho0, pmin = prm["sound_speed"], prm["viscosity"], prm["rest_density"], prm["min_pressure"]
        J = state["J"] * jnp.linalg.det(eye + dt * grad_v)
        p = c * c * (rho0 / J - rho0)                          # Eq. 20, rho = rho0 / J
        # tension cut-off p = max(p, pmin); where(>=) keeps the unclamped gradient at p == pmin (rest)
        p = jnp.where(p >= pmin, p, pmin)
        D = 0.5 * (grad_v + grad_v.T)                          # strain rate (Eq. 19 uses D dt: see Law)
        sigma = -p * eye + 2.0 * mu * (D - jnp.trace(D) / 3.0 * eye)   # 1/3 also in 2D (paper's deviator)
        return {"J": J, "sigma": sigma}

    return SimpleNamespace(kirchhoff=kirchhoff, update=update)
