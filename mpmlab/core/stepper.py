"""Backend-independent rollout driver: frames, guards and divergence localisation.

A backend stepper implements a few primitives (``init``, ``_advance``, ``_is_bad``, ``to_numpy``);
this base class turns them into ``rollout`` with the stability guards of issue #2:

* every ``check_every`` steps a device-side reduction asks "is any x/v/law state non-finite, any
  J <= 0, any particle outside the domain interior?" (one scalar crosses to the host);
* only when it says yes, the chunk is replayed one step at a time from its saved start to find the
  exact step, and the offending particle/field/value is found on the host, so the guard costs one
  reduction per check, not per step;
* ``SimulationDiverged`` carries the frames produced so far (``.trajectory``).
"""
from __future__ import annotations

import time
from abc import abstractmethod
from typing import Any, Callable

import numpy as np

from . import signals
from .errors import ConfigError, SimulationDiverged
from .interfaces import AbstractStepper, AbstractTransfer
from .scene import Scene
from .state import Trajectory


class BaseStepper(AbstractStepper):
    backend_name = "?"

    def __init__(self, scene: Scene, transfer: AbstractTransfer, precision: str = "fp32", check_every: int | None = None):
        if precision not in ("fp32", "fp64"):
            raise ConfigError(f"precision '{precision}' unknown; use 'fp32' or 'fp64'.")
        for b in scene.boundaries:
            b.validate(scene)
        walls = [b for b in scene.boundaries if b.name == "walls"]
        if len(walls) > 1:
            raise ConfigError(
                f"scene '{scene.name}' has {len(walls)} 'walls' boundaries; give one, with a kind per face "
                f"(faces: {{x-: sticky, y-: slip, ...}})."
            )
        self.scene = scene
        self.transfer = transfer
        self.precision = precision
        self.dim = scene.dim
        self.dt = scene.resolve_dt()
        self._dt0 = self.dt            # build-time dt: fixed-dt runs and gradient rollouts (observe) use it
        self.particles = scene.particles()
        self.groups = self.particles.groups
        if self.particles.C is not None and not transfer.needs_affine:
            with_C = [b.name or str(i) for i, b in enumerate(scene.bodies) if b.C is not None]
            raise ConfigError(f"scene '{scene.name}': body {', '.join(with_C)} sets an initial C, but transfer "
                              f"'{transfer.name}' stores no C; use apic, mls or tpic, or remove C.")
        self.check_every = check_every
        self.compile_time_s = 0.0
        #: every law state field of the scene (declared by its laws), in order of first appearance
        self.state_fields = {}
        for g in self.groups:
            for f in g.law.state:
                self.state_fields.setdefault(f.name, f)
        self.state_field_names = tuple(self.state_fields)

    # ---- primitives a backend implements ---------------------------------------------------
    @abstractmethod
    def _advance(self, state, steps: int):
        """Advance ``steps`` steps (compiled loop); returns the new state."""

    @abstractmethod
    def _is_bad(self, state) -> bool:
        """Device-side guard reduction: any non-finite value, J <= 0 or particle outside the domain."""

    def step(self, state):
        return self._advance(state, 1)

    def initial_C(self) -> np.ndarray:
        """The affine field C at t = 0 [N, D, D] (the bodies' initial C; zero where none is given)."""
        C = self.particles.C
        return np.zeros((self.particles.count, self.dim, self.dim)) if C is None else C

    def initial_domain(self) -> np.ndarray:
        """CPDI's particle domains at t = 0 [N, D, D] (``mpmlab.shapes.cpdi.reference.initial_domain``): the
        cube of each particle's reference volume, deformed by its body's initial F where its law has one."""
        from ..shapes.cpdi.reference import initial_domain

        P = self.particles
        F = np.tile(np.eye(self.dim), (P.count, 1, 1))
        for g in self.groups:
            st = g.initial_state(self.dim)
            if "F" in st:
                F[g.start:g.stop] = np.asarray(st["F"], np.float64).reshape(-1, self.dim, self.dim)
        return initial_domain(P.volume, self.dim, F)

    # ---- dt: auto recomputed during a rollout (issue #5 item 4) ---------------------------------
    def _max_speed(self, state) -> float:
        """Largest particle speed |v| of ``state`` [m/s] (a device reduction where a backend has one)."""
        v = self.to_numpy(state)["v"]
        return float(np.max(np.linalg.norm(v, axis=1), initial=0.0))

    def _observe_dt_note(self) -> None:
        """Gradient rollouts (``observe``) step with the build-time dt; say so once when the scene asks
        for an adaptive dt: auto (a dt that follows max |v| is piecewise constant in the controls and
        would make the step count per unit time depend on them)."""
        if self.scene.adaptive_dt and not getattr(self, "_observe_dt_noted", False):
            import warnings

            self._observe_dt_noted = True
            warnings.warn(
                f"scene '{self.scene.name}': observe() keeps the initial dt: auto step dt = {self._dt0:.4g} s for "
                f"every step (scene.dt_every = {self.scene.dt_every} applies to rollout() only); set a fixed "
                f"dt to silence this.", UserWarning, stacklevel=3)

    def _set_dt(self, dt: float | None) -> None:
        """Use ``dt`` for the following steps (None: back to the build-time dt). Backends that bake dt
        into compiled code override this to pass it as a runtime value instead."""
        self.dt = self._dt0 if dt is None else float(dt)

    # ---- shared logic ----------------------------------------------------------------------
    def meta(self) -> dict[str, Any]:
        s = self.scene
        return {
            "dim": s.dim, "dt": getattr(self, "_dt0", self.dt), "dx": s.dx, "grid_origin": s.origin.tolist(), "grid_shape": list(s.grid_shape),
            "gravity": s.gravity.tolist(), "backend": self.backend_name, "transfer": self.transfer.name,
            "shape": getattr(getattr(self, "shape", None), "name", "quadratic"),        # mpmlab.shapes
            "transfer_options": self.transfer.options(), "precision": self.precision, "scene": s.name,
            "laws": [g.law.name for g in self.groups],
            **({"dt_auto_every": int(s.dt_every), "cfl": float(s.cfl)} if s.adaptive_dt else {}),
        }

    def locate_failure(self, npstate: dict[str, np.ndarray]) -> tuple[int, str, Any] | None:
        """(particle, field, value) of the first bad value in a NumPy state, or None if all is well."""
        # a stepper whose shape function has a wider window (cubic B-splines) keeps a narrower region
        lo, hi = getattr(self, "inner_bounds", self.scene.inner_bounds)
        for name in ("x", "v"):
            a = npstate[name]
            bad = ~np.all(np.isfinite(a), axis=1)
            if bad.any():
                p = int(np.argmax(bad)); return p, name, a[p].tolist()
        for name in (*self.state_field_names, "C", "domain"):
            if name not in npstate:
                continue
            a = npstate[name].reshape(len(npstate[name]), -1)
            idx = npstate.get(name + "_particles", np.arange(len(a)))
            bad = ~np.all(np.isfinite(a), axis=1)
            if bad.any():
                k = int(np.argmax(bad)); return int(idx[k]), name, a[k].tolist()
        checks = [(n, f.check) for n, f in self.state_fields.items() if f.check and n in npstate]
        if checks:
            # scalar checks first (J before det F); det F <= 0 is reported as field "J" (the volume ratio)
            for name, check in sorted(checks, key=lambda c: c[1] != "positive"):
                J = npstate[name] if check == "positive" else np.linalg.det(npstate[name])
                idx = npstate.get(name + "_particles", np.arange(len(J)))
                bad = J <= 0
                if bad.any():
                    k = int(np.argmax(bad))
                    return int(idx[k]), name if check == "positive" else "J", float(J[k])
        x = npstate["x"]
        out = np.any((x < lo) | (x >= hi), axis=1)
        if out.any():
            p = int(np.argmax(out)); return p, "x (outside the domain)", x[p].tolist()
        if "domain" in npstate:             # CPDI: a corner of the particle's domain left the grid
            from ..shapes.cpdi.reference import corners

            xc = corners(x.astype(np.float64), npstate["domain"].astype(np.float64))
            out = np.any((xc < lo) | (xc >= hi), axis=(1, 2))
            if out.any():
                p = int(np.argmax(out)); c = int(np.argmax(np.any((xc[p] < lo) | (xc[p] >= hi), axis=1)))
                return p, "domain (a CPDI corner outside the domain)", xc[p, c].tolist()
        return None

    def cfl_number(self, npstate) -> float:
        speed = float(np.nanmax(np.linalg.norm(npstate["v"], axis=1), initial=0.0))
        return self.dt * (self.scene.wave_speed() + speed) / self.scene.dx

    def _diverged(self, start_state, start_step: int, steps: int, traj_so_far: Callable[[], Trajectory]):
        """Replay a failed chunk one step at a time to name the exact step, classify the cause from the
        states just before it (``mpmlab.core.diagnosis``), then raise.

        Bounded cost: the replay is the chunk's steps (as before), and only the chunk's start and the
        last three sound states are kept on the host for the diagnosis."""
        from collections import deque

        from .diagnosis import diagnose

        state = start_state
        first = self.to_numpy(state)
        recent = deque([first], maxlen=3)
        for k in range(steps):
            state = self._advance(state, 1)
            now = self.to_numpy(state)
            bad = self.locate_failure(now)
            if bad is not None:
                p, field, value = bad
                try:
                    d = diagnose(self, first, list(recent), now, bad, frames=list(getattr(self, "_frame_notes", ())))
                    hint, cause, measures = d.line, d.cause, d.measures
                except Exception as exc:   # the diagnosis must never hide the failure itself
                    C = self.cfl_number(recent[-1])
                    hint = (f"CFL number was {C:.3g} (cfl_limit {self.scene.cfl_limit:g}) one step before; "
                            f"diagnosis failed ({type(exc).__name__}: {exc})")
                    cause, measures = "unknown", {}
                raise SimulationDiverged(start_step + k + 1, p, field, value, hint, trajectory=traj_so_far(),
                                         cause=cause, measures=measures)
            recent.append(now)
        # The reduction flagged the chunk but the replay did not reproduce it (non-determinism).
        raise SimulationDiverged(start_step + steps, -1, "state", "non-finite (not reproduced on replay)",
                                 trajectory=traj_so_far())

    def rollout(self, state=None, steps: int = 100, every: int | None = None, fields: tuple[str, ...] = (),
                progress: bool | None = None, on_frame: Callable | None = None,
                keep_frames: bool = True) -> Trajectory:
        """Run ``steps`` steps keeping every ``every``-th frame (frame 0 = the initial state) and the last.

        ``every`` defaults to the scene's ``substeps`` (time steps per output frame).

        With ``dt: auto`` and ``scene.dt_every`` > 0 the time step is recomputed every ``dt_every``
        steps (and at the start) as ``cfl dx / (c_p + max |v|)`` of the current state; the kept
        frames' times (``Trajectory.t``) are the sums of the steps actually taken. Otherwise every
        step uses the build-time ``dt``.

        Args:
            state: start state (default ``init()``).
            fields: extra per-particle fields to keep per frame (``F``, ``C``, ``J``, ``sigma``, ``eps_p``).
            progress: show a tqdm bar (None: only when stderr is a terminal).
            on_frame: called as ``on_frame(frame_index, numpy_state)`` after each kept frame; the
                state carries its ``step`` and ``time`` (the last frame's step is ``steps`` itself
                when ``steps`` is not a multiple of ``every``).
            keep_frames: False: hand the frames to ``on_frame`` only, and return a trajectory with
                their steps and times but no frames (memory stays bounded on any horizon; the
                ``TrajectoryWriter`` streams them to disk).

        A stop signal (``mpmlab.core.signals``) is checked between chunks.
        """
        every = self.scene.substeps if every is None else every
        if steps < 0 or every < 1:
            raise ConfigError(f"rollout needs steps >= 0 and every >= 1 (got steps={steps}, every={every}).")
        from tqdm.auto import tqdm

        state = self.init() if state is None else state
        check = self.check_every or every
        adaptive = self.scene.adaptive_dt
        dt_every = self.scene.dt_every if adaptive else steps + 1
        frames: list[dict[str, np.ndarray]] = []
        step_ids: list[int] = []
        times: list[float] | None = [] if adaptive else None
        t_now = 0.0                      # simulated time (float64 sum of the steps taken; adaptive dt)

        from collections import deque

        from .diagnosis import frame_note

        self._frame_notes = deque(maxlen=64)   # J range and speed of the recent kept frames (diagnosis)

        def keep(npstate, step_id):
            self._frame_notes.append(frame_note(self, npstate, step_id))
            if keep_frames:
                frames.append({k: npstate[k] for k in ("x", "v", *fields) if k in npstate})
            step_ids.append(step_id)
            t = t_now if times is not None else step_id * self.dt
            if times is not None:
                times.append(t_now)
            npstate["time"], npstate["step"] = t, step_id   # the real labels, for on_frame consumers
            if on_frame is not None:
                with signals.deferred():       # a frame reaches all of on_frame's outputs or none
                    on_frame(len(step_ids) - 1, npstate)

        def partial():
            return self._trajectory(frames, step_ids, fields, times)

        npstate = self.to_numpy(state)
        bad = self.locate_failure(npstate)
        if bad is not None:
            raise SimulationDiverged(0, bad[0], bad[1], bad[2], "the initial state is already invalid")
        keep(npstate, 0)
        done = 0
        bar = tqdm(total=steps, disable=None if progress is None else not progress, mininterval=0.5,
                   unit="step", leave=False)
        t_first = None
        try:
            while done < steps:
                signals.check()
                if adaptive and done % dt_every == 0:
                    speed = self._max_speed(state)
                    if np.isfinite(speed):   # a non-finite state is left to the guard to report
                        self._set_dt(self.scene.auto_dt(speed))
                # chunk boundary: next kept frame, guard check or dt update, whichever comes first
                next_frame = (done // every + 1) * every
                next_check = (done // check + 1) * check
                next_dt = (done // dt_every + 1) * dt_every
                n = min(next_frame, next_check, next_dt, steps) - done
                start_state, start_step = state, done
                t0 = time.perf_counter()
                state = self._advance(state, n)
                if t_first is None:
                    self._block(state)
                    t_first = time.perf_counter() - t0
                done += n
                t_now += n * self.dt
                if done % check == 0 or done == steps:
                    if self._is_bad(state):
                        self._diverged(start_state, start_step, n, partial)
                if done % every == 0 or done == steps:   # the final state is always kept
                    keep(self.to_numpy(state), done)
                bar.update(n)
        finally:
            bar.close()
            if adaptive:
                self._set_dt(None)       # stepper.dt is the build-time dt again (observe, meta)
        return partial()

    def _block(self, state) -> None:
        """Wait for asynchronous work (JAX dispatch); no-op by default."""

    def _trajectory(self, frames, step_ids, fields, times=None) -> Trajectory:
        P = self.particles
        nparams = max(len(g.law.params) for g in self.groups)
        params = np.full((P.count, nparams), np.nan)
        materials = []
        for g in self.groups:
            params[g.start:g.stop, : g.params.shape[1]] = g.params
            materials.append({"law": g.law.name, "param_names": list(g.law.param_names()),
                              "start": g.start, "stop": g.stop, "provenance": _provenance(g.law.name)})
        stack = lambda k: np.stack([f[k] for f in frames]) if frames else np.zeros((0,))
        extra = {k: stack(k) for k in fields if frames and k in frames[0]}
        fp = {k: self._field_particles(k) for k in extra}
        steps = np.asarray(step_ids, dtype=np.int64)
        t = steps * self.dt if times is None else np.asarray(times, dtype=np.float64)
        return Trajectory(stack("x"), stack("v"), t, steps, P.mass, P.volume, P.material_id,
                          P.body_id, materials, params, self.meta(), extra, fp)

    def _field_particles(self, name: str) -> np.ndarray:
        if name in ("x", "v", "C"):
            return np.arange(self.particles.count)
        idx = [np.arange(g.start, g.stop) for g in self.groups if name in g.law.state_fields]
        return np.concatenate(idx) if idx else np.zeros(0, int)


def _provenance(name: str) -> str:
    from . import registry

    return registry.laws.provenance(name)
