"""Gradient-based fitting of rollout controls to observations (JAX-MPM Eq. 28), on either backend.

``Fit`` owns: the stepper, the observation operator and schedule, the reference data, the
:class:`~mpmlab.inverse.parameters.FitParameter` list and an optimiser. One ``epoch`` = one rollout,
one gradient, one optimiser step. The loss is the masked mean of Eq. 28's squared residuals
(the mean instead of the sum: Adam is invariant to the scale, and the number reads the same at every
observation density).

The fit names no backend: everything array-shaped goes through the stepper's
:class:`~mpmlab.core.autodiff.AutodiffAdapter` (``Fit.adapter``). On JAX that is ``jax.value_and_grad``
of a jitted loss through ``stepper.observe`` and an optax GradientTransformation; on Warp
``stepper.observe`` is a ``torch.autograd.Function`` and the optimiser is ``torch.optim`` (+ an optional
lr scheduler). A non-finite loss stops the fit with ``FitDiverged``; a non-finite gradient is located
(``GradientError``: step and particle). Checkpoints (every ``checkpoint_every`` epochs, atomic) let an
interrupted fit resume where it stopped.

``on_divergence="backoff"`` (``max_backoffs`` times at most) turns a diverged epoch into a logged step
back instead: the parameters and optimiser state of the epoch before it are restored (from
``<checkpoint>.prev``, written before every optimiser step, so a resumed fit can step back too), and
every later update is scaled by a further 1/2 (for Adam without weight decay, exactly a halved
learning rate). Each history entry carries its ``lr_scale``; the epoch re-run after a step back carries
``backoff: {diverged_at, why}``. The default, ``stop``, raises ``FitDiverged``.
"""
from __future__ import annotations

import logging
import pickle
import time
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from ..core import signals
from ..core.autodiff import adapter
from ..core.errors import ConfigError, FitDiverged, MpmlabError
from ..io.files import write_pickle
from ..observations import ObservationSchedule
from .parameters import FitParameter

log = logging.getLogger("mpmlab")


