"""Gradients through JAX rollouts: checkpointed segments, observations, NaN localisation.

JAX-MPM Sec. 3.3.2: the step is rematerialised (``jax.checkpoint``, Remark 4) and the loop is a
``lax.scan`` over checkpointed segments of ``segment`` steps (Remark 5), so reverse mode keeps one
state per segment plus one per step of the segment being recomputed: O(steps / segment + segment)
states instead of O(steps) full intermediates (grid included).

Observations are taken on a regular schedule: the state after step s_1, then every g steps, where g
is the gcd of the gaps between the requested steps; the requested ones are picked from those. For
the usual evenly spaced schedules (JAX-MPM Sec. 5) nothing extra is observed.
"""
from __future__ import annotations

import math
from functools import reduce
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ...core.errors import ConfigError, GradientError

DEFAULT_SEGMENT = 100


def controls(stepper) -> dict[str, Any]:
    """The differentiable inputs of a rollout (``AbstractStepper.controls``), as JAX arrays."""
    P, dt = stepper.particles, stepper.dtype
    prm = stepper.default_params()
    scene_order = [None] * len(stepper._bc_order)
    for k, i in enumerate(stepper._bc_order):
        scene_order[i] = prm["boundary"][k]
    law_state = stepper.to_scene_order(stepper.init())["law"]   # the initial state (the bodies' F)
    out = {"x": jnp.asarray(P.x, dt), "v": jnp.asarray(P.v, dt), "law": prm["law"], "law_weights": prm["law_weights"],
           "law_state": law_state, "boundary": tuple(scene_order),
           "gravity": prm["gravity"], "mass": prm["mass"], "volume": prm["volume"]}
    if stepper.transfer.needs_affine:
        out["C"] = jnp.asarray(stepper.initial_C(), dt)
    return out


REQUIRED = ("x", "v", "law", "boundary", "gravity", "mass", "volume")


def split_controls(stepper, c: dict[str, Any]) -> tuple[dict, dict]:
    """(initial state, step parameters) from controls, in the layout ``stepper.step_fn`` works on (a
    sharded stepper's: ``to_layout``). ``law_state`` and ``C`` are optional: without them the rollout
    starts from the scene's initial state (the bodies' F and C; F = I, J = 1, C = 0 by default);
    ``law_weights`` defaults to the laws' own weights."""
    missing = set(REQUIRED) - set(c)
    if missing:
        raise ConfigError(f"controls lack {sorted(missing)}; start from stepper.controls() and replace entries.")
    dt = stepper.dtype
    if "law_state" in c:
        law_states = tuple(c["law_state"])
        if len(law_states) != len(stepper.groups):
            raise ConfigError(f"controls['law_state'] has {len(law_states)} entries; the scene has "
                              f"{len(stepper.groups)} material groups.")
        for g, st in zip(stepper.groups, law_states):
            if set(st) != set(g.law.state_fields):
                raise ConfigError(f"controls['law_state'] for law '{g.law.name}' has fields {sorted(st)}; the law "
                                  f"declares {sorted(g.law.state_fields)}.")
    else:
        law_states = stepper.to_scene_order(stepper.init())["law"]
    state = {"x": jnp.asarray(c["x"], dt), "v": jnp.asarray(c["v"], dt), "law": law_states, "t": jnp.asarray(0.0, dt)}
    if stepper.transfer.needs_affine:
        state["C"] = (jnp.asarray(c["C"], dt) if "C" in c
                      else jnp.asarray(stepper.initial_C(), dt))
    if getattr(stepper, "corners", False):       # CPDI's domains: the scene's, a constant of the run
        state["domain"] = jnp.asarray(stepper.initial_domain(), dt)
    if len(c["boundary"]) != len(stepper._bc_order):
        raise ConfigError(f"controls have {len(c['boundary'])} boundary entries; the scene has {len(stepper._bc_order)}.")
    weights = tuple(c["law_weights"]) if "law_weights" in c else stepper.default_params()["law_weights"]
    params = {"law": tuple(c["law"]), "law_weights": weights, "mass": c["mass"], "volume": c["volume"],
              "gravity": c["gravity"], "boundary": tuple(c["boundary"][i] for i in stepper._bc_order),   # scene -> stepper order
              **stepper._shape_params()}      # uGIMP's lp: a constant of the run, not a control
    return stepper.to_layout(state, params)


