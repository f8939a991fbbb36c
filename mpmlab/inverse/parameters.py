"""What an inverse fit adjusts, and how (JAX-MPM Sec. 3.2, Fig. 2).

A :class:`FitParameter` names a *target* in the rollout controls (``AbstractStepper.controls``) and a
*form* for it:

* ``initial_velocity`` of a body (one ``component``): ``scalar`` -- v = theta * basis(x) with ``basis``
  an expression of the coordinates (JAX-MPM Sec. 5.1: ``basis: "H0 - y"``), ``mlp`` -- v = N_theta(x)
  over the ``inputs`` coordinates (Sec. 5.2, three hidden ReLU layers of 30);
* ``law`` parameter of a body: ``scalar`` (one value for the body);
* ``boundary`` data (``friction_walls`` ``mu`` per segment or per node, ``plane`` ``friction``):
  ``array`` (Sec. 5.3) or ``scalar``;
* ``gravity``: ``array``;
* ``law_weights`` of a body's law (its shared arrays, e.g. a neural law's matrices; ``field`` names
  the array): ``array`` (every entry; ``init`` omitted: the law's own initial weights).

``transform`` reparameterises the trainable value: ``identity``, ``softplus`` (positive; JAX-MPM's
friction), ``exp`` (positive, log-scale steps). ``init`` and ``truth`` are in physical units; a field's
truth is an expression of x, y, z and the fit's ``constants``.

The same code serves every backend: the array operations (``asarray``, ``transform``, ``mlp``,
``mlp_apply``, ``set_column``, ``numpy``) are those of the backend's
:class:`~mpmlab.core.autodiff.AutodiffAdapter`, passed in as ``ops``. The trainable values are then a
JAX pytree (optax) or torch tensors and ``nn.Linear`` layers (torch.optim). MLP weights start from the
same NumPy draw (Glorot-uniform, ``seed``) on every backend.
"""
from __future__ import annotations

import math
import dataclasses
from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np

from ..core.errors import ConfigError

TARGETS = ("initial_velocity", "law", "boundary", "gravity", "law_weights")
FORMS = ("scalar", "array", "mlp")
TRANSFORMS = ("identity", "softplus", "exp")
ACTIVATIONS = ("relu", "tanh", "softplus")

_EXPR_NAMES = {k: getattr(np, k) for k in ("sin", "cos", "tan", "exp", "log", "sqrt", "abs", "tanh", "minimum",
                                           "maximum", "where")}
_EXPR_NAMES.update(pi=math.pi, e=math.e)


def eval_expression(expr: str, coords: Mapping[str, np.ndarray], constants: Mapping[str, float], where: str) -> np.ndarray:
    """Evaluate a field expression such as ``"2*(1-(y/H0)**2) + 0.2*sin(4*pi*y/H0)"`` at the particles.

    Only NumPy's elementary functions, the coordinates (x, y, z) and the fit's ``constants`` are in
    scope."""
    scope = dict(_EXPR_NAMES)
    scope.update({k: float(v) for k, v in constants.items()})
    scope.update(coords)
    try:
        out = eval(compile(str(expr), "<expression>", "eval"), {"__builtins__": {}}, scope)  # noqa: S307
    except Exception as exc:  # a user's expression: report it in one line
        raise ConfigError(f"{where}: cannot evaluate expression '{expr}' ({type(exc).__name__}: {exc}); "
                          f"it may use x, y, z, {', '.join(sorted(constants)) or 'no constants'} and numpy "
                          f"functions ({', '.join(sorted(_EXPR_NAMES))}).") from None
    n = len(next(iter(coords.values())))
    return np.broadcast_to(np.asarray(out, dtype=float), (n,)).copy()


def _inv_transform(kind: str, value: np.ndarray) -> np.ndarray:
    value = np.asarray(value, float)
    if kind == "identity":
        return value
    if np.any(value <= 0):
        raise ConfigError(f"transform '{kind}' needs a positive initial value, got {value.tolist()}.")
    if kind == "exp":
        return np.log(value)
    return value + np.log(-np.expm1(-value))      # inverse softplus, stable


