"""The JAX backend's :class:`~mpmlab.core.autodiff.AutodiffAdapter`: jax arrays, ``jax.value_and_grad``,
optax optimisers, pickled checkpoints, ``jax.jacfwd`` / ``jax.jacrev`` Jacobians, and NaN gradients
located by replaying the backward pass step by step (``differentiable.locate_nan_gradient``)."""
from __future__ import annotations

import os
import pickle
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from . import differentiable as JD

DTYPES = {"fp32": jnp.float32, "fp64": jnp.float64}
#: what a fit reports when the rollout's health flag fires
DIVERGED = "the rollout left the domain or became non-finite"


class JaxAdapter:
    name = "jax"
    checkpoint_suffix = "pkl"
    default_jacobian = "forward"            # one batched rollout carrying P tangents
    jacobian_modes = ("forward", "reverse")

    def __init__(self, precision: str = "fp32"):
        self.precision = precision
        self.dtype = DTYPES[precision]

    # ---- arrays ---------------------------------------------------------------------------------
    def asarray(self, a):
        return jnp.asarray(a, self.dtype)

    def numpy(self, a):
        return np.asarray(a, dtype=float)

    def tree_map(self, f, tree, *rest):
        return jax.tree.map(f, tree, *rest)

    # ---- parametrisations -----------------------------------------------------------------------
    def transform(self, kind, raw):
        if kind == "softplus":
            return jax.nn.softplus(raw)
        if kind == "exp":
            return jnp.exp(raw)
        return raw

    def mlp(self, weights):
        return [(self.asarray(W), self.asarray(b)) for W, b in weights]

    def mlp_apply(self, net, X, act):
        f = {"relu": jax.nn.relu, "tanh": jnp.tanh, "softplus": jax.nn.softplus}[act]
        h = X
        for k, (W, b) in enumerate(net):
            h = h @ W + b
            if k < len(net) - 1:
                h = f(h)
        return h[:, 0]

    def set_column(self, a, rows: slice, col: int, values):
        return a.at[rows, col].set(values)

    # ---- the differentiable rollout ---------------------------------------------------------------
    def observe(self, stepper, controls, observation, steps, segment=None):
        """``segment``: steps per recomputed segment (None: ``DEFAULT_SEGMENT``) or ``"auto"``: keep every
        step's state and residuals when they fit the memory budget (F + B instead of F + F + F + B;
        ``mpmlab.core.budget.resolve_segment``), else ``DEFAULT_SEGMENT``."""
        return JD.observe(stepper, controls, observation, steps, segment, health=True)

    # ---- gradients -------------------------------------------------------------------------------
    def value_and_grad(self, loss):
        """``loss(raw, *data) -> (value, invalid)`` -> ``(raw, *data) -> (value, why or None, grad or None)``;
        the gradient is w.r.t. ``raw`` only, ``data`` (arrays) are traced arguments: new values of the
        same shapes reuse the compiled function."""
        vg = jax.jit(jax.value_and_grad(loss, has_aux=True))

        def value_and_grad(raw, *data):
            (val, bad), g = vg(raw, *data)
            val = float(val)
            if bool(bad):
                return val, DIVERGED, None
            return val, None, (g if np.isfinite(val) else None)
        return value_and_grad

    def value(self, loss, raw, *data):
        """The loss alone; NaN for a rollout that left the domain or became non-finite."""
        val, bad = loss(raw, *data)
        return float("nan") if bool(bad) else float(val)

    def tracking_value_and_grad(self, stepper, controls, observations, weights, segment=None, grad=True):
        """A fixed set of compiled pieces for every rollout length (``differentiable.tracking_value_and_grad``;
        ``segment="auto"`` keeps each call's chunk residuals when the rollout fits the memory budget)."""
        return JD.tracking_value_and_grad(stepper, controls, observations, weights, segment, grad, DIVERGED)

    def check_gradient(self, grad):
        return JD.check_gradient(grad)

    def grad_norm(self, grad):
        import optax

        return float(optax.global_norm(grad))

    def locate_nan_gradient(self, stepper, controls, observation, steps, data_loss, segment=None):
        pred = stepper.observe(controls, observation, steps, segment)
        ct = jax.grad(data_loss)(pred)
        JD.locate_nan_gradient(stepper, controls, observation, steps, ct, segment)

    # ---- optax --------------------------------------------------------------------------------------
    def optimizer_from_config(self, optimizer_node, schedule_node, learning_rate):
        """An optax GradientTransformation; the schedule (optax, e.g. ``exponential_decay``) is its learning
        rate, so the returned schedule is None."""
        from hydra.utils import instantiate

        if schedule_node is not None:
            kw = {"learning_rate": instantiate(schedule_node)}
        else:
            kw = {} if "learning_rate" in optimizer_node else {"learning_rate": float(learning_rate)}
        return instantiate(optimizer_node, **kw), None

    def optimizer_init(self, optimizer, schedule, raw):
        """``optimizer``: an optax GradientTransformation, or a callable ``schedule -> transformation``."""
        opt = optimizer(schedule) if callable(optimizer) else optimizer
        return raw, (opt, opt.init(raw))

    def optimizer_step(self, state, raw, grad, scale=1.0):
        import optax

        opt, opt_state = state
        updates, opt_state = opt.update(grad, opt_state, raw)
        if scale != 1.0:
            updates = jax.tree.map(lambda u: u * scale, updates)
        return optax.apply_updates(raw, updates), (opt, opt_state)

    def grouped_optimizer(self, names, groups, schedule, epochs):
        """One Adam per group ``{label: {lr, clip, params}}``: ``optax.multi_transform`` of
        ``clip_by_global_norm(clip)`` (the group's own norm) then ``adam`` at the group's learning rate,
        decayed to 0 over ``epochs`` by ``cosine_decay_schedule`` (= torch's CosineAnnealingLR(T_max=epochs)
        stepped once per epoch) or constant."""
        import optax

        label_of = {n: label for label, g in groups.items() for n in g["params"]}
        tx = {}
        for label, g in groups.items():
            lr = optax.cosine_decay_schedule(g["lr"], int(epochs)) if schedule == "cosine" else g["lr"]
            parts = [optax.clip_by_global_norm(g["clip"])] if g["clip"] is not None else []
            tx[label] = optax.chain(*parts, optax.adam(lr))
        return optax.multi_transform(tx, {n: label_of[n] for n in names}), None

    def save_checkpoint(self, path, epoch, history, raw, state):
        path = Path(path)
        tmp = path.with_name(path.name + ".tmp")
        with open(tmp, "wb") as f:
            pickle.dump({"epoch": epoch, "history": history, "raw": jax.device_get(raw),
                         "opt_state": jax.device_get(state[1])}, f)
        os.replace(tmp, path)

    def load_checkpoint(self, path, raw, state):
        with open(path, "rb") as f:
            ck = pickle.load(f)
        raw = jax.tree.map(lambda a: self.asarray(a), ck["raw"])
        opt_state = jax.tree.map(lambda ref, a: jnp.asarray(a, ref.dtype) if hasattr(ref, "dtype") else a,
                                 state[1], ck["opt_state"])
        return ck["epoch"], ck["history"], raw, (state[0], opt_state)

    # ---- least squares ---------------------------------------------------------------------------------
    def residual_functions(self, observe, reference, mask, scale, mode):
        """The residuals in the stepper's precision inside one jitted function; Jacobians by
        ``jax.jacfwd`` (one rollout carrying P tangents) or ``jax.jacrev`` (N cotangents)."""
        ref, m = self.asarray(reference), self.asarray(mask)[..., None]

        def resid(x):
            pred, bad = observe(x)
            return ((pred - ref) * m).ravel() * scale, bad

        f = jax.jit(resid)

        def residual(x):
            r, bad = f(self.asarray(x))
            r = np.asarray(r, np.float64)
            return None if bool(bad) or not np.all(np.isfinite(r)) else r

        if mode not in self.jacobian_modes:
            return residual, None

        def with_aux(x):
            r, bad = resid(x)
            return r, (r, bad)
        jf = jax.jit((jax.jacfwd if mode == "forward" else jax.jacrev)(with_aux, has_aux=True))

        def jacobian(x, r_known=None):      # the primal comes with the derivatives
            J, (r, bad) = jf(self.asarray(x))
            return np.asarray(r, np.float64), np.asarray(J, np.float64), bool(bad)
        return residual, jacobian

    # ---- the task ------------------------------------------------------------------------------------
    def before_build(self, task_config):
        if not task_config.get("jax_ynn_fusions", False):
            from .xla_options import disable_ynn_fusions

            disable_ynn_fusions()