def advance(stepper, state, params, n: int, segment: int, keep: bool = False, remat_steps: bool = True):
    """``n`` steps as a scan over checkpointed segments of rematerialised steps (JAX-MPM Remarks 4-5).

    ``keep=True`` (``segment="auto"`` when the rollout fits the memory budget: :func:`resolve`): one
    plain scan, no ``jax.checkpoint`` anywhere, so reverse mode keeps every step's residuals and pays
    forward + backward (F + B) instead of recomputing. ``remat_steps=False`` drops the per-step
    checkpoint inside a recomputed segment (the segment's residuals are kept while it is
    differentiated: F + F + B instead of F + F + F + B, segment x the residual bytes of a step)."""
    if keep:
        return jax.lax.scan(lambda c, _: (stepper.step_fn(c, params), None), state, None, length=n)[0] if n else state
    step = jax.checkpoint(stepper.step_fn) if remat_steps else stepper.step_fn

    def run(s, p, length):
        return jax.lax.scan(lambda c, _: (step(c, p), None), s, None, length=length)[0]

    segment = max(1, min(segment, n)) if n else 1
    nseg, rem = divmod(n, segment)
    if nseg:
        seg = jax.checkpoint(lambda s, p: run(s, p, segment))
        state = jax.lax.scan(lambda c, _: (seg(c, params), None), state, None, length=nseg)[0] if nseg > 1 \
            else seg(state, params)
    if rem:
        state = jax.checkpoint(lambda s, p: run(s, p, rem))(state, params)
    return state


def step_bytes(stepper) -> int:
    """Bytes one kept step costs a gradient: its state plus the residuals reverse mode saves for it
    (``jax.ad_checkpoint`` 's list of a step's saved residuals, shapes only, traced once per stepper)."""
    cache = stepper.__dict__.setdefault("_step_bytes", {})
    if "b" not in cache:
        state, params = split_controls(stepper, controls(stepper))
        nbytes = lambda a: int(np.prod(a.shape)) * np.dtype(a.dtype).itemsize
        total = sum(nbytes(a) for a in jax.tree_util.tree_leaves(state))
        try:
            from jax._src.ad_checkpoint import saved_residuals

            res = saved_residuals(stepper.step_fn, state, params)
            total += sum(nbytes(a) for a, _ in res)
        except Exception:  # noqa: BLE001 -- a JAX without it: the per-particle scratch of a step, from shapes
            N, D = stepper.particles.count, stepper.dim
            K = D + 1 + (D if stepper.transfer.split_force else 0)
            total += N * (int(stepper.shape.width) ** D) * K * np.dtype(stepper.dtype).itemsize * 4
        cache["b"] = int(total)
    return cache["b"]


def resolve(stepper, segment, steps: int) -> tuple[int, bool]:
    """(segment length, keep every step) for a rollout of ``steps`` steps: ``segment`` an int, None
    (``DEFAULT_SEGMENT``) or ``"auto"`` (keep the states and residuals when ``steps x step_bytes``
    fits the budget of ``mpmlab.core.budget.resolve_segment``)."""
    from ...core.budget import resolve_segment

    auto = isinstance(segment, str)
    return resolve_segment(segment, steps, step_bytes(stepper) if auto else 0, default=DEFAULT_SEGMENT)


