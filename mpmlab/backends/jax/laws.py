"""A law instance's JAX functions in the stepper's calling convention, checked against its declarations.

Law code reads parameters by name (``prm["E"]``); the stepper stores them per particle as one row
``[P]`` in the declared order, so the names are attached here, inside the vmapped function -- the
traced program is the one a positional read would give. Shared weights are passed un-batched.
"""
from __future__ import annotations

from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np

from ...core.errors import ConfigError


def law_functions(law, dim: int, dtype=jnp.float64, check: bool = True) -> SimpleNamespace:
    """``kirchhoff(state, row, weights)`` and ``update(state, grad_v, dt, row, weights)`` for one
    particle (``row``: its parameters in declared order), to be vmapped with ``in_axes`` 0 for
    state/row/grad_v and None for dt/weights. ``check``: trace both once on one particle and refuse a
    law whose results do not match its declared state (one line naming the law)."""
    impl = law.implementation("jax", "law")(law, dim)
    names = law.param_names()

    def named(row):
        return {n: row[i] for i, n in enumerate(names)}

    def kirchhoff(state, row, weights):
        return impl.kirchhoff(state, named(row), weights)

    def update(state, grad_v, dt, row, weights):
        return impl.update(state, grad_v, dt, named(row), weights)

    out = SimpleNamespace(kirchhoff=kirchhoff, update=update, impl=impl, law=law)
    if check:
        check_law(out, law, dim, dtype)
    return out


def check_law(fns, law, dim: int, dtype) -> None:
    """Shape-only trace (``jax.eval_shape``: nothing is computed) of one particle's kirchhoff and update."""
    spec = {f.name: f.resolved_shape(dim) for f in law.state}
    state = {k: jax.ShapeDtypeStruct(s, dtype) for k, s in spec.items()}
    row = jax.ShapeDtypeStruct((len(law.param_names()),), dtype)
    weights = {k: jax.ShapeDtypeStruct(tuple(s), dtype) for k, s in law.weight_shapes(dim).items()}
    gv = jax.ShapeDtypeStruct((dim, dim), dtype)
    where = f"law '{law.name}' ({type(law).__module__})"
    try:
        tau = jax.eval_shape(fns.kirchhoff, state, row, weights)
        new = jax.eval_shape(lambda s, g, r, w: fns.update(s, g, jnp.asarray(1e-3, dtype), r, w), state, gv, row, weights)
    except Exception as e:  # noqa: BLE001 -- any failure here is the plugin's: say which and why
        raise ConfigError(f"{where}: its JAX functions fail on its declared state {sorted(spec)} and "
                          f"parameters {list(law.param_names())}: {type(e).__name__}: {e}".split("\n")[0]) from None
    if tuple(getattr(tau, "shape", ())) != (dim, dim):
        raise ConfigError(f"{where}: JAX kirchhoff returns shape {getattr(tau, 'shape', None)}; it must be ({dim}, {dim}).")
    if not isinstance(new, dict) or set(new) != set(spec):
        got = sorted(new) if isinstance(new, dict) else type(new).__name__
        raise ConfigError(f"{where}: JAX update returns state {got}; the law declares {sorted(spec)} "
                          f"(declare every field in Law.state, and return exactly those).")
    for k, s in spec.items():
        if tuple(new[k].shape) != s:
            raise ConfigError(f"{where}: JAX update returns '{k}' with shape {tuple(new[k].shape)}; the law declares {s}.")


def weights_of(group, dtype) -> dict:
    return {k: jnp.asarray(np.asarray(a), dtype) for k, a in group.weights.items()}
