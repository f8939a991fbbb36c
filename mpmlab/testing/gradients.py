"""Central differences against the backends' reverse-mode gradients of a fixed observation loss.

The loss: sum(W * observe(controls, Lagrangian(v), steps)) over ``gradient_scene`` (one block, fp64),
W a fixed random array, the controls' initial velocity sheared and compressed (``SHEAR``) so the law
leaves its rest state (plastic laws yield). For each key, one random direction d (positions: scaled
by 0.01; law parameters: relative, d * |p|; shared weights: unscaled) and the directional derivative
<grad, d> against (L(c + h d) - L(c - h d)) / 2h, relative error at the best h of ``HS`` (the V of
truncation against round-off). The same protocol as ``tests/test_grad_warp.py``.
"""
from __future__ import annotations

import numpy as np

from ._common import fail, law_name

#: finite-difference steps (relative to the direction's scale)
HS = (1e-4, 3e-5, 1e-5, 3e-6, 1e-6)
STEPS = (7, 15)
#: initial velocity gradient added to the rigid motion: shear + compression
SHEAR = {2: np.array([[0.5, 1.0], [0.3, -1.5]]),
         3: np.array([[0.5, 1.0, 0.2], [0.3, -1.5, 0.4], [-0.6, 0.1, 0.8]])}
KEYS = ("x", "v", "law", "law_weights")
_SCALE = {"x": 0.01}


def _stepper(law, backend, transfer, dim, shape="quadratic"):
    import mpmlab

    from .scenes import gradient_scene

    return mpmlab.build_stepper(gradient_scene(law, dim), backend, transfer, "fp64",
                                **({} if shape == "quadratic" else {"shape": shape}))


def leaf(c, key):
    """One control: 'law' / 'law_weights' (of the first group), ('boundary', i, name), or a top-level name."""
    if key in ("law", "law_weights"):
        return c[key][0]
    if isinstance(key, tuple):
        return c["boundary"][key[1]][key[2]]
    return c[key]


def with_leaf(c, key, value):
    """A copy of controls ``c`` with one control (a key as in ``leaf``) replaced."""
    c = dict(c)
    if key in ("law", "law_weights"):
        c[key] = (value,) + tuple(c[key][1:])
    elif isinstance(key, tuple):
        _, i, name = key
        b = [dict(d) for d in c["boundary"]]
        b[i][name] = value
        c["boundary"] = tuple(b)
    else:
        c[key] = value
    return c


def _tree(a, f):
    """f over an array or a dict of arrays (law_weights)."""
    return {k: f(v) for k, v in a.items()} if isinstance(a, dict) else f(a)


def _dot(a, b) -> float:
    if isinstance(a, dict):
        return sum(_dot(a[k], b[k]) for k in a)
    return float((a * b).sum())


def _direction(key, base, rng, to, scale=None):
    scale = _SCALE if scale is None else scale

    def one(b):
        d = rng.standard_normal(tuple(np.shape(b)))
        d = d * scale.get(key, 1.0)
        if key == "law":
            d = d * np.abs(np.asarray(b))
        return to(d)
    return _tree(base, one)


def check_gradients(law, backend: str, transfer: str = "apic", dim: int = 2, *, keys=KEYS, steps=STEPS,
                    tol: float = 1e-6, seed: int = 0, min_derivative: float = 1e-9, shape: str = "quadratic") -> dict:
    """Central differences vs reverse-mode AD (``jax.grad`` / torch autograd through Warp) of the kit's
    observation loss, w.r.t. each of ``keys``: ``x``, ``v`` (initial positions, velocities), ``law``
    (the per-particle parameters; skipped for laws without), ``law_weights`` (shared weights; skipped for
    laws without). fp64; ``shape``: the shape function (``mpmlab.shapes``) the stepper runs with;
    the relative error at the best step must be <= ``tol`` and |<grad, d>| > ``min_derivative``.

    Returns ``{key: {"error": e, "derivative": <grad, d>}}``."""
    name = law_name(law)
    st = _stepper(law, backend, transfer, dim, shape)
    c = st.controls()
    keys = [k for k in keys if not (k == "law_weights" and not c["law_weights"][0])
            and not (k == "law" and not st.groups[0].law.param_names())]   # a law without parameters
    where = f"law '{name}' {dim}D {backend} {transfer}" + ("" if shape == "quadratic" else f" shape {shape}")
    if backend == "jax":
        res = _jax(st, c, keys, steps, seed)
    elif backend == "warp":
        res = _warp(st, c, keys, steps, seed)
    else:
        raise ValueError(f"backend '{backend}': use 'jax' or 'warp'.")
    out = {}
    for k in keys:
        e, ad = res[k]
        if not abs(ad) > min_derivative:
            fail(f"{where}: d loss / d {k}: the directional derivative {ad:.3e} is too small to test anything "
                 f"(<= {min_derivative:g}); choose Law.test_params that load the law")
        if not e <= tol:
            fail(f"{where}: d loss / d {k}: AD {ad:.6e} vs central differences, relative error {e:.3e} > tolerance "
                 f"{tol:.0e} (best of h = {', '.join(f'{h:g}' for h in HS)})")
        out[k] = {"error": e, "derivative": ad}
    return out


