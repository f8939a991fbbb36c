"""Checks on a law's two functions alone (no stepper): each backend against the NumPy reference on
hard states, the rest state, rotation equivariance and a symmetric Kirchhoff stress."""
from __future__ import annotations

import numpy as np

from ._common import fail, law_class, law_instance, law_name, rel_err, resolve_params
from .evaluate import evaluate, ref_kirchhoff, ref_update
from .states import KINDS, hard_states, rest_state, rotate_state, rotation, rotation_rules, velocity_gradients


def _worst(got, ref) -> int:
    d = np.abs(np.asarray(got, float) - np.asarray(ref, float)).reshape(len(got), -1)
    return int(np.argmax(d.max(axis=1)))


def check_reference(law, dim: int, backend: str, *, what=("kirchhoff", "update"), params=None, seed: int = 1,
                    dt: float = 1e-2, tol: float = 1e-10) -> dict:
    """``backend``'s kirchhoff and update against the law's NumPy reference on 16 hard states
    (``states.hard_states``: near-singular and large-strain F, stresses of the law's scale, ...).

    Kirchhoff stress from states drawn with ``seed``; the update from states drawn with ``seed + 1``
    (a random velocity gradient of scale 2 per state, ``dt``). The error is max |got - ref| / max |ref|
    over the batch, per quantity; each must be <= ``tol``. ``params``: None (``test_params``),
    ``"defaults"`` or a mapping (``_common.resolve_params``).

    Returns ``{"kirchhoff": err, "update": {field: err}}`` (the quantities in ``what``); raises
    ``AssertionError`` naming the law, backend, quantity, error, tolerance and the worst state.
    """
    law = law_instance(law)
    name = law_name(law)
    what = (what,) if isinstance(what, str) else tuple(what)
    prm = resolve_params(law, params)
    out = {}
    where = f"law '{name}' {dim}D {backend}"
    if "kirchhoff" in what:
        rng = np.random.default_rng(seed)
        states = hard_states(law, dim, rng, prm)
        ref = evaluate(law, dim, "reference", "kirchhoff", states, prm)
        got = evaluate(law, dim, backend, "kirchhoff", states, prm)
        e = rel_err(got, ref)
        if not e <= tol:
            i = _worst(got, ref)
            fail(f"{where}: kirchhoff vs the NumPy reference: relative error {e:.3e} > tolerance {tol:.0e} "
                 f"(worst: state {i}, {KINDS[i]} F)")
        out["kirchhoff"] = e
    if "update" in what:
        rng = np.random.default_rng(seed + 1 if "kirchhoff" in what else seed)
        states = hard_states(law, dim, rng, prm)
        L = velocity_gradients(len(states), dim, rng)
        ref = evaluate(law, dim, "reference", "update", states, prm, L, dt)
        got = evaluate(law, dim, backend, "update", states, prm, L, dt)
        errs = {}
        for f in law.state_fields:
            a, b = [g[f] for g in got], [r[f] for r in ref]
            e = rel_err(a, b)
            if not e <= tol:
                i = _worst(a, b)
                fail(f"{where}: update field '{f}' vs the NumPy reference: relative error {e:.3e} > tolerance "
                     f"{tol:.0e} (worst: state {i}, {KINDS[i]} F)")
            errs[f] = e
        out["update"] = errs
    return out


def check_rest_state(law, dim: int, backends=("reference",), *, params=None, dt: float = 1e-3,
                     tol: float = 1e-12) -> dict:
    """The declared initial state (``Law.state`` inits) is a rest state on each backend: |tau| <= ``tol``
    (absolute, in Pa), and one ``update`` with grad_v = 0 keeps it (each field within ``tol`` of its
    initial value, relative to max(1, |value|); a field the law names in ``clock_fields`` advanced by
    exactly dt) and its stress (|tau| <= ``tol``).

    Returns ``{backend: {"tau": max|tau|, "tau_after": ..., "state": max field change}}``."""
    law = law_instance(law)
    name = law_name(law)
    prm = resolve_params(law, params)
    st = rest_state(law, dim)
    out = {}
    for b in ((backends,) if isinstance(backends, str) else backends):
        where = f"law '{name}' {dim}D {b}"
        tau = np.asarray(evaluate(law, dim, b, "kirchhoff", [st], prm))[0]
        t0 = float(np.max(np.abs(tau)))
        if not t0 <= tol:
            fail(f"{where}: the declared initial state is not at rest: max |tau| = {t0:.3e} Pa > tolerance "
                 f"{tol:.0e} Pa")
        new = evaluate(law, dim, b, "update", [st], prm, np.zeros((1, dim, dim)), dt)[0]
        ds = 0.0
        clocks = tuple(getattr(law_class(law), "clock_fields", ()))
        for f in law.state_fields:
            want = st[f] + dt if f in clocks else st[f]       # a clock field counts time: + dt per update
            d = float(np.max(np.abs(np.asarray(new[f], float) - want)) / max(1.0, float(np.max(np.abs(want)))))
            if not d <= tol:
                fail(f"{where}: update with grad_v = 0 moves field '{f}' off its initial value by {d:.3e} "
                     f"(relative) > tolerance {tol:.0e}")
            ds = max(ds, d)
        tau1 = np.asarray(evaluate(law, dim, b, "kirchhoff", [new], prm))[0]
        t1 = float(np.max(np.abs(tau1)))
        if not t1 <= tol:
            fail(f"{where}: after an update with grad_v = 0 the rest state has max |tau| = {t1:.3e} Pa > tolerance "
                 f"{tol:.0e} Pa")
        out[b] = {"tau": t0, "tau_after": t1, "state": ds}
    return out


