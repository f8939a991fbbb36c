"""A transfer scheme's JAX functions, checked against its declarations when the stepper is built.

The step (``stepper.py``) composes ``p2g(p) -> P2GTerms`` and ``g2p(g) -> G2PResult`` of the scheme
(``AbstractTransfer`` documents both); here they are traced once on two particles (shapes only,
``jax.eval_shape``), so a scheme whose functions do not fit what it declares is refused in one line
naming it, not with a KeyError during tracing or a silently absent term.
"""
from __future__ import annotations

from types import SimpleNamespace

import jax
import jax.numpy as jnp

from ...core.errors import ConfigError


def transfer_functions(transfer, dim: int, dtype=jnp.float64, per_particle_Dinv: bool = False) -> SimpleNamespace:
    """The scheme's JAX ``p2g`` / ``g2p``, traced once on the inputs the step will give them: ``Dinv`` a
    Python float (B-spline shapes) or, with ``per_particle_Dinv`` (uGIMP), an [N, D, D] array."""
    transfer.check()
    where = transfer.describe()
    fns = transfer.implementation("jax", "transfer")(transfer, dim)
    for attr in ("p2g", "g2p"):
        if not callable(getattr(fns, attr, None)):
            raise ConfigError(f"{where}: its JAX factory gives no {attr}(...) (AbstractTransfer documents both).")
    check_transfer(fns, transfer, dim, dtype, per_particle_Dinv)
    return fns


def _first_line(e: Exception) -> str:
    return f"{type(e).__name__}: {e}".split("\n")[0]


def check_transfer(fns, transfer, dim: int, dtype, per_particle_Dinv: bool = False) -> None:
    N, D = 2, dim
    where = transfer.describe()
    S = lambda *shape: jax.ShapeDtypeStruct(shape, dtype)           # noqa: E731
    split = bool(transfer.split_force)

    Dinv = S(N, D, D) if per_particle_Dinv else None       # None: the float 400.0 (4 / dx^2, dx = 0.1)

    def p2g(m, V, v, C, tau, Dinv):
        return tuple(fns.p2g(SimpleNamespace(m=m, V=V, v=v, C=C, tau=tau, dt=1e-3, inv_dx=10.0, dx=0.1,
                                             Dinv=400.0 if Dinv is None else Dinv)))

    try:
        got = jax.eval_shape(p2g, S(N), S(N), S(N, D), S(N, D, D) if transfer.carries_C else None, S(N, D, D), Dinv)
    except Exception as e:  # noqa: BLE001 -- any failure here is the plugin's: say which and why
        raise ConfigError(f"{where}: its JAX p2g fails on the declared inputs: {_first_line(e)}") from None
    if len(got) != 5:
        raise ConfigError(f"{where}: JAX p2g must return P2GTerms(q, A, G, force_A, force_G); got {len(got)} items.")
    want = {"q": True, "A": "affine" in transfer.momentum_terms, "G": "gradient" in transfer.momentum_terms,
            "force_A": split and "affine" in transfer.force_terms,
            "force_G": split and "gradient" in transfer.force_terms}
    for (name, declared), a in zip(want.items(), got):
        if declared and a is None:
            raise ConfigError(f"{where}: JAX p2g returns no {name}, but the scheme declares it "
                              f"(momentum_terms {sorted(transfer.momentum_terms)}, force_terms {sorted(transfer.force_terms)}).")
        if a is not None and not declared:
            raise ConfigError(f"{where}: JAX p2g returns {name}, which the scheme does not declare "
                              f"(momentum_terms {sorted(transfer.momentum_terms)}, force_terms "
                              f"{sorted(transfer.force_terms)}, split_force {split}): declare it or return None.")
        shape = (N, D) if name == "q" else (N, D, D)
        if a is not None and tuple(a.shape) != shape:
            raise ConfigError(f"{where}: JAX p2g returns {name} of shape {tuple(a.shape)} for {N} particles; "
                              f"it must be {shape}.")

    def g2p(v, v_pic, v_old, first, grad, fx, Dinv):
        return tuple(fns.g2p(SimpleNamespace(v=v, v_pic=v_pic, v_old=v_old, first=first, grad=grad, fx=fx,
                                             inv_dx=10.0, dx=0.1, Dinv=400.0 if Dinv is None else Dinv)))

    try:
        res = jax.eval_shape(g2p, S(N, D), S(N, D), S(N, D) if split else None,
                             S(N, D, D) if "first" in transfer.moments else None,
                             S(N, D, D) if "gradient" in transfer.moments else None, S(N, D), Dinv)
    except Exception as e:  # noqa: BLE001
        raise ConfigError(f"{where}: its JAX g2p fails on the declared moments {sorted(transfer.moments)}: "
                          f"{_first_line(e)}") from None
    if len(res) != 3:
        raise ConfigError(f"{where}: JAX g2p must return G2PResult(v, C, grad_v); got {len(res)} items.")
    v, C, gv = res
    if v is None or tuple(v.shape) != (N, D):
        raise ConfigError(f"{where}: JAX g2p returns v of shape {getattr(v, 'shape', None)}; it must be {(N, D)}.")
    if (C is None) == bool(transfer.carries_C):
        raise ConfigError(f"{where}: JAX g2p returns {'no C' if C is None else 'a C'}, but the scheme declares "
                          f"carries_C = {bool(transfer.carries_C)}.")
    for name, a in (("C", C), ("grad_v", gv)):
        if name == "C" and a is None:
            continue
        if a is None or tuple(a.shape) != (N, D, D):
            raise ConfigError(f"{where}: JAX g2p returns {name} of shape {getattr(a, 'shape', None)}; "
                              f"it must be {(N, D, D)}.")
