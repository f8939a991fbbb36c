"""Warp types generated from a law's declarations (``AbstractConstitutiveLaw``): the ``LawState``
struct of its state fields, the ``Params`` struct of its named parameters, the ``Weights`` struct of
its shared arrays, and the loaders the kernels use, built once per (law, dim, precision).

Structs are created with ``wp.struct`` on a class made at run time; the three small loader/storer
functions are generated as source (Warp compiles ``@wp.func``s from their source text, so the text is
registered with ``linecache``). Law code never sees storage: it reads ``s.F``, ``prm.E``, ``w.W1``.
"""
from __future__ import annotations

import hashlib
import linecache
from functools import lru_cache
from types import SimpleNamespace

import numpy as np
import warp as wp

from .types import warp_types

_ARRAY_DIMS = {1: wp.array, 2: wp.array2d, 3: wp.array3d, 4: wp.array4d}


def field_dtype(T, shape: tuple[int, ...]):
    """The Warp type of one particle's value of a field of (resolved) ``shape``."""
    if shape == ():
        return T.scalar
    if len(shape) == 1:
        return T.vec if shape[0] == T.dim else wp.types.vector(shape[0], T.scalar)
    if shape == (T.dim, T.dim):
        return T.mat
    return wp.types.matrix(shape, T.scalar)


def _struct(name: str, fields: dict, key: str):
    # a distinct, stable class name per law/dim/precision: Warp keys struct types by qualified name
    qual = f"{name}_{key}"
    cls = type(qual, (), {"__annotations__": dict(fields), "__module__": __name__, "__qualname__": qual})
    return wp.struct(cls)


def _generated_func(name: str, src: str, namespace: dict, key: str):
    filename = f"<mpmlab law_types {key} {name}>"
    linecache.cache[filename] = (len(src), None, src.splitlines(True), filename)
    ns = dict(namespace)
    exec(compile(src, filename, "exec"), ns)
    fn = ns[name]
    fn.__qualname__ = f"{name}_{key}"
    return wp.func(fn)


@lru_cache(maxsize=None)
def law_types(law, dim: int, precision: str) -> SimpleNamespace:
    """Types and loaders for one law instance (``law``: an ``AbstractConstitutiveLaw`` instance).

    Returns a namespace with the base types (``scalar``, ``vec``, ``mat``, ``ivec``) and
    ``LawState`` (struct: one member per state field), ``Params`` (struct: one scalar per parameter,
    by name), ``Weights`` (struct: one ``wp.array`` per shared array), ``StateArrays`` (struct: one
    per-particle array per state field), the ``@wp.func``s ``load_state(a, q)``,
    ``store_state(a, q, s)`` and ``load_params(prm, q)``, and ``fields``: [(name, dtype, shape)].
    """
    T = warp_types(dim, precision)
    # stable across processes (Warp's kernel cache keys on the generated source, names included)
    digest = hashlib.sha1(repr(law.code_key()).encode()).hexdigest()[:8]
    key = f"{type(law).__module__}.{type(law).__qualname__}_{digest}_{dim}d_{precision}".replace(".", "_")
    fields = [(f.name, field_dtype(T, f.resolved_shape(dim)), f.resolved_shape(dim)) for f in law.state]
    LawState = _struct("LawState", {n: d for n, d, _ in fields}, key)
    StateArrays = _struct("StateArrays", {n: wp.array(dtype=d) for n, d, _ in fields}, key)
    Params = _struct("Params", {n: T.scalar for n in law.param_names()}, key)
    wshapes = law.weight_shapes(dim)
    for k, s in wshapes.items():
        if not 1 <= len(s) <= 4:
            raise ValueError(f"law '{law.name}': weight '{k}' has {len(s)} dimensions; Warp arrays take 1-4.")
    # the law's vector views of its arrays (``AbstractConstitutiveLaw.weight_views``): one vector type each
    views = {}
    for v, (src, how) in law.weight_views(dim).items():
        s = wshapes[src]
        n = {"cols": lambda: s[0], "rows": lambda: s[-1], "grad_rows": lambda: s[-1], "whole": lambda: s[0]}[how]()
        if (len(s) != 1) != (how != "whole"):
            raise ValueError(f"law '{law.name}': weight view '{v}' ({how}) of '{src}' {s}: cols/rows take a 2D array, "
                             f"whole a 1D one.")
        views[v] = (src, how, wp.types.vector(n, T.scalar))
    Weights = _struct("Weights", {**{k: _ARRAY_DIMS[len(s)](dtype=T.scalar) for k, s in wshapes.items()},
                                  **{v: wp.array(dtype=vt) for v, (_, _, vt) in views.items()}}, key)
    ns = {"wp": wp, "scalar": T.scalar, "LawState": LawState, "StateArrays": StateArrays, "Params": Params}
    body = "".join(f"    s.{n} = a.{n}[q]\n" for n, _, _ in fields)
    load_state = _generated_func("load_state", f"def load_state(a: StateArrays, q: int):\n    s = LawState()\n{body}"
                                 f"    return s\n", ns, key)
    body = "".join(f"    a.{n}[q] = s.{n}\n" for n, _, _ in fields) or "    pass\n"
    store_state = _generated_func("store_state", f"def store_state(a: StateArrays, q: int, s: LawState):\n{body}",
                                  ns, key)
    body = "".join(f"    out.{n} = prm[q, {i}]\n" for i, n in enumerate(law.param_names()))
    load_params = _generated_func("load_params", "def load_params(prm: wp.array2d(dtype=scalar), q: int):\n"
                                  f"    out = Params()\n{body}    return out\n", ns, key)

    def state_arrays(arrays: dict):
        """A ``StateArrays`` instance over ``{field: wp.array}``."""
        s = StateArrays()
        for n, _, _ in fields:
            setattr(s, n, arrays[n])
        return s

    def grad_rows(a, vt):
        """``a.grad`` (a contiguous 2D [r, c] array) seen as r vectors of type ``vt`` (no copy); an empty
        array when ``a`` takes no gradient. It holds no reference: ``a`` (and so its gradient) must outlive
        the struct, as the controls of a gradient path do."""
        g = a.grad if a.requires_grad else None
        if g is None:
            return wp.empty(0, dtype=vt, device=a.device)
        if not g.is_contiguous or g.ndim != 2:
            raise ValueError(f"a grad_rows view needs a contiguous 2D gradient array; got shape {g.shape}")
        return wp.array(ptr=g.ptr, dtype=vt, shape=(g.shape[0],), device=g.device)

    def weights(arrays: dict):
        """A ``Weights`` instance over ``{name: wp.array}``."""
        w = Weights()
        for k in wshapes:
            setattr(w, k, arrays[k])
        for v, (src, how, vt) in views.items():       # copies laid out as the view says, or a gradient alias
            a = arrays[src]
            if how == "grad_rows":                     # an alias of the source's gradient, not a copy
                setattr(w, v, grad_rows(a, vt))
                continue
            m = a.numpy()
            m = m.T if how == "cols" else (m[None] if how == "whole" else m)
            setattr(w, v, wp.array(np.ascontiguousarray(m), dtype=vt, device=a.device))
        return w

    return SimpleNamespace(scalar=T.scalar, vec=T.vec, mat=T.mat, ivec=T.ivec, dim=dim, precision=precision, views=views,
                           LawState=LawState, Params=Params, Weights=Weights, StateArrays=StateArrays,
                           load_state=load_state, store_state=store_state, load_params=load_params,
                           fields=fields, weight_shapes=wshapes, state_arrays=state_arrays, weights=weights)
