"""Teacher-forced fitting through the simulator (NCLaw, Ma et al. 2023, Sec. 3.4 and App. D.2).

A :class:`TeacherForcedFit` is a :class:`~mpmlab.inverse.fit.Fit` whose epoch is one pass over a
ground-truth trajectory cut into segments: at the start of each segment the simulated state is reset
to the ground truth, the segment is rolled out, and the loss sums the per-step position MSE inside
it. Gradients flow only within a segment, so the back-propagation horizon is the segment length.

* **Period** (:class:`TeacherForcing`): lambda(e) = end + (start - end) * (1 + cos(pi e / E)) / 2 at
  epoch e of E (NCLaw's released ``teacher.py``: start 25, end 200): 25 steps at the first epoch,
  200 at the last. The trajectory's ``steps`` are cut into n_seg = ceil(steps / lambda) segments
  whose lengths differ by at most one step (step t belongs to segment floor(t n_seg / steps)).
* **Reset**: ``("x", "v", "C", "F")`` resets the whole state as the release does (C and the law
  state are privileged data: the simulator's own, not observable); ``("x", "v")`` is the
  kinematics-only variant the paper's text describes ("restarts from the ground-truth position"):
  C and the law state carry over from the simulation, detached at the segment boundary.
* **Loss** (the release's ``train.py``): sum over the steps of MSE(x, x_gt) (mean over particles and
  coordinates) times ``1e4 n_seg / steps``; ``velocity_weight`` adds that weight times the same sum
  for v (NCLaw Tab. 7 "with velocity loss"; the paper gives no weight).
* **segment_fraction** f < 1: each epoch back-propagates a random subset of m = max(1, round(f
  n_seg)) segments (seeded by (seed, epoch), so a resumed fit draws the same subsets), the loss
  rescaled by n_seg / m: an unbiased estimate of the full-epoch loss and gradient at a fraction of
  its cost. This holds because fully reset segments are independent; with the kinematics-only reset
  the skipped segments are still rolled forward (without gradient) to carry C and the law state.

Every segment is one call of the backend's ``observe`` (JAX: one compiled function per segment
length, reused across segments and epochs; Warp: the tape-per-segment bridge), and the gradients
are summed on the host. The optimiser is one Adam per group of parameters (NCLaw: the elastic and
the plastic network) with its own learning rate, cosine decay to 0 over the epochs and gradient-norm
clipping per group (``adapter.grouped_optimizer``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np

from ..core.errors import ConfigError, GradientError
from ..observations import Lagrangian, ObservationSchedule
from .fit import Fit

RESETS = (("x", "v", "C", "F"), ("x", "v"))
#: the release's loss scale: MSE summed over steps times LOSS_SCALE * n_seg / steps
LOSS_SCALE = 1.0e4


@dataclass(frozen=True)
class TeacherForcing:
    """The segment schedule of a teacher-forced fit (module docstring)."""

    steps: int
    start: float = 25.0
    end: float = 200.0
    reset: tuple = ("x", "v", "C", "F")

    def __post_init__(self):
        if not (isinstance(self.steps, (int, np.integer)) and self.steps >= 1):
            raise ConfigError(f"teacher forcing: steps = {self.steps!r} must be an integer >= 1.")
        if not (self.start >= 1 and self.end >= 1):
            raise ConfigError(f"teacher forcing: the period runs from {self.start} to {self.end} steps; both must be >= 1.")
        if tuple(self.reset) not in RESETS:
            raise ConfigError(f"teacher forcing: reset = {list(self.reset)}; use [x, v, C, F] (the whole state, as "
                              f"NCLaw's release) or [x, v] (kinematics only).")

    def period(self, epoch: int, epochs: int) -> float:
        """lambda at epoch ``epoch`` (completed epochs) of ``epochs``: ``start`` at 0, ``end`` at ``epochs``."""
        e = min(max(int(epoch), 0), int(epochs))
        return self.end + (self.start - self.end) * 0.5 * (1.0 + math.cos(math.pi * e / max(int(epochs), 1)))

    def count(self, epoch: int, epochs: int) -> int:
        return max(1, min(self.steps, math.ceil(self.steps / self.period(epoch, epochs) - 1e-9)))

    def segments(self, epoch: int, epochs: int) -> list[tuple[int, int]]:
        """(first step, length) of each segment; they partition ``range(steps)``."""
        n = self.count(epoch, epochs)
        ids = (np.arange(self.steps) * n) // self.steps
        starts = np.searchsorted(ids, np.arange(n))
        stops = np.append(starts[1:], self.steps)
        return [(int(a), int(b - a)) for a, b in zip(starts, stops)]

    @property
    def full_reset(self) -> bool:
        return tuple(self.reset) == RESETS[0]


def chosen_segments(n: int, fraction: float, seed: int, epoch: int) -> np.ndarray:
    """The segments an epoch back-propagates: all of them (fraction 1), or a seeded random subset."""
    if not 0.0 < fraction <= 1.0:
        raise ConfigError(f"segment_fraction = {fraction} must be in (0, 1].")
    m = n if fraction >= 1.0 else max(1, int(round(fraction * n)))
    if m == n:
        return np.arange(n)
    return np.sort(np.random.default_rng([int(seed), int(epoch)]).choice(n, size=m, replace=False))


class TeacherForcedFit(Fit):
    """A fit of ``parameters`` (e.g. a neural law's weights, ``FitParameter(target="law_weights")``) to a
    ground-truth trajectory ``truth`` by teacher-forced segments (module docstring).

    ``truth``: ``x``, ``v`` [steps + 1, N, D] (scene order, every step), and for a full reset ``C``
    [steps + 1, N, D, D] (affine transfers) and each law state field the scene's laws declare (e.g.
    ``F`` [steps + 1, N, D, D]), as NumPy arrays. ``groups``: ``{label: [parameter names]}`` for the
    optimiser (one Adam per group)."""

    def __init__(self, stepper, scene, parameters: Sequence, truth: Mapping[str, np.ndarray], forcing: TeacherForcing,
                 epochs: int, segment_fraction: float = 1.0, velocity_weight: float = 0.0, seed: int = 0,
                 groups: Mapping[str, Sequence[str]] | None = None, segment: int | None = None):
        obs = Lagrangian(quantity="x")
        super().__init__(stepper, scene, parameters, obs, ObservationSchedule(steps=(0,)), segment=segment)
        self.forcing, self.epochs = forcing, int(epochs)
        self.segment_fraction, self.velocity_weight, self.seed = float(segment_fraction), float(velocity_weight), int(seed)
        chosen_segments(1, self.segment_fraction, 0, 0)            # validate the fraction now
        names = [p.name for p in self.parameters]
        self.groups = {k: list(v) for k, v in (groups or {"all": names}).items()}
        grouped = [n for v in self.groups.values() for n in v]
        if sorted(grouped) != sorted(names):
            raise ConfigError(f"teacher-forced fit: the optimiser groups {self.groups} must list each parameter "
                              f"({names}) exactly once.")
        self._obs_v = Lagrangian(quantity="v")
        if not forcing.full_reset:
            other = sorted({f for g in stepper.groups for f in g.law.state_fields} - {"F"})
            if other:
                raise ConfigError(f"teacher forcing with reset [x, v] carries C and F across a reset; the scene's laws "
                                  f"also keep {other}: use reset [x, v, C, F].")
        self.truth = self._check_truth(truth)
        self.reference = self.truth["x"]            # Fit.run generates no reference data
        self._vg: dict[Any, Any] = {}
        self._state_obs: dict[str, Any] = {}
        self._bad_segment = None          # (start, length, initial state) of the first non-finite gradient
        self._data = None
        self.last_epoch: dict[str, Any] = {}

    # ---- ground truth ---------------------------------------------------------------------------------
    def _check_truth(self, truth):
        st, P = self.stepper, self.stepper.particles
        T = self.forcing.steps + 1
        need = ["x", "v"]
        if self.forcing.full_reset:
            if st.transfer.needs_affine:
                need.append("C")
            need += sorted({f for g in st.groups for f in g.law.state_fields})
        missing = [k for k in need if k not in truth or truth[k] is None]
        if missing:
            raise ConfigError(f"teacher forcing with reset {list(self.forcing.reset)} needs {', '.join(missing)} at every "
                              f"step in the dataset; rerun experiment=nclaw_datasets (frame_every=1, fields F and C).")
        out = {}
        for k in need:
            a = np.asarray(truth[k])
            if a.shape[0] < T or a.shape[1] != P.count:
                raise ConfigError(f"the dataset's '{k}' has shape {a.shape}; the fit needs {T} frames (steps {self.forcing.steps} "
                                  f"+ 1) of {P.count} particles (the scene's); check the dataset matches the scene.")
            out[k] = a[:T]
        return out

    def _backend_data(self):
        """The ground truth as backend arrays, once."""
        if self._data is None:
            self._data = {k: self.ops.asarray(a) for k, a in self.truth.items()}
        return self._data

    def _initial(self, s: int, carry=None) -> dict:
        """The reset state at step ``s``: ground truth (and the carried C / law state when kinematics only)."""
        d = self._backend_data()
        init = {"x": d["x"][s], "v": d["v"][s]}
        if self.forcing.full_reset:
            if "C" in d:
                init["C"] = d["C"][s]
            init["law_state"] = tuple({f: d[f][s][g.start:g.stop] for f in g.law.state_fields}
                                      for g in self.stepper.groups)
        elif carry is not None:
            init.update(carry)
        return init

    def _controls(self, raw, init) -> dict:
        """The rollout controls of a segment: the trained values from ``raw``, the start state ``init``."""
        return {**self.controls_of(raw), **init}

    # ---- the loss of one segment -------------------------------------------------------------------------
    def _value_and_grad(self, grad: bool = True):
        """``(raw, init, (target_x, target_v), scale) -> (loss, why, grad)`` for segments of any length:
        Σ_t MSE(x_t) (+ velocity_weight Σ_t MSE(v_t)), times ``scale`` (the adapter's tracking loss)."""
        if grad not in self._vg:
            self._vg[grad] = self.adapter.tracking_value_and_grad(
                self.stepper, self._controls, (self.observation, self._obs_v), (1.0, self.velocity_weight),
                self.segment, grad)
        return self._vg[grad]

    def _carry_after(self, raw, init, length):
        """C and the law state F after a segment (kinematics-only reset), detached: one more forward
        rollout of the segment, observed by ``ParticleState`` at its last step."""
        from ..observations import ParticleState

        c = self._controls(raw, init)
        st, D, N = self.stepper, self.stepper.dim, self.stepper.particles.count
        carry = {}
        quantities = (["C"] if st.transfer.needs_affine else []) + ["F"]
        for q in quantities:
            obs = self._state_obs.setdefault(q, ParticleState(quantity=q))
            y, bad = self.adapter.observe(st, c, obs, np.array([length]), self.segment)
            a = self.ops.asarray(self.ops.numpy(y).reshape(N, D, D))       # detached: no gradient across a reset
            if q == "C":
                carry["C"] = a
            else:
                carry["law_state"] = tuple({"F": a[g.start:g.stop]} for g in st.groups)
        return carry

    def epoch_loss(self, raw, epoch: int, fraction: float | None = None, grad: bool = True):
        """(loss, why invalid or None, gradient or None, info) of one teacher-forced epoch; ``grad=False``:
        the loss alone (no backward pass; the gradient entry is None)."""
        f = self.segment_fraction if fraction is None else fraction
        segs = self.forcing.segments(epoch, self.epochs)
        n_seg = len(segs)
        chosen = chosen_segments(n_seg, f, self.seed, epoch)
        scale = LOSS_SCALE * n_seg / self.forcing.steps * n_seg / len(chosen)
        d = self._backend_data()
        total, acc, carry = 0.0, None, None
        chosen_set = set(int(k) for k in chosen)
        for k, (s, L) in enumerate(segs):
            if k not in chosen_set and self.forcing.full_reset:
                continue
            init = self._initial(s, carry)
            if not self.forcing.full_reset:
                carry = self._carry_after(raw, init, L)
                if k not in chosen_set:
                    continue
            tv = d["v"][s + 1:s + L + 1]
            try:
                val, why, g = self._value_and_grad(grad)(raw, init, (d["x"][s + 1:s + L + 1], tv),
                                                         self.ops.asarray(scale))
            except GradientError as e:        # raised inside a backend's backward pass: the trajectory's step
                raise GradientError(s + e.step, e.particle, e.field,
                                    f"in the teacher-forced segment starting at step {s}; " + (e.hint or "")) from None
            if why is not None or (grad and g is None):
                return val, why, None, {}
            if grad and self._bad_segment is None and not self.adapter.check_gradient(g):
                self._bad_segment = (s, L, init)
            total += val
            if grad:
                acc = g if acc is None else self.ops.tree_map(lambda a, b: a + b, acc, g)
        info = {"period": self.forcing.period(epoch, self.epochs), "segments": n_seg,
                "segments_backpropagated": int(len(chosen))}
        return total, None, (acc if grad else None), info

    def _locate(self, raw):
        """A non-finite gradient: replay the segment that produced it step by step (``GradientError``
        with the trajectory's step: the segment's start plus the step inside it, and the particle)."""
        if self._bad_segment is None:
            raise GradientError(0, -1, "weights", "the summed gradient is non-finite although every segment's "
                                               "is finite: an overflow in the sum; lower the loss scale")
        s, L, init = self._bad_segment
        self._bad_segment = None
        c = self._controls(raw, init)
        tx = self._backend_data()["x"][s + 1:s + L + 1]
        n = float(self.stepper.particles.count * self.stepper.dim)
        try:
            self.adapter.locate_nan_gradient(self.stepper, c, self.observation, np.arange(1, L + 1),
                                             lambda y: ((y - tx) ** 2).sum() / n, self.segment)
        except GradientError as e:
            raise GradientError(s + e.step, e.particle, e.field,
                                f"in the teacher-forced segment starting at step {s}; " + (e.hint or "")) from None
        raise GradientError(s, -1, "weights", f"the gradient of the segment starting at step {s} is non-finite "
                                              f"but its replay is finite: check the weights for Inf")

    # ---- Fit hooks ------------------------------------------------------------------------------------
    def values(self, raw) -> dict[str, Any]:
        """Per epoch, the Frobenius norm of each weight array (not the 11k numbers themselves)."""
        return {p.name: float(np.linalg.norm(self.ops.numpy(p.value(self.ops, raw[p.name])))) for p in self.parameters}

    def epoch_objective(self):
        def objective(raw):
            val, why, g, info = self.epoch_loss(raw, self.epoch)
            self.last_epoch = info
            return val, why, g
        return objective

    def grad_norms(self, grad) -> dict[str, float]:
        """The gradient norm of each optimiser group (before clipping)."""
        names = [p.name for p in self.parameters]
        by_name = grad if isinstance(grad, dict) else dict(zip(names, grad))
        out = {}
        for label, members in self.groups.items():
            out[label] = float(math.sqrt(sum(float(np.sum(self.ops.numpy(by_name[m]) ** 2)) for m in members)))
        return out

    def epoch_extras(self, raw, grad):
        return {**self.last_epoch, "grad_norms": self.grad_norms(grad), "lr": self.learning_rates(self.epoch)}

    def learning_rates(self, epoch: int) -> dict[str, float]:
        """Each group's learning rate at ``epoch`` (the cosine schedule of ``grouped_optimizer``, times the
        fit's ``lr_scale`` after a step back)."""
        sched = getattr(self, "lr_config", None) or {}
        out = {}
        for label, g in sched.get("groups", {}).items():
            lr = float(g["lr"])
            if sched.get("schedule", "cosine") == "cosine":
                lr *= 0.5 * (1.0 + math.cos(math.pi * min(epoch, self.epochs) / max(self.epochs, 1)))
            out[label] = lr * getattr(self, "lr_scale", 1.0)      # Fit's step-back factor (on_divergence)
        return out

    def final_value(self, raw) -> float:
        """The full teacher-forced loss (every segment) at the last epoch's period."""
        val, why, _, _ = self.epoch_loss(raw, min(self.epoch, self.epochs), fraction=1.0, grad=False)
        return float(val) if why is None else float("nan")

    def optimizer(self, groups: Mapping[str, Mapping[str, Any]], schedule: str = "cosine"):
        """(optimizer, schedule) for ``Fit.run``: one Adam per group {label: {lr, clip}} (``grouped_optimizer``)."""
        unknown = sorted(set(groups) ^ set(self.groups))
        if unknown:
            raise ConfigError(f"optimiser groups {sorted(groups)} do not match the parameter groups {sorted(self.groups)}.")
        if schedule not in ("cosine", "constant"):
            raise ConfigError(f"lr schedule '{schedule}' unknown; use cosine (to 0 over the epochs, NCLaw) or constant.")
        self.lr_config = {"groups": {k: dict(v) for k, v in groups.items()}, "schedule": schedule}
        names = [p.name for p in self.parameters]
        spec = {label: {"lr": float(g["lr"]), "clip": (None if g.get("clip") is None else float(g["clip"])),
                        "params": list(self.groups[label])} for label, g in groups.items()}
        return self.adapter.grouped_optimizer(names, spec, schedule, self.epochs)
