"""Warp ``phase_change``: a per-particle branch to the active law's ``@wp.func``s. The two laws keep
their own ``LawState``/``Params``/``Weights`` structs; small generated functions copy this law's
members into them (shared weights are ``wp.array``s: a copy points at the same memory and gradient)."""

from functools import lru_cache
from types import SimpleNamespace

import warp as wp

from ...backends.warp.kernels import law_module_options
from ...backends.warp.law_structs import _generated_func, law_types


def _converters(law, side: str, sub, T, S, key: str) -> SimpleNamespace:
    """``state(s) -> S.LawState``, ``params(prm) -> S.Params``, ``weights(w) -> S.Weights`` and
    ``merge(s, sub_state) -> LawState`` between this law's structs ``T`` and side law's ``S``."""
    ns = {"wp": wp, "LawState": T.LawState, "Params": T.Params, "Weights": T.Weights,
          "SState": S.LawState, "SParams": S.Params, "SWeights": S.Weights}
    names = [f.name for f in sub.state]
    k = f"{key}_{side}"
    body = "".join(f"    out.{n} = s.{n}\n" for n in names)
    state = _generated_func("state", f"def state(s: LawState):\n    out = SState()\n{body}    return out\n", ns, k)
    body = "".join(f"    out.{n} = s.{n}\n" for n in names) or "    pass\n"
    merge = _generated_func("merge", f"def merge(t: LawState, s: SState):\n    out = t\n"
                            + body.replace("    pass\n", "") + "    return out\n", ns, k)
    body = "".join(f"    out.{n} = prm.{side}_{n}\n" for n in sub.param_names())
    params = _generated_func("params", f"def params(prm: Params):\n    out = SParams()\n{body}    return out\n", ns, k)
    members = list(sub.weight_shapes(T.dim)) + list(sub.weight_views(T.dim))
    body = "".join(f"    out.{n} = w.{side}_{n}\n" for n in members)
    weights = _generated_func("weights", f"def weights(w: Weights):\n    out = SWeights()\n{body}    return out\n", ns, k)
    return SimpleNamespace(state=state, merge=merge, params=params, weights=weights)


@lru_cache(maxsize=None)
def make(law, dim: int, precision: str) -> SimpleNamespace:
    T = law_types(law, dim, precision)
    (_, a), (_, b) = law.sides()
    Sa, Sb = law_types(a, dim, precision), law_types(b, dim, precision)
    Fa = a.implementation("warp", "law")(a, dim, precision)
    Fb = b.implementation("warp", "law")(b, dim, precision)
    key = T.LawState.key.replace(".", "_")
    Ca = _converters(law, "before", a, T, Sa, key)
    Cb = _converters(law, "after", b, T, Sb, key)
    scalar, mat, LawState, Params, Weights = T.scalar, T.mat, T.LawState, T.Params, T.Weights

    @wp.func
    def kirchhoff(s: LawState, prm: Params, w: Weights):
        if s.clock >= prm.switch_time:
            return Fb.kirchhoff(Cb.state(s), Cb.params(prm), Cb.weights(w))
        return Fa.kirchhoff(Ca.state(s), Ca.params(prm), Ca.weights(w))

    @wp.func
    def update(s: LawState, grad_v: mat, dt: scalar, prm: Params, w: Weights):
        out = s
        if s.clock >= prm.switch_time:
            out = Cb.merge(s, Fb.update(Cb.state(s), grad_v, dt, Cb.params(prm), Cb.weights(w)))
        else:
            out = Ca.merge(s, Fa.update(Ca.state(s), grad_v, dt, Ca.params(prm), Ca.weights(w)))
        out.clock = s.clock + dt
        return out

    opts = {**law_module_options(Fa), **law_module_options(Fb)}
    return SimpleNamespace(kirchhoff=kirchhoff, update=update, module_options=opts)
