"""JAX ``phase_change``: both laws on every particle, the active one selected (``jnp.where``; under
the stepper's ``vmap`` a ``lax.cond`` would evaluate both as well)."""
from __future__ import annotations

from types import SimpleNamespace

import jax.numpy as jnp


def make(law, dim: int) -> SimpleNamespace:
    sides = [(s, sub, sub.implementation("jax", "law")(sub, dim)) for s, sub in law.sides()]

    def split(side, sub, state, prm, w):
        return ({f.name: state[f.name] for f in sub.state}, law.side_params(side, prm),
                law.side_weights(side, w, dim))

    def kirchhoff(state, prm, w):
        (sa, a, fa), (sb, b, fb) = sides
        after = state["clock"] >= prm["switch_time"]
        return jnp.where(after, fb.kirchhoff(*split(sb, b, state, prm, w)), fa.kirchhoff(*split(sa, a, state, prm, w)))

    def update(state, grad_v, dt, prm, w):
        after = state["clock"] >= prm["switch_time"]
        new = dict(state)
        for side, sub, fns in sides:
            s, p, ws = split(side, sub, state, prm, w)
            out = fns.update(s, grad_v, dt, p, ws)
            on = after if side == "after" else jnp.logical_not(after)
            for k, val in out.items():
                new[k] = jnp.where(on, val, new[k])
        new["clock"] = state["clock"] + dt
        return new

    return SimpleNamespace(kirchhoff=kirchhoff, update=update)