class Fit:
    def __init__(self, stepper, scene, parameters: Sequence[FitParameter], observation, schedule: ObservationSchedule,
                 segment: int | None = None, reference: np.ndarray | None = None):
        self.stepper, self.scene = stepper, scene
        self.backend = stepper.backend_name
        #: the backend's differentiable surface (mpmlab.core.autodiff); ``ops`` is the same object
        self.adapter = self.ops = adapter(stepper)
        self.parameters = list(parameters)
        self.observation, self.schedule, self.segment = observation, schedule, segment
        self.steps = schedule.steps_array()
        self.base = stepper.controls()
        self.reference = reference
        self.history: list[dict[str, Any]] = []
        #: what a resume accepted (data that differ from the checkpoint's at round-off: mpmlab.core.resume)
        self.resume_notes: list[str] = []
        self.epoch = 0
        self.lm_stop: str | None = None     # why a Levenberg-Marquardt fit stopped early
        self.stopped_early = False          # a gradient fit ended by its stop() budget

    # ---- reference data --------------------------------------------------------------------------
    def truth_controls(self):
        c = self.base
        for p in self.parameters:
            c = p.truth_controls(self.ops, c, self.stepper, self.scene)
        return c

    def make_reference(self) -> np.ndarray:
        """Observations of the rollout under the truth (plus the schedule's noise), NumPy."""
        if any(p.truth is None for p in self.parameters):
            missing = [p.name for p in self.parameters if p.truth is None]
            raise MpmlabError(f"cannot generate reference observations: parameter(s) {missing} have no 'truth'; "
                              f"give task.parameters.<name>.truth or a reference trajectory (input=PATH.h5).")
        y = self.stepper.observe(self.truth_controls(), self.observation, self.steps, self.segment)
        ref = self.ops.numpy(y)
        self.reference = self.schedule.add_noise(ref)
        return self.reference

    # ---- the loss ----------------------------------------------------------------------------------------
    def controls_of(self, raw: dict):
        c = self.base
        for p in self.parameters:
            c = p.apply(self.ops, c, p.value(self.ops, raw[p.name]))
        return c

    def _mask(self):
        T, L, d = np.shape(self.reference)
        m = self.schedule.mask_array((T, L))
        if self.observation.name == "eulerian":
            # an empty monitor reads exactly 0 (Eq. 27 is undefined there): no data, m_{l,t} = 0
            m = m * np.any(np.asarray(self.reference) != 0.0, axis=2)
        return m

    def data_loss(self) -> Callable:
        """predicted observations [T, L, d] -> the masked mean squared residual (JAX-MPM Eq. 28, mean)."""
        mask = self._mask()
        norm = float(mask.sum() * np.shape(self.reference)[2])
        ref = self.ops.asarray(self.reference)
        m = self.ops.asarray(mask)[..., None]

        def data_loss(pred):
            r = (pred - ref) * m
            return (r * r).sum() / norm

        return data_loss

    def loss_function(self) -> Callable:
        """``raw -> (loss, invalid)``: ``invalid`` says the rollout diverged (a backend whose rollout raises
        ``SimulationDiverged`` itself always reports False)."""
        obs, steps, seg = self.observation, self.steps, self.segment
        data_loss = self.data_loss()

        def loss(raw):
            pred, bad = self.adapter.observe(self.stepper, self.controls_of(raw), obs, steps, seg)
            return data_loss(pred), bad

        return loss

    def init_raw(self) -> dict:
        return {p.name: p.init_raw(self.ops) for p in self.parameters}

    # ---- reporting ----------------------------------------------------------------------------------------
    def values(self, raw) -> dict[str, Any]:
        out = {}
        for p in self.parameters:
            if p.form == "mlp":
                continue
            v = self.ops.numpy(p.value(self.ops, raw[p.name]))
            out[p.name] = v.tolist() if np.ndim(v) else float(v)
        return out

    def field_errors(self, raw) -> dict[str, float]:
        """Relative L2 error over the body's particles of each MLP field with a known truth (JAX-MPM
        Fig. 14b); recorded every epoch."""
        out = {}
        for p in self.parameters:
            if p.form == "mlp":
                truth = p.truth_value(self.stepper, self.scene)
                if truth is not None:
                    val = np.asarray(self.ops.numpy(p.value(self.ops, raw[p.name])), float)
                    out[p.name] = float(np.linalg.norm(val - truth) / max(np.linalg.norm(truth), 1e-300))
        return out

    def report(self, raw) -> dict[str, Any]:
        return {p.name: p.report(self.ops, raw[p.name], self.stepper, self.scene) for p in self.parameters}

    def profiles(self, raw) -> dict[str, Any]:
        out = {}
        for p in self.parameters:
            pr = p.profile(self.ops, raw[p.name], self.stepper, self.scene)
            if pr is not None:
                out[p.name] = pr
        return out

    # ---- the loop -----------------------------------------------------------------------------------------
    def run(self, epochs: int, optimizer_cfg, schedule_cfg=None, checkpoint: Path | None = None,
            checkpoint_every: int = 10, resume: bool = True, progress: bool | None = None,
            on_epoch: Callable[[int, float, dict], None] | None = None, tolerance: float = 0.0,
            on_checkpoint: Callable[[Any], None] | None = None, stop: Callable[[], bool] | None = None,
            on_divergence: str = "stop", max_backoffs: int = 4, identity: dict | None = None) -> dict:
        """Optimise for ``epochs`` epochs (total, counting those done before a resume); returns the
        final trainable values. ``on_epoch(epoch, loss, values)`` runs after every epoch,
        ``on_checkpoint(raw)`` after every checkpoint written (gradient optimisers); ``stop()`` returning
        True ends the fit after the current epoch, checkpointed (a time budget: rerun to continue).
        ``on_divergence``: ``stop`` (raise ``FitDiverged``) or ``backoff`` (gradient optimisers: step back one
        epoch and halve the updates, at most ``max_backoffs`` times; see the module docstring).
        ``identity`` (JSON values: the data's digest, the options that shape the curve) is kept beside the
        checkpoint, and a resume with another identity is refused (``mpmlab.core.resume``)."""
        if on_divergence not in ("stop", "backoff"):
            raise ConfigError(f"on_divergence must be 'stop' or 'backoff', not {on_divergence!r}.")
        if on_divergence == "backoff" and (not isinstance(max_backoffs, int) or max_backoffs < 1):
            raise ConfigError(f"max_backoffs must be a positive integer, not {max_backoffs!r}.")
        if checkpoint is not None and identity is not None:
            from ..core.resume import NOTES, check_identity, read_identity, write_identity

            if resume and Path(checkpoint).exists():
                saved = read_identity(checkpoint)
                notes = check_identity(type(self).__name__, checkpoint, saved, identity)
                for note in notes:
                    log.warning(note)
                # the notes of every resume so far, kept in the identity file (with when they were made)
                when = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
                self.resume_notes = list((saved or {}).get(NOTES, [])) + [f"{when}: {n}" for n in notes]
            identity = dict(identity, **({NOTES: self.resume_notes} if self.resume_notes else {}))
            write_identity(checkpoint, identity)
        if self.reference is None:
            self.make_reference()
        from .lm import LevenbergMarquardt

        try:
            if isinstance(optimizer_cfg, LevenbergMarquardt):
                return self._run_lm(epochs, optimizer_cfg, checkpoint, checkpoint_every, resume, progress, on_epoch,
                                    tolerance)
            return self._run_gradient(epochs, optimizer_cfg, schedule_cfg, checkpoint, checkpoint_every, resume,
                                      progress, on_epoch, tolerance, on_checkpoint, stop,
                                      max_backoffs if on_divergence == "backoff" else 0)
        except KeyboardInterrupt as stopped:
            # a stop signal mid-fit: say how far it got and what was kept (without this detail the CLI reads
            # it as a run stopped before its first step, "nothing was written", beside a checkpoint of hours)
            if not hasattr(stopped, "mpmlab_detail"):
                kept = (f"; {Path(checkpoint).name} keeps the last checkpointed epoch: rerun the same command to "
                        f"resume" if checkpoint is not None and Path(checkpoint).exists() else "")
                stopped.mpmlab_detail = f"at epoch {self.epoch} of {epochs}{kept}"
                from ..core.signals import stop_reason

                log.warning("fit %s %s.", stop_reason(stopped), stopped.mpmlab_detail)
            raise

    def _bar(self, epochs, progress):
        """The progress bar, once the checkpoint (if any) is loaded; a resume is said in the run's log."""
        from tqdm.auto import tqdm

        if self.epoch:
            log.info("fit resumed at epoch %d of %d from its checkpoint.", self.epoch, epochs)
        return tqdm(total=epochs, initial=self.epoch, disable=None if progress is None else not progress,
                    unit="epoch", leave=False, mininterval=0.5)

    def _record(self, epoch, loss, raw, grad_norm, t):
        entry = {"epoch": epoch, "loss": float(loss), "grad_norm": float(grad_norm), "time_s": float(t),
                 "values": self.values(raw)}
        errors = self.field_errors(raw)
        if errors:
            entry["field_errors"] = errors
        self.history.append(entry)
        return entry

    def _epoch_done(self, bar, loss, on_epoch):
        """Count the epoch, show it on the progress bar and report it to ``on_epoch``; a stop signal
        (SIGINT/SIGTERM) ends the fit here, after the last checkpoint."""
        signals.check()
        self.epoch += 1
        bar.update(1)
        bar.set_postfix(loss=f"{loss:.3e}")
        if on_epoch is not None:
            on_epoch(self.epoch - 1, loss, self.history[-1]["values"])

    def _diverged(self, epoch, loss, why: str = ""):
        last = self.history[-1]["values"] if self.history else {}
        return FitDiverged(f"fit diverged at epoch {epoch}: {why or 'the loss is ' + str(loss)} (parameters of the "
                           f"last good epoch: {last}); lower the learning rate, bound the parameter with transform: "
                           f"softplus, or check the data.")

    def _last_lr_scale(self) -> float:
        """The update scale of the last recorded epoch (1 before any step back, or with no history)."""
        return float(self.history[-1].get("lr_scale", 1.0)) if self.history else 1.0

    def _run_gradient(self, epochs, opt_cfg, sched_cfg, checkpoint, every, resume, progress, on_epoch, tol,
                      on_checkpoint=None, stop=None, max_backoffs=0):
        """One rollout, one gradient and one optimiser step per epoch (optimiser and schedule as the
        adapter's ``optimizer_init`` takes them: optax on JAX, torch.optim factories on Warp)."""
        import tempfile

        ad = self.adapter
        vg = self.epoch_objective()
        raw, state = ad.optimizer_init(opt_cfg, sched_cfg, self.init_raw())
        if checkpoint is not None and resume and checkpoint.exists():
            self.epoch, self.history, raw, state = ad.load_checkpoint(checkpoint, raw, state)
        self.lr_scale = self._last_lr_scale()
        scratch = None
        if max_backoffs:
            if checkpoint is None:
                scratch = tempfile.TemporaryDirectory(prefix="mpmlab-fit-")
                prev = Path(scratch.name) / "prev"
            else:
                prev = checkpoint.with_name(checkpoint.name + ".prev")
                if not (resume and checkpoint.exists()):
                    prev.unlink(missing_ok=True)        # a fresh fit: no epoch to step back to
        bar = self._bar(epochs, progress)
        t0 = time.perf_counter() - (self.history[-1]["time_s"] if self.history else 0.0)
        backoff = None
        # step-backs taken, counted here: the history cannot count them, since stepping back again to
        # the epoch re-run after a step back drops that epoch's record (with its "backoff" entry)
        used = sum(1 for h in self.history if "backoff" in h)
        try:
            while self.epoch < epochs:
                val, why, g = vg(raw)
                if why is not None or not np.isfinite(val):
                    err = self._diverged(self.epoch, val, why or "")
                    if not max_backoffs or used >= max_backoffs or not prev.exists():
                        if max_backoffs:
                            err.args = (err.args[0] + f" [{used} step(s) back already taken of {max_backoffs}"
                                        + ("" if prev.exists() else "; no earlier epoch to step back to") + "]",)
                        raise err
                    at = self.epoch
                    self.epoch, self.history, raw, state = ad.load_checkpoint(prev, raw, state)
                    self.lr_scale = 0.5 * self.lr_scale        # the scale that diverged, halved
                    used += 1
                    backoff = {"diverged_at": int(at), "why": why or f"the loss is {val}"}
                    log.warning("fit: epoch %d diverged (%s); stepping back to epoch %d with the updates scaled by "
                                "%g (step back %d of %d).", at, backoff["why"], self.epoch, self.lr_scale, used,
                                max_backoffs)
                    continue
                if not ad.check_gradient(g):
                    self._locate(raw)
                gn = ad.grad_norm(g)
                self._record(self.epoch, val, raw, gn, time.perf_counter() - t0)
                self.history[-1].update(self.epoch_extras(raw, g))
                self.history[-1]["lr_scale"] = self.lr_scale
                if backoff is not None:
                    self.history[-1]["backoff"], backoff = backoff, None
                if max_backoffs:                # the state this epoch started from, to step back to
                    ad.save_checkpoint(prev, self.epoch, self.history[:-1], raw, state)
                raw, state = ad.optimizer_step(state, raw, g, scale=self.lr_scale)
                self._epoch_done(bar, val, on_epoch)
                stopping = stop is not None and self.epoch < epochs and stop()
                if checkpoint is not None and (self.epoch % every == 0 or self.epoch == epochs or stopping):
                    ad.save_checkpoint(checkpoint, self.epoch, self.history, raw, state)
                    if on_checkpoint is not None:
                        on_checkpoint(raw)
                if val <= tol or stopping:
                    self.stopped_early = stopping
                    break
        finally:
            bar.close()
            if scratch is not None:
                scratch.cleanup()
        self.final_loss = self.final_value(raw)
        return raw

    # ---- what a subclass changes (mpmlab.inverse.teacher: teacher-forced segments) ----------------------------
    def epoch_objective(self) -> Callable:
        """``raw -> (loss, why_invalid or None, gradient or None)`` for the epoch ``self.epoch``: here
        one rollout of the whole schedule."""
        return self.adapter.value_and_grad(self.loss_function())

    def epoch_extras(self, raw, grad) -> dict[str, Any]:
        """Entries added to the epoch's history record (and to the recording)."""
        return {}

    def final_value(self, raw) -> float:
        """The loss at the final parameters."""
        return self.adapter.value(self.loss_function(), raw)

    def _locate(self, raw):
        """Turn a non-finite gradient into a GradientError naming step and particle."""
        self.adapter.locate_nan_gradient(self.stepper, self.controls_of(raw), self.observation, self.steps,
                                         self.data_loss(), self.segment)

    # ---- Levenberg-Marquardt (mpmlab.inverse.lm): a few scalar / array parameters ----------------------------
    def _flat_layout(self, lm) -> list[tuple[str, tuple[int, ...], slice]]:
        layout, start = [], 0
        for p in self.parameters:
            if p.form == "mlp":
                raise ConfigError(f"{p.where()}: LevenbergMarquardt fits scalar and array parameters only (this one "
                                  f"is an MLP field); use a gradient optimiser such as optax.adam / torch.optim.Adam.")
        init = self.init_raw()
        for p in self.parameters:
            shape = tuple(np.shape(self.ops.numpy(init[p.name])))
            n = int(np.prod(shape)) if shape else 1
            layout.append((p.name, shape, slice(start, start + n)))
            start += n
        if start > lm.max_parameters:
            raise ConfigError(f"task.optimizer: LevenbergMarquardt with {start} parameters exceeds max_parameters = "
                              f"{lm.max_parameters} (the Jacobian costs ~one rollout per parameter); use a gradient "
                              f"optimiser, or raise max_parameters.")
        return layout

    def _residual_functions(self, lm, unflatten):
        """(residual(x) -> r or None when the rollout diverged, jacobian(x) -> (r, J, diverged)) on NumPy float64
        vectors, scaled so that r.r is the data loss. ``unflatten`` maps the parameter vector (a backend
        array) to the raw values by name. The Jacobian is the adapter's AD mode, or central differences."""
        mask = self._mask()
        scale = 1.0 / np.sqrt(float(mask.sum() * np.shape(self.reference)[2]))
        obs, steps, seg = self.observation, self.steps, self.segment
        kind = lm.jacobian_kind(self.adapter)

        def observe(x):
            return self.adapter.observe(self.stepper, self.controls_of(unflatten(x)), obs, steps, seg)

        residual, jacobian = self.adapter.residual_functions(observe, self.reference, mask, scale, kind)
        if jacobian is not None:
            return residual, jacobian

        def jacobian(x, r_known=None):
            r = residual(x) if r_known is None else r_known
            return r, (lm.central_jacobian(residual, x) if r is not None else None), r is None
        return residual, jacobian

    def _run_lm(self, epochs, lm, checkpoint, every, resume, progress, on_epoch, tol):
        layout = self._flat_layout(lm)
        init = self.init_raw()
        x = np.concatenate([np.ravel(self.ops.numpy(init[name])) for name, _, _ in layout]).astype(np.float64)

        def unflatten(v):
            return {name: v[sl].reshape(shape) for name, shape, sl in layout}

        def to_raw(v):
            return {k: self.ops.asarray(np.asarray(a)) for k, a in unflatten(np.asarray(v, np.float64)).items()}

        residual, jacobian = self._residual_functions(lm, unflatten)
        damping = float(lm.damping)
        if checkpoint is not None and resume and checkpoint.exists():
            with open(checkpoint, "rb") as fh:
                ck = pickle.load(fh)
            if not isinstance(ck, dict) or ck.get("optimizer") != "levenberg_marquardt":
                raise ConfigError(f"{checkpoint} was written by another optimiser; delete it or set task.resume=false.")
            x, damping = np.asarray(ck["x"], np.float64), float(ck["damping"])
            self.epoch, self.history = ck["epoch"], ck["history"]
        self.lm_stop = None
        r_known = None              # the residuals at the current x, once computed
        bar = self._bar(epochs, progress)
        t0 = time.perf_counter() - (self.history[-1]["time_s"] if self.history else 0.0)
        try:
            while self.epoch < epochs:
                r, J, bad = jacobian(x, r_known)
                if bad or r is None:
                    raise self._diverged(self.epoch, float("nan"), "the rollout diverged at the current parameters")
                r_known = r
                val = float(r @ r)
                if not np.isfinite(val) or not np.all(np.isfinite(J)):
                    raise self._diverged(self.epoch, val, "non-finite residuals or Jacobian")
                self._record(self.epoch, val, to_raw(x), float(np.linalg.norm(2 * J.T @ r)), time.perf_counter() - t0)
                self.history[-1]["damping"] = damping
                for _ in range(int(lm.max_tries)):
                    trial = x + lm.propose(r, J, damping)
                    rt = residual(trial)
                    if rt is not None and float(rt @ rt) < val:
                        x, damping, r_known = trial, max(damping / lm.decrease, lm.min_damping), rt
                        break
                    damping *= lm.increase
                else:
                    self.lm_stop = (f"no damped Gauss-Newton step lowers the loss after {lm.max_tries} tries "
                                    f"(lambda = {damping:.3g}): converged")
                self._epoch_done(bar, val, on_epoch)
                if checkpoint is not None and (self.epoch % every == 0 or self.epoch == epochs or self.lm_stop):
                    write_pickle(checkpoint, {"optimizer": "levenberg_marquardt", "epoch": self.epoch,
                                                "history": self.history, "x": x, "damping": damping})
                if self.lm_stop or val <= tol:
                    break
        finally:
            bar.close()
        r = r_known if r_known is not None else residual(x)
        self.final_loss = float(r @ r) if r is not None else float("nan")
        return to_raw(x)
