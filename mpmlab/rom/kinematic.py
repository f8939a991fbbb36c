"""Kinematic (Dirichlet) boundaries of the reduced model held at the position level.

The admissible deformation maps of the ROM paper (Sec. 2, Eq. 3) satisfy phi(X, t) = phi_bar(X, t) on
the Dirichlet part of the reference boundary: a condition on *positions*. The full-order model meets it
for a ``particle_velocity`` boundary by moving the prescribed particles exactly rigidly every step
(``mpmlab.boundaries.ParticleVelocity``), so their positions never drift. The reduced model evaluates
those points at g(X; x_hat), and the velocity least squares (Eqs. 21/23) gives them the prescribed
*velocity* only in the least-squares sense: whatever position error a step leaves (e.g. while a poke
pushes the body) is never corrected. On the continual poke (no gravity) the reduced body slid off its
held base by 0.13 mm in the first poke and rested there, a rigid offset that carries 99.8 % of the squared error
(benchmarks/rom.md, "Tab. 6: the base slid").

``kinematic="position"`` (the default of the reduced steppers) makes each sample point of an active
``particle_velocity`` region target its prescribed position at the end of the step: the nonlinear
projection (Eq. 22) fits that position, and the linear one (Alg. 7) steps x_hat with the velocity that
reaches it, (x_bar(t + dt) - g(X; x_hat_n)) / dt, which is the prescribed velocity when nothing has
drifted. v_hat is still fitted to the prescribed velocity. ``kinematic="velocity"`` is the earlier,
velocity-level hold.

Where the map cannot put the held points exactly where they belong while it follows the rest of the body,
the exact hold asks every step for the whole position error as a velocity ((0.05 mm) / dt = 0.18 m/s on the
poke, against the body's mm/s): those rows then outweigh the free ones in the least squares and can lock the
body in a strained state (benchmarks/rom.md). ``hold_steps`` = k closes 1/k of the error per step instead (a
relaxation time of k dt, as Baumgarte's stabilisation of constraint drift); 1 (the default) is the exact hold.

The prescribed position is the boundary's motion in closed form from the reference position X (the
scene's positions at t = 0): x_bar(t) = c(t) + R(omega t) (X - c(0)), with c(t) = c0 + v0 (t - t_start)
(a translation when omega is absent), which the full-order model's exactly rigid steps compose to.
It holds for boundaries acting from t = 0 (t_start <= 0); the reduced steppers refuse a later start
with ``kinematic="position"``.
"""
from __future__ import annotations

import numpy as np

from ..core.errors import ConfigError

KINEMATIC = ("position", "velocity")


class Holds:
    """The scene's ``particle_velocity`` boundaries as the reduced model holds them: ``which[p]`` is the
    boundary (in the stepper's particle-boundary order) that prescribes material point p, or -1; per
    boundary its centre c0, t_start, t_end and whether it rotates."""

    def __init__(self, scene, x0: np.ndarray, mode: str, steps: float = 1.0):
        if mode not in KINEMATIC:
            raise ConfigError(f"ReducedStepper: kinematic '{mode}'; choose {' or '.join(KINEMATIC)} (hold the "
                              f"particle_velocity boundaries' points at their prescribed positions, or velocities only).")
        if not float(steps) >= 1.0:
            raise ConfigError(f"ReducedStepper: hold_steps = {steps}; the position-level hold closes a held point's "
                              f"position error over this many steps: at least 1 (1: at once).")
        self.mode, self.steps = mode, float(steps)
        self.bcs = [b for b in scene.boundaries if getattr(b, "stage", "") == "particle_velocity"]
        self.which = np.full(len(x0), -1, np.int64)
        for i, b in enumerate(self.bcs):                 # a later boundary overrides, as the steppers apply them
            self.which[np.asarray(b.select(x0))] = i
            if mode == "position" and float(b.t_start) > 0.0:
                raise ConfigError(f"ReducedStepper: boundary '{b.name}' starts at t_start = {b.t_start} s; "
                                  f"kinematic='position' holds prescribed positions from t = 0 only: use "
                                  f"kinematic='velocity' for a boundary that starts later.")
        self.centers = [np.asarray(b.rotation_center(x0), float) for b in self.bcs]

    @property
    def active(self) -> bool:
        """Whether any point is held at the position level."""
        return self.mode == "position" and bool(np.any(self.which >= 0))

    def targets(self, xp, rotation, which_M, X_M, t1, params):
        """(x_bar [|M|, d], on [|M|] bool): the prescribed positions at time ``t1`` of sample points with
        reference positions ``X_M`` and boundaries ``which_M``, and which rows a boundary holds over the
        step that ends at ``t1`` (the window ``apply_particles`` tests). ``xp``: the array namespace
        (jax.numpy or torch), ``rotation(theta_vector) -> R``, ``params``: per boundary its
        ``velocity`` and (rotating) ``angular_velocity`` and ``center`` (c0, :attr:`centers`) in that namespace."""
        target, on = X_M, None
        for i, (b, p) in enumerate(zip(self.bcs, params)):
            v0 = p["velocity"]
            if b.rotating:
                w, c0 = p["angular_velocity"], p["center"]
                pos = c0 + v0 * (t1 - b.t_start) + (X_M - (c0 - v0 * b.t_start)) @ rotation(w * t1).T
            else:
                pos = X_M + v0 * t1
            hit = (which_M == i) & (t1 > b.t_start) & (t1 <= b.t_end)
            target = xp.where(hit[:, None], pos, target)
            on = hit if on is None else (on | hit)
        return target, on


def hold(holds: Holds, xp, rotation, which_M, X_M, x_M, x_tr, v_tr, t1, params, dt):
    """The samples' trial state with the position-level hold: (x_tr, v_step) where held rows get
    x_bar(t1) (or, with ``holds.steps`` = k > 1, the trial position moved 1/k of the way to it) and the
    velocity (that - x_M) / dt that the linear projection steps with; other rows keep x_tr and v_tr.
    Without held points: (x_tr, None), the velocity-level step unchanged."""
    if not holds.active:
        return x_tr, None
    target, on = holds.targets(xp, rotation, which_M, X_M, t1, params)
    if holds.steps != 1.0:
        target = x_tr + (target - x_tr) / holds.steps
    return xp.where(on[:, None], target, x_tr), xp.where(on[:, None], (target - x_M) / dt, v_tr)