def check_equivariance(law, dim: int, *, params=None, seed: int = 3, dt: float = 1e-2, tol: float = 1e-9,
                       sym_tol: float = 1e-10) -> dict:
    """On the NumPy reference, for 16 hard states each with a random rotation Q:

    * tau is symmetric: |tau - tau^T| <= ``sym_tol`` * max(|tau|, 1)  (tau = P F^T), unless the law
      declares ``symmetric_stress = False`` (the asymmetry is then measured, not required);
    * tau(Q.s) = Q tau(s) Q^T within ``tol`` * max(|tau|, 1);
    * the update commutes with rotation: Q.update(s, L) = update(Q.s, Q L Q^T) per field within
      ``tol`` * max(|field|, 1).

    Q.s rotates each field by ``states.rotation_rules`` (F -> Q F, stresses -> Q S Q^T, vectors -> Q n,
    scalars unchanged; ``Law.test_rotation`` overrides). Returns the largest scaled error of each."""
    law = law_instance(law)
    name = law_name(law)
    prm = resolve_params(law, params)
    rules = rotation_rules(law, dim)
    rng = np.random.default_rng(seed)
    where = f"law '{name}' {dim}D reference"
    worst = {"symmetry": 0.0, "kirchhoff": 0.0, "update": {f: 0.0 for f in law.state_fields}}
    for i, st in enumerate(hard_states(law, dim, rng, prm)):
        Q = rotation(dim, rng)
        tau = ref_kirchhoff(law, st, prm, dim)
        scale = max(np.max(np.abs(tau)), 1.0)
        e = float(np.max(np.abs(tau - tau.T)) / scale)
        if not e <= sym_tol and getattr(law, "symmetric_stress", True):
            fail(f"{where}: tau is not symmetric: |tau - tau^T| / max(|tau|, 1) = {e:.3e} > tolerance {sym_tol:.0e} "
                 f"(state {i}, {KINDS[i]} F)")
        worst["symmetry"] = max(worst["symmetry"], e)
        tau_r = ref_kirchhoff(law, rotate_state(st, Q, rules), prm, dim)
        e = float(np.max(np.abs(tau_r - Q @ tau @ Q.T)) / scale)
        if not e <= tol:
            fail(f"{where}: kirchhoff is not rotation-equivariant: |tau(Q.s) - Q tau(s) Q^T| / max(|tau|, 1) = "
                 f"{e:.3e} > tolerance {tol:.0e} (state {i}, {KINDS[i]} F; rotation rules {rules})")
        worst["kirchhoff"] = max(worst["kirchhoff"], e)
        L = rng.standard_normal((dim, dim))
        a = rotate_state(ref_update(law, st, L, dt, prm, dim), Q, rules)
        b = ref_update(law, rotate_state(st, Q, rules), Q @ L @ Q.T, dt, prm, dim)
        for f in law.state_fields:
            sc = max(np.max(np.abs(a[f])), 1.0)
            e = float(np.max(np.abs(np.asarray(a[f]) - np.asarray(b[f]))) / sc)
            if not e <= tol:
                fail(f"{where}: update does not commute with rotation in field '{f}': "
                     f"|Q.update(s, L) - update(Q.s, Q L Q^T)| / max(|{f}|, 1) = {e:.3e} > tolerance {tol:.0e} "
                     f"(state {i}, {KINDS[i]} F; '{f}' rotates as '{rules[f]}')")
            worst["update"][f] = max(worst["update"][f], e)
    return worst
