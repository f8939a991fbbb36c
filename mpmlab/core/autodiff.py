"""The one seam between the differentiable workflows and a backend's arrays: :class:`AutodiffAdapter`.

A backend's differentiable surface is its own (JAX: jax arrays under ``jax.grad``; Warp: torch tensors
through ``torch.autograd.Function``). The workflows above the stepper (``mpmlab/inverse/``,
``task=inverse``, and whatever trains through rollouts next) do not name a backend. They get an
adapter from :func:`adapter` and do everything array-shaped through it: they convert NumPy to and
from the backend's arrays, parametrise controls, take a loss's value and gradient, step an optimiser,
checkpoint it, locate a non-finite gradient, and build the residuals and Jacobian of a least-squares
fit.

Controls are a generic pytree, nested dicts, tuples and lists of the backend's arrays
(``AbstractStepper.controls()``). Adapters never list its keys, so keys a stepper adds (``law_weights``,
``law_state``, ...) flow through.

Finding a backend's adapter
---------------------------
``adapter(stepper)`` builds ``cls(stepper.precision)``, where ``cls`` is the first of:

1. ``stepper.autodiff_adapter``, if the stepper class defines it (for a stepper that is not the
   backend's usual one, such as a reduced-order stepper);
2. ``autodiff_adapter`` of the backend registered under ``stepper.backend_name`` in
   ``mpmlab.core.registry.backends`` (the built-ins: ``JaxBackend``, ``WarpBackend``; a third-party
   backend from the ``mpmlab.backends`` entry point sets it on its backend class).

Either may be the class or a ``"package.module:Class"`` string, which is imported when first needed.
Importing this module imports neither JAX nor Warp nor torch. A backend without an adapter raises a
``ConfigError`` that says so.

Built-ins: ``mpmlab.backends.jax.adapter:JaxAdapter`` and ``mpmlab.backends.warp.adapter:WarpAdapter``.
:func:`missing_members` lists what an object lacks of the protocol, for a plugin's own tests.
"""
from __future__ import annotations

from typing import Any, Callable, Mapping, NoReturn, Protocol, Sequence, runtime_checkable

import numpy as np

from .errors import ConfigError

#: Jacobian modes an adapter may offer to least-squares fits (``AutodiffAdapter.residual_functions``).
#: ``central`` (finite differences of the residual) is done by the workflow on any backend.
AD_JACOBIANS = ("forward", "reverse")

Array = Any       # the backend's differentiable array (jax.Array, torch.Tensor, ...)
Tree = Any        # nested dict / tuple / list of Arrays (controls, trainable values, gradients)
#: numpy x [P] -> residuals r [N] (float64), or None when the rollout diverged or r is not finite
Residual = Callable[[np.ndarray], "np.ndarray | None"]
#: (numpy x [P], residuals at x if known) -> (r [N] or None, J [N, P] or None, diverged)
Jacobian = Callable[..., "tuple[np.ndarray | None, np.ndarray | None, bool]"]


