"""Evaluate a law's kirchhoff/update on batches, on the NumPy reference, JAX or Warp (test helper)."""
from __future__ import annotations

import numpy as np

def states_from_F(law, Fs: np.ndarray, rng: np.random.Generator) -> list[dict]:
    """Law states built from deformation gradients: F itself, J = det F, a stress of the law's scale."""
    E = law_stiffness(law)
    out = []
    for F in Fs:
        s = {}
        for f in law.state_fields:
            if f == "F":
                s["F"] = F
            elif f == "J":
                s["J"] = abs(np.linalg.det(F))
            elif f == "sigma":
                A = rng.standard_normal(F.shape) * 0.3 * E
                s["sigma"] = 0.5 * (A + A.T) - 0.5 * E * np.eye(len(F))
            elif f == "eps_p":
                s["eps_p"] = abs(rng.standard_normal()) * 0.01
        out.append(s)
    return out


def law_stiffness(law) -> float:
    for name in ("E", "bulk_modulus"):
        if name in law.param_names():
            return float(next(p.default for p in law.params if p.name == name) or 1e4)
    return 1e4


def default_params(law, density: float = 1000.0) -> np.ndarray:
    prm = law.resolve_params({}, "test", density=density)
    return np.array([prm[k] for k in law.param_names()])


def ref_kirchhoff(law, state, prm, dim):
    """reference.kirchhoff; a state without a matrix field (J only) carries no dimension, so pass it."""
    if {"F", "sigma"} & set(law.state_fields):
        return law.reference.kirchhoff(state, prm)
    return law.reference.kirchhoff(state, prm, dim=dim)


def reference(law, dim, what, states, prm, grad_v=None, dt=0.0):
    if what == "kirchhoff":
        return np.array([ref_kirchhoff(law, s, prm, dim) for s in states])
    return [law.reference.update(s, L, dt, prm) for s, L in zip(states, grad_v)]


def _stack(states, fields):
    return {f: np.array([s[f] for s in states]) for f in fields}


def jax_eval(law, dim, what, states, prm, grad_v=None, dt=0.0):
    import jax
    import jax.numpy as jnp

    from mpmlab.backends.jax import stepper  # noqa: F401  (enables x64)
    from mpmlab.backends.jax.laws import law_functions

    law = law() if isinstance(law, type) else law
    fns = law_functions(law, dim)
    w = {k: jnp.asarray(a) for k, a in law.initial_weights(dim).items()}
    st = {k: jnp.asarray(v) for k, v in _stack(states, law.state_fields).items()}
    P = jnp.asarray(np.tile(prm, (len(states), 1)))
    if what == "kirchhoff":
        return np.asarray(jax.vmap(fns.kirchhoff, in_axes=(0, 0, None))(st, P, w))
    new = jax.vmap(fns.update, in_axes=(0, 0, None, 0, None))(st, jnp.asarray(grad_v), dt, P, w)
    return [{k: np.asarray(v[i]) for k, v in new.items()} for i in range(len(states))]


def warp_eval(law, dim, what, states, prm, grad_v=None, dt=0.0, precision="fp64"):
    import warp as wp

    from mpmlab.backends.warp.kernels import law_kernels

    law = law() if isinstance(law, type) else law
    K = law_kernels(law, dim, precision)
    L = K.types
    n = len(states)
    st = _stack(states, law.state_fields)
    ins = L.state_arrays({f: wp.array(st[f], dtype=d) for f, d, _ in L.fields})
    outs_d = {f: wp.zeros(n, dtype=d) for f, d, _ in L.fields}
    w = L.weights({k: wp.array(a, dtype=L.scalar) for k, a in law.initial_weights(dim).items()})
    P = wp.array(np.tile(prm, (n, 1)), dtype=L.scalar)
    tau = wp.zeros(n, dtype=L.mat)
    if what == "kirchhoff":
        wp.launch(K.stress, dim=n, inputs=[ins, P, w, 0, tau])
        return tau.numpy()
    wp.launch(K.update, dim=n, inputs=[ins, wp.array(np.asarray(grad_v), dtype=L.mat), P, w, L.scalar(dt), 0,
                                       L.state_arrays(outs_d), tau])
    got = {f: o.numpy() for f, o in outs_d.items()}
    return [{k: v[i] for k, v in got.items()} for i in range(n)]


EVAL = {"reference": reference, "jax": jax_eval, "warp": warp_eval}


def jax_law(law, dim):
    """A law's JAX functions on one particle with parameters as a row in declared order and the law's
    own weights: ``kirchhoff(state, row)``, ``update(state, grad_v, dt, row)`` (the v1 call shape)."""
    import jax.numpy as jnp

    from mpmlab.backends.jax.laws import law_functions

    law = law() if isinstance(law, type) else law
    fns = law_functions(law, dim)
    w = {k: jnp.asarray(a) for k, a in law.initial_weights(dim).items()}
    from types import SimpleNamespace

    return SimpleNamespace(kirchhoff=lambda st, row: fns.kirchhoff(st, row, w),
                           update=lambda st, gv, dt, row: fns.update(st, gv, dt, row, w))