def schedule(steps) -> tuple[int, int, int, np.ndarray]:
    """(first step, spacing g, number of regular observations, indices of the requested ones)."""
    s = np.asarray(steps, dtype=np.int64).reshape(-1)
    if s.size == 0 or s[0] < 0 or np.any(np.diff(s) <= 0):
        raise ConfigError("observation steps must be non-empty, non-negative and strictly increasing.")
    gaps = np.diff(s)
    g = int(reduce(math.gcd, gaps.tolist())) if gaps.size else 1
    count = int((s[-1] - s[0]) // g) + 1
    return int(s[0]), g, count, ((s - s[0]) // g).astype(np.int64)


def _invalid(stepper, state):
    """True where the state has a non-finite x/v or a particle outside the domain interior (the Warp
    path raises there; a JAX gather would silently clip)."""
    lo, hi = stepper.inner_bounds          # the scene's, narrower for a wider shape window (cubic)
    x, v = state["x"], state["v"]
    if "domain" in state:                  # CPDI: the corners of the particles' domains
        from ...shapes.cpdi.reference import corners
        x = corners(x, state["domain"], jnp)
    return (~jnp.all(jnp.isfinite(x)) | ~jnp.all(jnp.isfinite(v)) | jnp.any((x < jnp.asarray(lo, x.dtype))
            | (x >= jnp.asarray(hi, x.dtype))))


def observe_fn(stepper, observation, steps, segment: int | str | None = None, health: bool = False,
               remat_steps: bool = True):
    """A pure function ``controls -> [T, L, d]`` (jitted): the rollout observed after each of ``steps``.

    ``segment``: steps per checkpointed segment (None: ``DEFAULT_SEGMENT``), or ``"auto"``: keep every
    step (no recomputation, F + B) when the rollout's ``steps[-1] x step_bytes`` fits the memory budget
    (``mpmlab.core.budget.resolve_segment``), else ``DEFAULT_SEGMENT``.
    ``health=True``: ``controls -> ([T, L, d], invalid)`` where ``invalid`` says whether any observed
    state had a non-finite position/velocity or a particle outside the domain interior."""
    impl = observation.implementation("jax", "observation")(observation, stepper)
    first, g, count, pick = schedule(steps)
    if not isinstance(segment, str) and segment is not None and int(segment) < 1:
        raise ConfigError(f"segment = {segment} must be >= 1 step.")
    segment, keep = resolve(stepper, segment, int(np.asarray(steps).reshape(-1)[-1]))
    dense = len(pick) != count
    adv = lambda s, p, n: advance(stepper, s, p, n, segment, keep, remat_steps)
    ckpt = (lambda f: f) if keep else jax.checkpoint

    def fn(c):
        state, params = split_controls(stepper, c)
        state = adv(state, params, first)
        y0 = impl.fn(stepper.to_scene_order(state))
        bad0 = _invalid(stepper, state)
        if count == 1:
            return (y0[None], bad0) if health else y0[None]

        @ckpt
        def interval(s, _):
            s = adv(s, params, g)
            return s, (impl.fn(stepper.to_scene_order(s)), _invalid(stepper, s))

        _, (ys, bad) = jax.lax.scan(interval, state, None, length=count - 1)
        ys = jnp.concatenate([y0[None], ys], axis=0)
        ys = ys[jnp.asarray(pick)] if dense else ys
        return (ys, bad0 | jnp.any(bad)) if health else ys

    return jax.jit(fn)


def observe(stepper, c, observation, steps, segment: int | str | None = None, health: bool = False):
    key = (id(observation), tuple(np.asarray(steps).reshape(-1).tolist()), segment, health)
    cache = stepper.__dict__.setdefault("_observe_cache", {})
    if key not in cache:
        cache[key] = (observation, observe_fn(stepper, observation, steps, segment, health))
    return cache[key][1](c)


# ---- tracking losses over rollouts of any length --------------------------------------------------
def tracking_value_and_grad(stepper, controls_fn, observations, weights, segment: int | str | None = None,
                            grad: bool = True, diverged: str = "diverged"):
    """``AutodiffAdapter.tracking_value_and_grad`` from a fixed set of compiled pieces.

    ``jax.jit`` of a whole L-step loss compiles once per L; a teacher-forced training (NCLaw Sec. 4)
    asks for ~70 lengths, each a 30-70 s compile of a 3D step and its adjoint. Here an L-step rollout
    is ``L // k`` chunks of ``k = segment`` steps and ``L % k`` single steps, run from Python: the
    forward keeps each chunk's start state, the backward replays the chunks in reverse with
    ``jax.vjp`` (each chunk rematerialised, its steps ``jax.checkpoint``-ed: the memory and the
    recomputation of ``advance``). Four programs (k steps and 1 step, forward and adjoint) plus the
    controls' parametrisation serve every length.

    ``segment="auto"``: chunks of ``DEFAULT_SEGMENT`` steps; when an L-step rollout's states and
    residuals fit the memory budget (:func:`resolve`, decided per call), the forward keeps every chunk's
    residuals (``jax.vjp`` of the plain, uncheckpointed chunk) and the backward applies them: F + B, no
    recomputation; otherwise as above."""
    impls = [(o.implementation("jax", "observation")(o, stepper), float(w))
             for o, w in zip(observations, weights) if w]
    auto = isinstance(segment, str)
    if auto:
        resolve(stepper, segment, 1)          # validates the string
    k = DEFAULT_SEGMENT if auto else max(1, int(segment or DEFAULT_SEGMENT))
    remat = jax.checkpoint(stepper.step_fn)

    def chunk(state, params, targets, scale, step=remat):
        """``len(targets[0])`` steps from ``state``: (state after them, their scaled loss, invalid)."""
        def body(carry, tgt):
            s, val, bad = carry
            s = step(s, params)
            seen = stepper.to_scene_order(s)
            for (impl, w), t in zip(impls, tgt):
                r = impl.fn(seen) - t
                val = val + w * jnp.sum(r * r) / r.size
            return (s, val, bad | _invalid(stepper, s)), None
        zero = jnp.zeros((), stepper.dtype)
        (state, val, bad), _ = jax.lax.scan(body, (state, zero, jnp.asarray(False)), targets)
        return state, val * scale, bad

    def chunk_adjoint(state, params, targets, scale, ct_state, acc):
        f = lambda s, p: (lambda o: ((o[0], o[1]), o[2]))(chunk(s, p, targets, scale))
        (_, val), pull, _ = jax.vjp(f, state, params, has_aux=True)
        ct_in, ct_p = pull((ct_state, jnp.ones_like(val)))
        return ct_in, jax.tree.map(jnp.add, acc, ct_p)

    prep = jax.jit(lambda raw, init: split_controls(stepper, controls_fn(raw, init)))
    prep_adjoint = jax.jit(lambda raw, init, ct: jax.vjp(lambda r: split_controls(stepper, controls_fn(r, init)), raw)[1](ct)[0])
    forward, adjoint = jax.jit(chunk), jax.jit(chunk_adjoint)

    def chunk_keep(state, params, targets, scale):
        """The chunk's outputs and its pullback (residuals of every step kept: no recomputation)."""
        f = lambda s, p: (lambda o: ((o[0], o[1]), o[2]))(chunk(s, p, targets, scale, stepper.step_fn))
        (state, val), pull, bad = jax.vjp(f, state, params, has_aux=True)
        return state, val, bad, pull

    def pull_adjoint(pull, ct_state, acc, one):
        ct_in, ct_p = pull((ct_state, one))
        return ct_in, jax.tree.map(jnp.add, acc, ct_p)
    forward_keep, adjoint_keep = jax.jit(chunk_keep), jax.jit(pull_adjoint)

    def pieces(L):
        """(start, length) of the chunks of an L-step rollout."""
        out = [(i * k, k) for i in range(L // k)]
        return out + [(j, 1) for j in range((L // k) * k, L)]

    def vg(raw, init, targets, scale):
        targets = [t for t, w in zip(targets, weights) if w]
        L = int(targets[0].shape[0])
        keep = grad and auto and resolve(stepper, segment, L)[1]
        state, params = prep(raw, init)
        starts, total, bad = [], jnp.zeros((), stepper.dtype), jnp.asarray(False)
        for a, m in pieces(L):
            tg = tuple(t[a:a + m] for t in targets)
            if keep:
                state, val, b, pull = forward_keep(state, params, tg, scale)
                starts.append(pull)
            else:
                starts.append(state)
                state, val, b = forward(state, params, tg, scale)
            total, bad = total + val, bad | b
        value = float(total)
        if bool(bad):
            return value, diverged, None
        if not grad:
            return value, None, None
        if not np.isfinite(value):
            return value, None, None
        ct = jax.tree.map(jnp.zeros_like, state)
        acc = jax.tree.map(jnp.zeros_like, params)
        one = jnp.ones((), stepper.dtype)
        for (a, m), s0 in zip(reversed(pieces(L)), reversed(starts)):
            if keep:
                ct, acc = adjoint_keep(s0, ct, acc, one)
            else:
                ct, acc = adjoint(s0, params, tuple(t[a:a + m] for t in targets), scale, ct, acc)
        return value, None, prep_adjoint(raw, init, (ct, acc))
    return vg


# ---- NaN gradients: find where they arose -----------------------------------------------------------
def _first_bad(tree, stepper) -> tuple[int, str] | None:
    """(particle in scene order, field) of the first non-finite entry of a state cotangent."""
    for name in ("x", "v", "C", "domain"):
        a = tree.get(name)
        if a is None:
            continue
        bad = ~np.all(np.isfinite(np.asarray(a).reshape(len(a), -1)), axis=1)
        if bad.any():
            return int(np.argmax(bad)), name
    for g, st in zip(stepper.groups, tree["law"]):
        for name, a in st.items():
            bad = ~np.all(np.isfinite(np.asarray(a).reshape(len(a), -1)), axis=1)
            if bad.any():
                return g.start + int(np.argmax(bad)), name
    return None


def _first_bad_param(tree) -> str | None:
    for path, leaf in jax.tree_util.tree_leaves_with_path(tree):
        if not np.all(np.isfinite(np.asarray(leaf))):
            return jax.tree_util.keystr(path)
    return None


def check_gradient(grads) -> bool:
    """True when every leaf of a gradient pytree is finite."""
    return all(bool(np.all(np.isfinite(np.asarray(a)))) for a in jax.tree_util.tree_leaves(grads))


def locate_nan_gradient(stepper, c, observation, steps, obs_cotangent, segment: int | str | None = None):
    """Replay the backward pass step by step and raise ``GradientError`` at the first step (counting
    backwards from the end, i.e. the order in which reverse mode runs) whose adjoint is non-finite.

    ``obs_cotangent``: dL/d(observations) [T, L, d]. States are recomputed from saved segment starts,
    so memory stays O(steps / segment + segment) here too (``segment="auto"``: every state is kept when
    they fit, :func:`resolve`). A sharded stepper replays on one device (its ``unsharded`` twin): the
    same step and particle, in scene order."""
    stepper = getattr(stepper, "unsharded", stepper)
    impl = observation.implementation("jax", "observation")(observation, stepper)
    s = np.asarray(steps, dtype=np.int64).reshape(-1)
    segment, _ = resolve(stepper, segment, int(s[-1]))
    state0, params = split_controls(stepper, c)
    step = jax.jit(stepper.step_fn)
    n = int(s[-1])
    starts = {}
    st = state0
    for k in range(n):
        if k % segment == 0:
            starts[k] = st
        st = step(st, params)
    vjp_step = jax.jit(lambda st_, p_, ct: jax.vjp(stepper.step_fn, st_, p_)[1](ct))
    vjp_obs = jax.jit(lambda st_, ct: jax.vjp(impl.fn, st_)[1](ct)[0])
    ct_obs = {int(k): obs_cotangent[i] for i, k in enumerate(s)}
    ct_state = jax.tree.map(jnp.zeros_like, st)
    if n in ct_obs:
        ct_state = jax.tree.map(jnp.add, ct_state, vjp_obs(st, ct_obs[n]))
        bad = _first_bad(ct_state, stepper)
        if bad is not None:
            raise GradientError(n, bad[0], bad[1], "the loss's derivative with respect to the observation "
                                                   "at this step is non-finite (check the loss and the data)")
    seg_cache: dict[int, Any] = {}
    for k in range(n - 1, -1, -1):            # the backward pass of step k+1 maps state k+1 -> state k
        if k not in seg_cache:
            seg_cache.clear()
            k0 = (k // segment) * segment
            cur = starts[k0]
            for j in range(k0, min(k0 + segment, n)):
                seg_cache[j] = cur
                cur = step(cur, params)
        ct_state, ct_params = vjp_step(seg_cache[k], params, ct_state)
        bad = _first_bad(ct_state, stepper)
        if bad is not None:
            raise GradientError(k + 1, bad[0], bad[1])
        name = _first_bad_param(ct_params)
        if name is not None:
            raise GradientError(k + 1, -1, f"parameter {name}")
        if k in ct_obs:
            ct_state = jax.tree.map(jnp.add, ct_state, vjp_obs(seg_cache[k], ct_obs[k]))
            bad = _first_bad(ct_state, stepper)
            if bad is not None:
                raise GradientError(k, bad[0], bad[1], "the loss's derivative with respect to the observation "
                                                       "at this step is non-finite (check the loss and the data)")
    raise GradientError(0, -1, "controls", "the step adjoints are finite: the non-finite value comes from the loss "
                                           "or the controls' parametrisation, not from the simulation")
