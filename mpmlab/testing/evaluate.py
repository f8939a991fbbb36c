"""One law's ``kirchhoff`` and ``update`` on a batch of states: on the NumPy reference, JAX or Warp.

``evaluate(law, dim, backend, "kirchhoff", states, prm)`` -> tau [n, D, D];
``evaluate(law, dim, backend, "update", states, prm, grad_v, dt)`` -> list of n state dicts.
``states``: a list of per-particle dicts of the declared fields; ``prm``: parameters by name (a
mapping) or a row in declared order. JAX and Warp are imported only when asked for.
"""
from __future__ import annotations

import inspect
from typing import Mapping

import numpy as np

from ._common import law_class, law_instance, param_row

BACKENDS = ("reference", "jax", "warp")


def _named(law, prm) -> dict:
    if isinstance(prm, Mapping):
        return {k: float(v) for k, v in prm.items()}
    return {n: float(v) for n, v in zip(law_class(law).param_names(), np.asarray(prm, float))}


def _row(law, prm) -> np.ndarray:
    return param_row(law, prm) if isinstance(prm, Mapping) else np.asarray(prm, float)


def _takes(fn, name: str) -> bool:
    try:
        return name in inspect.signature(fn).parameters
    except (TypeError, ValueError):
        return False


def _extra(fn, law, dim) -> dict:
    """Keywords a reference function accepts beyond (state, prm, w): ``dim=`` (references whose state
    carries no dimension, J only) and ``law=`` (the law instance: its options, e.g. a network variant)."""
    kw = {"dim": dim} if _takes(fn, "dim") else {}
    if _takes(fn, "law"):
        kw["law"] = law
    return kw


def ref_kirchhoff(law, state, prm, dim, weights=None):
    """``reference.kirchhoff(state, prm, w)``, with ``dim=`` and ``law=`` where the function accepts them."""
    law = law_instance(law)
    ref = _reference(law)
    w = law.initial_weights(dim) if weights is None else weights
    return np.asarray(ref.kirchhoff(state, _named(law, prm), w, **_extra(ref.kirchhoff, law, dim)), dtype=float)


def ref_update(law, state, grad_v, dt, prm, dim, weights=None):
    law = law_instance(law)
    ref = _reference(law)
    w = law.initial_weights(dim) if weights is None else weights
    kw = _extra(ref.update, law, dim)
    kw.pop("dim", None)
    return ref.update(state, np.asarray(grad_v, float), dt, _named(law, prm), w, **kw)


def _reference(law):
    ref = law_class(law).reference
    if ref is None:
        from ._common import fail

        fail(f"law '{law_class(law).name}' declares no NumPy reference (Law.reference = a module with "
             f"kirchhoff(state, prm, w) and update(state, grad_v, dt, prm, w)); the kit has nothing to compare to.")
    return ref


def reference(law, dim, what, states, prm, grad_v=None, dt=0.0):
    if what == "kirchhoff":
        return np.array([ref_kirchhoff(law, s, prm, dim) for s in states])
    return [ref_update(law, s, L, dt, prm, dim) for s, L in zip(states, grad_v)]


def _stack(states, fields):
    return {f: np.array([s[f] for s in states]) for f in fields}


def jax_eval(law, dim, what, states, prm, grad_v=None, dt=0.0):
    import jax
    import jax.numpy as jnp

    from ..backends.jax import stepper  # noqa: F401  (enables x64)
    from ..backends.jax.laws import law_functions

    law = law_instance(law)
    fns = law_functions(law, dim)
    w = {k: jnp.asarray(a) for k, a in law.initial_weights(dim).items()}
    st = {k: jnp.asarray(v) for k, v in _stack(states, law.state_fields).items()}
    P = jnp.asarray(np.tile(_row(law, prm), (len(states), 1)))
    if what == "kirchhoff":
        return np.asarray(jax.vmap(fns.kirchhoff, in_axes=(0, 0, None))(st, P, w))
    new = jax.vmap(fns.update, in_axes=(0, 0, None, 0, None))(st, jnp.asarray(grad_v), dt, P, w)
    return [{k: np.asarray(v[i]) for k, v in new.items()} for i in range(len(states))]


def warp_eval(law, dim, what, states, prm, grad_v=None, dt=0.0, precision="fp64"):
    import warp as wp

    from ..backends.warp.kernels import law_kernels

    law = law_instance(law)
    K = law_kernels(law, dim, precision)
    L = K.types
    n = len(states)
    st = _stack(states, law.state_fields)
    ins = L.state_arrays({f: wp.array(st[f], dtype=d) for f, d, _ in L.fields})
    outs_d = {f: wp.zeros(n, dtype=d) for f, d, _ in L.fields}
    w = L.weights({k: wp.array(a, dtype=L.scalar) for k, a in law.initial_weights(dim).items()})
    P = wp.array(np.tile(_row(law, prm), (n, 1)), dtype=L.scalar)
    tau = wp.zeros(n, dtype=L.mat)
    if what == "kirchhoff":
        wp.launch(K.stress, dim=n, inputs=[ins, P, w, 0, tau])
        return tau.numpy()
    wp.launch(K.update, dim=n, inputs=[ins, wp.array(np.asarray(grad_v), dtype=L.mat), P, w, L.scalar(dt), 0,
                                       L.state_arrays(outs_d), tau])
    got = {f: o.numpy() for f, o in outs_d.items()}
    return [{k: v[i] for k, v in got.items()} for i in range(n)]


EVAL = {"reference": reference, "jax": jax_eval, "warp": warp_eval}


def evaluate(law, dim, backend, what, states, prm, grad_v=None, dt=0.0):
    """``kirchhoff`` (tau [n, D, D]) or ``update`` (n state dicts) of ``law`` on ``backend``."""
    if backend not in EVAL:
        raise ValueError(f"backend '{backend}': use one of {', '.join(BACKENDS)}.")
    if what not in ("kirchhoff", "update"):
        raise ValueError(f"what='{what}': use 'kirchhoff' or 'update'.")
    return EVAL[backend](law, dim, what, states, prm, grad_v, dt)


def jax_law(law, dim):
    """A law's JAX functions on one particle with parameters as a row in declared order and the law's
    own weights: ``kirchhoff(state, row)``, ``update(state, grad_v, dt, row)``."""
    from types import SimpleNamespace

    import jax.numpy as jnp

    from ..backends.jax.laws import law_functions

    law = law_instance(law)
    fns = law_functions(law, dim)
    w = {k: jnp.asarray(a) for k, a in law.initial_weights(dim).items()}
    return SimpleNamespace(kirchhoff=lambda st, row: fns.kirchhoff(st, row, w),
                           update=lambda st, gv, dt, row: fns.update(st, gv, dt, row, w))