@runtime_checkable
class AutodiffAdapter(Protocol):
    """What the differentiable workflows need from a backend. One instance per precision.

    Attributes
    ----------
    name: the backend's registry name (``"jax"``, ``"warp"``); reports and error messages use it.
    dtype: the float dtype of the arrays ``asarray`` makes (the stepper's precision).
    checkpoint_suffix: the file suffix of the gradient optimiser's checkpoint (``"pkl"``, ``"pt"``).
    default_jacobian: the Jacobian mode a least-squares fit takes under ``jacobian: auto``: one of
        ``jacobian_modes``, or ``"central"``.
    jacobian_modes: the AD modes ``residual_functions`` offers, a subset of ``AD_JACOBIANS``.
    """

    name: str
    dtype: Any
    checkpoint_suffix: str
    default_jacobian: str
    jacobian_modes: tuple[str, ...]

    # ---- arrays ---------------------------------------------------------------------------------
    def asarray(self, a) -> Array:
        """NumPy (or a scalar or a list) -> the backend's array in ``dtype``; not a trainable leaf."""

    def numpy(self, a) -> np.ndarray:
        """The backend's array -> a float NumPy array (detached from any graph)."""

    def tree_map(self, f: Callable, tree: Tree, *rest: Tree) -> Tree:
        """``f`` over the leaves of ``tree`` (and the matching leaves of ``rest``), structure kept."""

    # ---- parametrisations (mpmlab.inverse.parameters) ---------------------------------------------
    def transform(self, kind: str, raw: Array) -> Array:
        """``identity``, ``softplus`` or ``exp`` of a raw trainable value."""

    def mlp(self, weights: Sequence[tuple[np.ndarray, np.ndarray]]) -> Any:
        """A trainable MLP from NumPy layers ``[(W [in, out], b [out]), ...]``."""

    def mlp_apply(self, net: Any, X: Array, activation: str) -> Array:
        """The MLP at inputs ``X`` [n, in] -> [n] (the hidden layers use ``activation``; the last is linear)."""

    def set_column(self, a: Array, rows: slice, col: int, values) -> Array:
        """A copy of ``a`` with ``a[rows, col] = values`` (differentiable in ``a`` and ``values``)."""

    # ---- the differentiable rollout ---------------------------------------------------------------
    def observe(self, stepper, controls: Tree, observation, steps, segment: int | None = None) -> tuple[Array, Any]:
        """``(stepper.observe(controls, ...), invalid)``. ``invalid`` is a backend bool (traceable) that is
        true when an observed state left the domain or became non-finite. A backend that raises
        ``SimulationDiverged`` itself returns False."""

    # ---- gradients -------------------------------------------------------------------------------
    def value_and_grad(self, loss: Callable[[Tree], tuple[Array, Any]]
                       ) -> Callable[[Tree], tuple[float, str | None, Any]]:
        """``loss(raw) -> (scalar, invalid)`` -> ``vg(raw) -> (value, why, grad)``. ``why`` says why the rollout
        is unusable (it diverged) or is None. ``grad`` is None when ``why`` is set or the value is not
        finite; otherwise it is what ``check_gradient``, ``grad_norm`` and ``optimizer_step`` take. ``raw``
        is the trainable tree that ``optimizer_init`` returned."""

    def value(self, loss: Callable[[Tree], tuple[Array, Any]], raw: Tree) -> float:
        """``loss(raw)[0]`` as a float, without a gradient; NaN when the rollout diverged."""

    def tracking_value_and_grad(self, stepper, controls: Callable[[Tree, Tree], Tree], observations: Sequence,
                                weights: Sequence[float], segment: int | None = None, grad: bool = True
                                ) -> Callable[..., tuple[float, str | None, Any]]:
        """A tracking loss over rollouts of any length: ``vg(raw, init, targets, scale) -> (value, why, grad)``
        with ``value = scale * sum_t sum_i weights[i] * mean((observations[i] after step t - targets[i][t-1])^2)``
        for t = 1..L, where L = ``len(targets[0])`` may change from call to call and the rollout starts from
        ``controls(raw, init)``. ``why`` and ``grad`` as in ``value_and_grad`` (``grad=False``: the value alone,
        ``grad`` None). :func:`tracking_loss` builds it from ``observe`` and ``value_and_grad``; a backend
        whose compiled programs depend on L (JAX) supplies one that compiles a fixed set of pieces."""

    def check_gradient(self, grad: Any) -> bool:
        """True when every entry of ``grad`` is finite."""

    def grad_norm(self, grad: Any) -> float:
        """The global L2 norm of ``grad``."""

    def locate_nan_gradient(self, stepper, controls: Tree, observation, steps, data_loss: Callable[[Array], Array],
                            segment: int | None = None) -> NoReturn:
        """Raise ``GradientError`` naming the step (and particle) where the adjoint of
        ``data_loss(stepper.observe(controls, ...))`` first becomes non-finite. If the rollout's adjoints
        are finite, the step is 0 and the error says the loss or the parametrisation is to blame."""

    # ---- gradient optimisers ------------------------------------------------------------------------
    def optimizer_from_config(self, optimizer_node, schedule_node, learning_rate: float) -> tuple[Any, Any]:
        """``(optimizer, schedule)`` from the task's ``_target_`` nodes (schedule_node may be None). These
        are what ``optimizer_init`` takes."""

    def optimizer_init(self, optimizer, schedule, raw: Tree) -> tuple[Tree, Any]:
        """``(raw, state)``: the trainable tree (made trainable where the backend needs it) and the
        optimiser's state."""

    def optimizer_step(self, state: Any, raw: Tree, grad: Any, scale: float = 1.0) -> tuple[Tree, Any]:
        """One optimiser (and schedule) step: the new ``(raw, state)``. ``scale`` multiplies the update
        (``raw + scale * (step(raw) - raw)``; the optimiser's moments are those of the unscaled step), which
        for Adam without weight decay is the step at ``scale`` times the learning rate."""

    def save_checkpoint(self, path, epoch: int, history: list, raw: Tree, state: Any) -> None:
        """Write ``epoch``, ``history``, ``raw`` and the optimiser state to ``path`` atomically."""

    def load_checkpoint(self, path, raw: Tree, state: Any) -> tuple[int, list, Tree, Any]:
        """``(epoch, history, raw, state)`` from a checkpoint that ``save_checkpoint`` wrote. ``raw`` and
        ``state`` from ``optimizer_init`` are the templates."""

    # ---- least squares (mpmlab.inverse.lm) ------------------------------------------------------------
    def residual_functions(self, observe: Callable[[Array], tuple[Array, Any]], reference: np.ndarray,
                           mask: np.ndarray, scale: float, mode: str) -> tuple[Residual, Jacobian | None]:
        """The residuals ``r(x) = ((observe(x)[0] - reference) * mask[..., None]).ravel() * scale`` as
        NumPy float64 callables, where ``observe(x)`` takes the parameter vector as a backend array [P].
        Returns ``(residual, jacobian)``: ``jacobian`` for ``mode`` in ``jacobian_modes`` (AD; the residuals
        come with it), or None for ``mode == "central"`` (the caller differences ``residual``)."""

    # ---- the task ------------------------------------------------------------------------------------
    def before_build(self, task_config: Mapping[str, Any]) -> None:
        """Called by ``task=inverse`` before the stepper is built, with the task's config. The JAX adapter
        uses it to turn off XLA CPU's YNNPACK fusions unless ``task.jax_ynn_fusions`` is set."""