def glorot_mlp(sizes: Sequence[int], seed: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Glorot-uniform weights, zero biases: [(W [in, out], b [out]), ...]."""
    rng = np.random.default_rng(seed)
    out = []
    for a, b in zip(sizes[:-1], sizes[1:]):
        lim = math.sqrt(6.0 / (a + b))
        out.append((rng.uniform(-lim, lim, (a, b)), np.zeros(b)))
    return out


def ops_for(backend: str, precision: str):
    """The autodiff adapter (:mod:`mpmlab.core.autodiff`) of the registered ``backend``; ``Fit`` takes
    its stepper's adapter itself."""
    from ..core.autodiff import adapter_for_backend

    return adapter_for_backend(backend, precision)


# ---- one fitted quantity ---------------------------------------------------------------------------------
@dataclass
class FitParameter:
    name: str
    target: str
    form: str = "scalar"
    body: str | None = None
    component: str | None = None
    param: str | None = None
    boundary: str | None = None
    field: str | None = None
    basis: str | None = None
    inputs: Sequence[str] = ("y",)
    hidden: Sequence[int] = (30, 30, 30)
    activation: str = "relu"
    init: Any = None
    truth: Any = None
    transform: str = "identity"
    seed: int = 0
    constants: Mapping[str, float] = dataclasses.field(default_factory=dict)

    # filled by bind()
    _rows: Any = None
    _col: int = 0
    _index: int = 0
    _basis: np.ndarray | None = None
    _X: np.ndarray | None = None
    _size: int = 1
    _wshape: tuple = ()
    _winit: np.ndarray | None = None

    def where(self) -> str:
        return f"task.parameters.{self.name}"

    def bind(self, scene, stepper, boundary_names: Sequence[str]) -> "FitParameter":
        """Resolve the target against a built scene/stepper; every mistake is a ConfigError naming the key."""
        w = self.where()
        if self.target not in TARGETS:
            raise ConfigError(f"{w}.target = '{self.target}' unknown; use one of {TARGETS}.")
        if self.form not in FORMS:
            raise ConfigError(f"{w}.form = '{self.form}' unknown; use one of {FORMS}.")
        if self.transform not in TRANSFORMS:
            raise ConfigError(f"{w}.transform = '{self.transform}' unknown; use one of {TRANSFORMS}.")
        if self.activation not in ACTIVATIONS:
            raise ConfigError(f"{w}.activation = '{self.activation}' unknown; use one of {ACTIVATIONS}.")
        P = stepper.particles
        bodies = [b.name for b in scene.bodies]
        if self.target in ("initial_velocity", "law", "law_weights"):
            if self.body is None and len(bodies) == 1:
                self.body = bodies[0]
            if self.body not in bodies:
                raise ConfigError(f"{w}.body = '{self.body}' is not a body of scene '{scene.name}' ({', '.join(bodies)}).")
            bi = bodies.index(self.body)
            idx = np.nonzero(P.body_id == bi)[0]
            self._rows = slice(int(idx[0]), int(idx[-1]) + 1)
            if not np.array_equal(idx, np.arange(idx[0], idx[-1] + 1)):
                raise ConfigError(f"{w}: body '{self.body}' particles are not contiguous; cannot address them as one block.")
        if self.target == "initial_velocity":
            axes = "xyz"[: scene.dim]
            if self.component not in list(axes):
                raise ConfigError(f"{w}.component = '{self.component}' must be one of {list(axes)}.")
            self._col = axes.index(self.component)
            coords = self._coords(P.x[self._rows], scene.dim)
            if self.form == "scalar":
                self._basis = eval_expression(self.basis or "1", coords, self.constants, f"{w}.basis")
            elif self.form == "mlp":
                bad = [c for c in self.inputs if c not in axes]
                if bad or not self.inputs:
                    raise ConfigError(f"{w}.inputs = {list(self.inputs)}: use coordinates among {list(axes)}.")
                x = P.x[self._rows]
                lo, hi = x.min(axis=0), x.max(axis=0)
                cols = [axes.index(c) for c in self.inputs]
                # inputs scaled to [0, 1] over the body's extent (well-conditioned first layer)
                self._X = (x[:, cols] - lo[cols]) / np.maximum(hi[cols] - lo[cols], 1e-12)
            else:
                raise ConfigError(f"{w}: initial_velocity takes form scalar or mlp, not '{self.form}'.")
        elif self.target == "law":
            g = next(g for g in stepper.groups if g.start <= self._rows.start < g.stop)
            names = g.law.param_names()
            if self.param not in names:
                raise ConfigError(f"{w}.param = '{self.param}' is not a parameter of law '{g.law.name}' ({', '.join(names)}).")
            if self.form != "scalar":
                raise ConfigError(f"{w}: a law parameter takes form scalar.")
            self._index = stepper.groups.index(g)
            self._col = names.index(self.param)
            self._rows = slice(self._rows.start - g.start, self._rows.stop - g.start)
        elif self.target == "law_weights":
            g = next(g for g in stepper.groups if g.start <= self._rows.start < g.stop)
            self._index = stepper.groups.index(g)
            if self.field not in g.weights:
                raise ConfigError(f"{w}.field = '{self.field}': law '{g.law.name}' of body '{self.body}' has shared "
                                  f"weights {sorted(g.weights) or 'none'}.")
            if self.form != "array":
                raise ConfigError(f"{w}: law weights take form array.")
            self._wshape = tuple(np.shape(g.weights[self.field]))
            self._winit = np.asarray(g.weights[self.field], float)
        elif self.target == "boundary":
            if self.boundary not in boundary_names:
                raise ConfigError(f"{w}.boundary = '{self.boundary}' is not a boundary of scene '{scene.name}' "
                                  f"({', '.join(boundary_names) or 'none'}).")
            self._index = list(boundary_names).index(self.boundary)
            data = stepper.controls()["boundary"][self._index]
            if self.field not in data:
                raise ConfigError(f"{w}.field = '{self.field}': boundary '{self.boundary}' has differentiable data "
                                  f"{sorted(data) or 'none'}.")
            self._size = int(np.prod(np.shape(data[self.field]))) if np.ndim(data[self.field]) else 1
        elif self.target == "gravity":
            self._size = scene.dim
        if self.form == "array" and self.target not in ("boundary", "gravity", "law_weights"):
            raise ConfigError(f"{w}: form array applies to boundary data, gravity and law weights.")
        return self

    @staticmethod
    def _coords(x: np.ndarray, dim: int) -> dict[str, np.ndarray]:
        return {a: x[:, k] for k, a in enumerate("xyz"[:dim])}

    # ---- values ------------------------------------------------------------------------------------
    def _shape(self) -> tuple[int, ...]:
        if self.target == "law_weights":
            return self._wshape
        if self.form == "array" or (self.target == "gravity"):
            return (self._size,)
        return ()

    def init_raw(self, ops):
        if self.form == "mlp":
            return ops.mlp(glorot_mlp([len(self.inputs), *self.hidden, 1], self.seed))
        if self.init is None and self.target == "law_weights":
            return ops.asarray(_inv_transform(self.transform, self._winit))
        if self.init is None:
            raise ConfigError(f"{self.where()}.init is missing: give the starting value in physical units.")
        v = np.broadcast_to(np.asarray(self.init, float), self._shape()) if self._shape() else np.asarray(float(self.init))
        return ops.asarray(_inv_transform(self.transform, v))

    def value(self, ops, raw):
        """Physical value: a scalar, an array, or (mlp) the field at the body's particles."""
        if self.form == "mlp":
            return ops.mlp_apply(raw, ops.asarray(self._X), self.activation)
        return ops.transform(self.transform, raw)

    def apply(self, ops, controls: dict, value) -> dict:
        """Controls with this parameter's value put in its place (a new dict; arrays not mutated)."""
        c = dict(controls)
        if self.target == "initial_velocity":
            vals = value * ops.asarray(self._basis) if self.form == "scalar" else value
            c["v"] = ops.set_column(c["v"], self._rows, self._col, vals)
        elif self.target == "law":
            law = list(c["law"])
            law[self._index] = ops.set_column(law[self._index], self._rows, self._col, value)
            c["law"] = tuple(law)
        elif self.target == "boundary":
            b = list(c["boundary"])
            d = dict(b[self._index])
            d[self.field] = value if self.form == "array" else value + 0 * d[self.field]
            b[self._index] = d
            c["boundary"] = tuple(b)
        elif self.target == "law_weights":
            lw = list(c["law_weights"])
            lw[self._index] = {**lw[self._index], self.field: value}
            c["law_weights"] = tuple(lw)
        else:
            c["gravity"] = value
        return c

    # ---- truth and reports ----------------------------------------------------------------------------
    def truth_value(self, stepper, scene) -> np.ndarray | None:
        """The truth in physical units (a field: its values at the body's particles), or None."""
        if self.truth is None:
            return None
        if isinstance(self.truth, str):
            if self.target != "initial_velocity":
                raise ConfigError(f"{self.where()}.truth: an expression is only meaningful for an initial_velocity field.")
            coords = self._coords(stepper.particles.x[self._rows], scene.dim)
            return eval_expression(self.truth, coords, self.constants, f"{self.where()}.truth")
        t = np.asarray(self.truth, float)
        return np.broadcast_to(t, self._shape()).copy() if self._shape() else t

    def truth_controls(self, ops, controls, stepper, scene):
        t = self.truth_value(stepper, scene)
        if t is None:
            return controls
        if isinstance(self.truth, str):       # a field given at the particles (initial_velocity only)
            c = dict(controls)
            c["v"] = ops.set_column(c["v"], self._rows, self._col, ops.asarray(t))
            return c
        return self.apply(ops, controls, ops.asarray(t))

    def report(self, ops, raw, stepper, scene) -> dict[str, Any]:
        """recovered value (scalar/list; a field: L2 over its particles) and relative error vs truth."""
        val = ops.numpy(self.value(ops, raw))
        truth = self.truth_value(stepper, scene)
        out: dict[str, Any] = {}
        if self.target == "initial_velocity" and (self.form == "mlp" or isinstance(self.truth, str)):
            field_val = val if self.form == "mlp" else float(val) * self._basis
            out["recovered_field_rms"] = float(np.sqrt(np.mean(field_val ** 2)))
            if self.form == "scalar":
                out["recovered"] = float(val)
            if truth is not None:
                out["truth_field_rms"] = float(np.sqrt(np.mean(truth ** 2)))
                out["relative_error"] = float(np.linalg.norm(field_val - truth) / max(np.linalg.norm(truth), 1e-300))
                out["error_kind"] = "relative L2 over the body's particles"
            return out
        out["recovered"] = val.tolist() if np.ndim(val) else float(val)
        if truth is not None:
            out["truth"] = truth.tolist() if np.ndim(truth) else float(truth)
            t, v = np.asarray(truth, float), np.asarray(val, float)
            rel = np.abs(v - t) / np.where(t != 0, np.abs(t), 1.0)
            out["relative_error"] = rel.tolist() if np.ndim(rel) else float(rel)
            out["absolute_error"] = np.abs(v - t).tolist() if np.ndim(v) else float(abs(v - t))
            if np.any(t == 0):
                out["error_kind"] = "relative (absolute where the truth is 0)"
        return out

    def profile(self, ops, raw, stepper, scene, n: int = 64) -> dict[str, list] | None:
        """A 1D field's recovered and true profile along its (single) input coordinate, for plots."""
        if self.form != "mlp" or len(self.inputs) != 1:
            return None
        axes = "xyz"[: scene.dim]
        x = stepper.particles.x[self._rows]
        k = axes.index(self.inputs[0])
        s = np.linspace(x[:, k].min(), x[:, k].max(), n)
        X = ((s - s[0]) / max(s[-1] - s[0], 1e-12))[:, None]
        rec = ops.numpy(ops.mlp_apply(raw, ops.asarray(X), self.activation))
        out = {"coordinate": self.inputs[0], "at": s.tolist(), "recovered": rec.tolist()}
        if isinstance(self.truth, str):
            coords = {a: np.full(n, float(x[:, j].mean())) for j, a in enumerate(axes)}
            coords[self.inputs[0]] = s
            out["truth"] = eval_expression(self.truth, coords, self.constants, f"{self.where()}.truth").tolist()
        return out