def _sheared_v(x, v, dim):
    return v + (x - x.mean(0)) @ SHEAR[dim].T


def _jax(st, c, keys, steps, seed):
    import jax
    import jax.numpy as jnp

    from mpmlab.observations import Lagrangian

    c = dict(c)
    x = np.asarray(c["x"])
    c["v"] = jnp.asarray(_sheared_v(x, np.asarray(c["v"]), st.dim))
    obs = Lagrangian(quantity="v")
    shape = jax.eval_shape(lambda c: st.observe(c, obs, steps, segment=4), c).shape
    w = jnp.asarray(np.random.default_rng(seed).standard_normal(tuple(shape)))
    loss = jax.jit(lambda c: jnp.sum(st.observe(c, obs, steps, segment=4) * w))
    g = jax.grad(loss)(c)
    rng = np.random.default_rng(seed + 1)
    out = {}
    for k in keys:
        base = _tree(leaf(c, k), np.asarray)
        d = _direction(k, base, rng, lambda a: a)
        ad = _dot(_tree(leaf(g, k), np.asarray), d)
        errs = []
        for h in HS:
            shift = lambda s: with_leaf(c, k, _tree(_tree_add(base, d, s), jnp.asarray))
            fd = (float(loss(shift(h))) - float(loss(shift(-h)))) / (2 * h)
            errs.append(abs(fd - ad) / max(abs(fd), 1e-300))
        out[k] = (min(errs), ad)
    return out


def _warp(st, c, keys, steps, seed):
    import torch

    from mpmlab.observations import Lagrangian

    c = dict(c)
    c["v"] = c["v"] + (c["x"] - c["x"].mean(0)) @ torch.tensor(SHEAR[st.dim]).T
    return warp_fd_errors(st, c, Lagrangian(quantity="v"), steps, keys, seed)


def warp_fd_errors(st, c, obs, steps, keys, seed: int = 0, scale=None) -> dict:
    """Central differences vs torch autograd through a Warp stepper's ``observe``: for each control key
    (as in ``leaf``), ``(min relative error over HS, <grad, d>)`` along one random direction d
    (standard normal x ``scale[key]`` (default: x 0.01), x |value| for 'law'), of the loss
    sum(observe(c) * w) with fixed random weights w."""
    import torch

    c = dict(c)
    leaves = {}
    for k in keys:
        leaves[k] = _tree(leaf(c, k), lambda a: a.detach().clone().requires_grad_(True))
        c = with_leaf(c, k, leaves[k])
    y = st.observe(c, obs, steps, segment=4)
    w = torch.tensor(np.random.default_rng(seed).standard_normal(tuple(y.shape)))
    (y * w).sum().backward()
    rng = np.random.default_rng(seed + 1)
    out = {}
    for k in keys:
        base = _tree(leaves[k], lambda a: a.detach())
        d = _direction(k, _tree(base, lambda a: a.numpy()), rng, torch.tensor, scale)
        ad = _dot(_tree(leaves[k], lambda a: a.grad), d)
        errs = []
        for h in HS:
            with torch.no_grad():
                at = lambda s: float((st.observe(with_leaf(c, k, _tree_add(base, d, s)), obs, steps) * w).sum())  # noqa: E731
                fd = (at(h) - at(-h)) / (2 * h)
            errs.append(abs(fd - ad) / max(abs(fd), 1e-300))
        out[k] = (min(errs), ad)
    return out


def _tree_add(base, d, s):
    if isinstance(base, dict):
        return {n: base[n] + s * d[n] for n in base}
    return base + s * d
