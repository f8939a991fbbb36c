"""Evaluate a law's kirchhoff/update on batches, on the NumPy reference, JAX or Warp (test helper)."""
from __future__ import annotations

import numpy as np

STATE_FIELDS = ("F", "J", "sigma", "eps_p")


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

    impl = law.implementation("jax", "law")(dim)
    st = {k: jnp.asarray(v) for k, v in _stack(states, law.state_fields).items()}
    P = jnp.asarray(np.tile(prm, (len(states), 1)))
    if what == "kirchhoff":
        return np.asarray(jax.vmap(impl.kirchhoff)(st, P))
    new = jax.vmap(impl.update, in_axes=(0, 0, None, 0))(st, jnp.asarray(grad_v), dt, P)
    return [{k: np.asarray(v[i]) for k, v in new.items()} for i in range(len(states))]


def warp_eval(law, dim, what, states, prm, grad_v=None, dt=0.0, precision="fp64"):
    import warp as wp

    from mpmlab.backends.warp.kernels import law_kernels
    from mpmlab.backends.warp.types import warp_types

    T = warp_types(dim, precision)
    K = law_kernels(law, dim, precision)
    n = len(states)
    st = _stack(states, law.state_fields)

    def arr(name, src=None):
        dtype = T.mat if name in ("F", "sigma") else T.scalar
        if src is None:
            return wp.zeros(n if name in st else 1, dtype=dtype)
        return wp.array(src, dtype=dtype)

    ins = [arr(f, st.get(f)) if f in st else arr(f) for f in STATE_FIELDS]
    P = wp.array(np.tile(prm, (n, 1)), dtype=T.scalar)
    tau = wp.zeros(n, dtype=T.mat)
    if what == "kirchhoff":
        wp.launch(K.stress, dim=n, inputs=[*ins, P, 0, tau])
        return tau.numpy()
    outs = [arr(f) if f in st else arr(f) for f in STATE_FIELDS]
    outs = [wp.zeros(n, dtype=o.dtype) if f in st else o for f, o in zip(STATE_FIELDS, outs)]
    wp.launch(K.update, dim=n, inputs=[*ins, wp.array(np.asarray(grad_v), dtype=T.mat), P, T.scalar(dt), 0, *outs, tau])
    got = {f: o.numpy() for f, o in zip(STATE_FIELDS, outs) if f in st}
    return [{k: v[i] for k, v in got.items()} for i in range(n)]


EVAL = {"reference": reference, "jax": jax_eval, "warp": warp_eval}
