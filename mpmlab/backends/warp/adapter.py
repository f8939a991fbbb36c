"""The Warp backend's :class:`~mpmlab.core.autodiff.AutodiffAdapter`. The differentiable surface is torch
tensors: ``stepper.observe`` is a ``torch.autograd.Function`` (``grad.py``) that recomputes segments
under ``wp.Tape`` -- or, with ``segment="auto"`` when the rollout's step buffers fit the memory budget
(``mpmlab.core.budget.resolve_segment``), keeps the forward pass's recording and recomputes nothing;
``segment`` passes through :meth:`WarpAdapter.observe` and the tracking loss unchanged. P2G and G2P
run their hand-written adjoints on the tape (``adjoints.py``). Gradients come from ``backward()``,
optimisers are ``torch.optim`` (plus an optional ``lr_scheduler``), and checkpoints are written with
``torch.save``.

A non-finite adjoint inside the rollout raises ``GradientError`` in the bridge itself, so
``locate_nan_gradient`` only has to name what the bridge cannot see: the loss or the parametrisation.

Jacobians of least-squares residuals: Warp's tape has no forward mode, so ``jacobian: auto`` means
central differences (2P rollouts, done by the workflow). ``reverse`` gives the rows by reverse mode
instead: one forward rollout, then one backward pass (a full segment recompute under the tape) per
residual that the mask keeps. A backward pass costs 2-3 forward rollouts, so this pays off only with
fewer residuals than about the parameter count (measured in ``mpmlab/inverse/lm.py``'s docstring).
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

from ...core.errors import GradientError, SimulationDiverged

DTYPES = {"fp32": torch.float32, "fp64": torch.float64}
_ACT = {"relu": torch.relu, "tanh": torch.tanh, "softplus": torch.nn.functional.softplus}


def _leaves(tree):
    """Tensors of a dict / tuple / list tree in order (an ``nn.Module``: its parameters)."""
    if isinstance(tree, torch.nn.Module):
        return list(tree.parameters())
    if isinstance(tree, dict):
        return [t for v in tree.values() for t in _leaves(v)]
    if isinstance(tree, (list, tuple)):
        return [t for v in tree for t in _leaves(v)]
    return [tree] if isinstance(tree, torch.Tensor) else []


def _map(f, tree, *rest):
    if isinstance(tree, dict):
        return type(tree)((k, _map(f, v, *(r[k] for r in rest))) for k, v in tree.items())
    if isinstance(tree, (list, tuple)) and not hasattr(tree, "_fields"):
        return type(tree)(_map(f, v, *(r[i] for r in rest)) for i, v in enumerate(tree))
    if isinstance(tree, tuple):                    # a NamedTuple
        return type(tree)(*(_map(f, v, *(r[i] for r in rest)) for i, v in enumerate(tree)))
    return f(tree, *rest)


class GroupClippedAdam(torch.optim.Adam):
    """Adam whose parameter groups are each clipped to their own gradient norm (``clip``) before the
    step: NCLaw's ``clip_grad_norm_(net.parameters(), 0.1)`` per network. A non-finite norm raises
    (``error_if_nonfinite``): a NaN gradient is never scaled into the weights."""

    def step(self, closure=None):
        for g in self.param_groups:
            if g.get("clip") is not None:
                torch.nn.utils.clip_grad_norm_([q for q in g["params"] if q.grad is not None], g["clip"],
                                               error_if_nonfinite=True)
        return super().step(closure)


class WarpAdapter:
    name = "warp"
    checkpoint_suffix = "pt"
    default_jacobian = "central"            # the tape has no forward mode
    jacobian_modes = ("reverse",)

    def __init__(self, precision: str = "fp32"):
        self.precision = precision
        self.dtype = DTYPES[precision]

    # ---- arrays ---------------------------------------------------------------------------------
    def asarray(self, a):
        return torch.as_tensor(np.asarray(a), dtype=self.dtype)

    def numpy(self, a):
        return a.detach().cpu().numpy().astype(float)

    def tree_map(self, f, tree, *rest):
        return _map(f, tree, *rest)

    # ---- parametrisations -----------------------------------------------------------------------
    def transform(self, kind, raw):
        if kind == "softplus":
            return torch.nn.functional.softplus(raw)
        if kind == "exp":
            return torch.exp(raw)
        return raw

    def mlp(self, weights):
        """A list of ``nn.Linear`` (``optimizer_init`` wraps it in an ``nn.ModuleList``)."""
        layers = []
        for W, b in weights:
            lin = torch.nn.Linear(W.shape[0], W.shape[1]).to(self.dtype)
            with torch.no_grad():
                lin.weight.copy_(torch.as_tensor(W.T))
                lin.bias.copy_(torch.as_tensor(b))
            layers.append(lin)
        return layers

    def mlp_apply(self, net, X, act):
        f = _ACT[act]
        h = X
        for k, lin in enumerate(net):
            h = lin(h)
            if k < len(net) - 1:
                h = f(h)
        return h[:, 0]

    def set_column(self, a, rows: slice, col: int, values):
        out = a.clone()
        out[rows, col] = values
        return out

    # ---- the differentiable rollout ---------------------------------------------------------------
    def observe(self, stepper, controls, observation, steps, segment=None):
        """The bridge raises ``SimulationDiverged`` itself: ``invalid`` is always False."""
        return stepper.observe(controls, observation, steps, segment), False

    # ---- gradients -------------------------------------------------------------------------------
    def value_and_grad(self, loss):
        """``loss(raw, *data) -> (value, invalid)`` -> ``(raw, *data) -> (value, why or None, grads or None)``
        (gradients of ``raw``'s leaves, in order)."""
        def value_and_grad(raw, *data):
            params = _leaves(raw)
            for q in params:                 # what optimizer.zero_grad() does (set_to_none)
                q.grad = None
            try:
                val = loss(raw, *data)[0]
            except SimulationDiverged as exc:
                return float("nan"), f"the rollout diverged ({exc})", None
            v = float(val.detach())
            if not np.isfinite(v):
                return v, None, None
            val.backward()                   # a non-finite adjoint raises GradientError in the bridge
            return v, None, [q.grad for q in params]
        return value_and_grad

    def value(self, loss, raw, *data):
        """The loss alone; NaN for a rollout that diverges (as ``value_and_grad`` reports it)."""
        try:
            with torch.no_grad():
                return float(loss(raw, *data)[0])
        except SimulationDiverged:
            return float("nan")

    def tracking_value_and_grad(self, stepper, controls, observations, weights, segment=None, grad=True):
        """Warp compiles nothing per rollout length: one loss per length, from ``observe``."""
        from ...core.autodiff import tracking_loss

        return tracking_loss(self, stepper, controls, observations, weights, segment, grad)

    def check_gradient(self, grad):
        return all(bool(torch.isfinite(g).all()) for g in grad if g is not None)

    def grad_norm(self, grad):
        return float(torch.sqrt(sum((g.detach() ** 2).sum() for g in grad if g is not None)))

    def locate_nan_gradient(self, stepper, controls, observation, steps, data_loss, segment=None):
        c = self.tree_map(lambda a: a.detach().clone().requires_grad_(True) if isinstance(a, torch.Tensor) else a,
                          controls)
        data_loss(stepper.observe(c, observation, steps, segment)).backward()   # the bridge raises first
        raise GradientError(0, -1, "controls", "the step adjoints are finite: the non-finite value comes from the "
                                               "loss or the controls' parametrisation, not from the simulation")

    # ---- torch.optim --------------------------------------------------------------------------------
    def optimizer_from_config(self, optimizer_node, schedule_node, learning_rate):
        """``params -> torch.optim optimiser`` and ``optimiser -> lr_scheduler`` (or None)."""
        from hydra.utils import instantiate

        kw = {} if "lr" in optimizer_node else {"lr": float(learning_rate)}
        optimizer = (lambda prm: instantiate(optimizer_node, prm, **kw))
        schedule = (lambda opt: instantiate(schedule_node, opt)) if schedule_node is not None else None
        return optimizer, schedule

    def optimizer_init(self, optimizer, schedule, raw):
        """Trainable leaves: each tensor a clone that requires grad, an MLP an ``nn.ModuleList``."""
        raw = dict(raw)
        for name, r in raw.items():
            raw[name] = torch.nn.ModuleList(r) if isinstance(r, list) else r.clone().requires_grad_(True)
        opt = optimizer(_leaves(raw))
        sched = schedule(opt) if schedule is not None else None
        return raw, (opt, sched)

    def grouped_optimizer(self, names, groups, schedule, epochs):
        """One Adam per group ``{label: {lr, clip, params}}`` (``GroupClippedAdam``: torch.optim.Adam with one
        param group per label, each clipped to its own gradient norm before the step) and, for
        ``schedule: cosine``, ``CosineAnnealingLR(T_max=epochs)`` stepped once per epoch."""
        def optimizer(params):
            by_name = dict(zip(names, params))
            return GroupClippedAdam([{"params": [by_name[n] for n in g["params"]], "lr": g["lr"], "clip": g["clip"],
                                      "label": label} for label, g in groups.items()])
        sched = ((lambda opt: torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=int(epochs)))
                 if schedule == "cosine" else None)
        return optimizer, sched

    def optimizer_step(self, state, raw, grad, scale=1.0):
        opt, sched = state
        leaves = _leaves(raw)
        for q, g in zip(leaves, grad or ()):       # gradients summed on the host (teacher forcing)
            if g is not None and q.grad is not g:
                q.grad = g
        before = [q.detach().clone() for q in leaves] if scale != 1.0 else None
        opt.step()
        if before is not None:
            with torch.no_grad():
                for q, b in zip(leaves, before):
                    q.copy_(b + scale * (q - b))
        if sched is not None:
            sched.step()
        return raw, state

    def save_checkpoint(self, path, epoch, history, raw, state):
        opt, sched = state
        path = Path(path)
        values = {k: (r.state_dict() if isinstance(r, torch.nn.Module) else r.detach().clone()) for k, r in raw.items()}
        tmp = path.with_name(path.name + ".tmp")
        torch.save({"epoch": epoch, "history": history, "raw": values, "opt": opt.state_dict(),
                    "sched": sched.state_dict() if sched is not None else None}, tmp)
        os.replace(tmp, path)

    def load_checkpoint(self, path, raw, state):
        opt, sched = state
        ck = torch.load(path, weights_only=False)
        with torch.no_grad():
            for k, r in raw.items():
                if isinstance(r, torch.nn.Module):
                    r.load_state_dict(ck["raw"][k])
                else:
                    r.copy_(ck["raw"][k])
        opt.load_state_dict(ck["opt"])
        if sched is not None and ck.get("sched") is not None:
            sched.load_state_dict(ck["sched"])
        return ck["epoch"], ck["history"], raw, state

    # ---- least squares ---------------------------------------------------------------------------------
    def residual_functions(self, observe, reference, mask, scale, mode):
        """The residuals in NumPy float64 from the rollout's observations; ``reverse``: the Jacobian's rows
        by one backward pass each (rows the mask drops are zero and cost nothing)."""
        ref = np.asarray(reference, np.float64)
        m = np.asarray(mask, np.float64)[..., None]

        def resid_of(pred):
            return ((self.numpy(pred).astype(np.float64) - ref) * m).ravel() * scale

        def residual(x):
            try:
                with torch.no_grad():
                    pred, _ = observe(self.asarray(x))
            except SimulationDiverged:
                return None
            r = resid_of(pred)
            return r if np.all(np.isfinite(r)) else None

        if mode not in self.jacobian_modes:
            return residual, None
        weight = np.broadcast_to(m, ref.shape).ravel() * scale

        def jacobian(x, r_known=None):
            xt = self.asarray(x).requires_grad_(True)
            try:
                pred, _ = observe(xt)
            except SimulationDiverged:
                return None, None, True
            r = resid_of(pred)
            if not np.all(np.isfinite(r)):
                return r, None, True
            flat = pred.reshape(-1)
            J = np.zeros((r.size, xt.numel()))
            rows = np.nonzero(weight)[0]
            for k, i in enumerate(rows):
                g, = torch.autograd.grad(flat[i], xt, retain_graph=k + 1 < len(rows))
                J[i] = g.detach().cpu().numpy().astype(np.float64) * weight[i]
            return r, J, False
        return residual, jacobian

    # ---- the task ------------------------------------------------------------------------------------
    def before_build(self, task_config):
        return None