def tracking_loss(adapter, stepper, controls, observations, weights, segment=None, grad=True):
    """``AutodiffAdapter.tracking_value_and_grad`` from the adapter's ``observe`` and ``value_and_grad``:
    one loss per rollout length, built when that length is first asked for (right for a backend that
    compiles nothing per length, such as Warp)."""
    pairs = [(o, float(w)) for o, w in zip(observations, weights) if w]
    by_length: dict[int, Callable] = {}

    def build(length: int):
        steps = np.arange(1, length + 1)

        def loss(raw, init, targets, scale):
            c = controls(raw, init)
            val, bad = 0.0, False
            for (obs, w), tgt in zip(pairs, targets):
                y, b = adapter.observe(stepper, c, obs, steps, segment)
                r = y - tgt
                val = val + w * (r * r).sum() / (r[0].numel() if hasattr(r, "numel") else r[0].size)
                bad = bad | b
            return val * scale, bad
        if grad:
            return adapter.value_and_grad(loss)
        return lambda raw, *data: (adapter.value(loss, raw, *data), None, None)

    def vg(raw, init, targets, scale):
        targets = [t for t, w in zip(targets, weights) if w]
        L = int(targets[0].shape[0])
        if L not in by_length:
            by_length[L] = build(L)
        return by_length[L](raw, init, targets, scale)
    return vg


def _resolve(target, where: str):
    if isinstance(target, str):
        from .registry import load_object

        try:
            return load_object(target)
        except (ImportError, AttributeError) as exc:
            raise ConfigError(f"{where} = '{target}' cannot be imported ({type(exc).__name__}: {exc}).") from None
    return target


def adapter_class(backend: str, stepper=None) -> type:
    """The adapter class of ``stepper`` (if given and it names one) or of the registered ``backend``."""
    target = getattr(type(stepper), "autodiff_adapter", None) if stepper is not None else None
    if target is not None:
        return _resolve(target, f"{type(stepper).__name__}.autodiff_adapter")
    from .registry import backends

    cls = backends.get(backend)
    target = getattr(cls, "autodiff_adapter", None)
    if target is None:
        raise ConfigError(f"backend '{backend}' has no autodiff adapter (an 'autodiff_adapter' attribute on its "
                          f"backend class, mpmlab.core.autodiff): the differentiable workflows (task=inverse) "
                          f"cannot drive it; use backend=jax or backend=warp.")
    return _resolve(target, f"{getattr(cls, '__name__', backend)}.autodiff_adapter")


def adapter_for_backend(backend: str, precision: str = "fp32") -> AutodiffAdapter:
    """The adapter of the registered ``backend`` at ``precision`` (``fp32``/``fp64``)."""
    return adapter_class(backend)(precision)


def adapter(stepper) -> AutodiffAdapter:
    """The adapter for ``stepper``'s arrays (see the module docstring for the lookup)."""
    return adapter_class(stepper.backend_name, stepper)(stepper.precision)


def missing_members(obj) -> list[str]:
    """The protocol's attributes and methods that ``obj`` lacks (``[]``: it satisfies the protocol).
    ``isinstance(obj, AutodiffAdapter)`` checks the same names; this names the missing ones."""
    names = {n for n in vars(AutodiffAdapter) if not n.startswith("_")} | set(AutodiffAdapter.__annotations__)
    return sorted(n for n in names if not hasattr(obj, n))
