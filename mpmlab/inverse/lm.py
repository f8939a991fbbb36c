"""Levenberg-Marquardt for fits of a few parameters (scalars and per-segment arrays), on either backend.

Why it exists: the loss of ``task=inverse`` is a sum of squared residuals (JAX-MPM Eq. 28), and with a
handful of parameters the Gauss-Newton matrix J^T J (P x P) is cheap. It couples the parameters, so one
step moves each by what the data say about it jointly. Adam, the paper's optimiser, moves every
parameter by about its learning rate whatever its gradient's size: in the basal-friction problem of
JAX-MPM Sec. 5.3 the first Adam steps raise mu_0 together with the under-estimated mu_1 (both slow the
flow) until the floor under the column sticks (Eq. 36 takes mu' < mu), where d loss / d mu_0 = 0 and
it never comes back (measured in benchmarks/inverse.md). Levenberg-Marquardt from the same start
recovers all four coefficients in ~10 iterations.

One iteration ("epoch"): residuals r and Jacobian J at x, then trial steps
    (J^T J + lambda D) dx = -J^T r,    D = diag(J^T J)     (Marquardt 1963 scaling)
until the loss r.r decreases (accept, lambda /= decrease) or ``max_tries`` fail (lambda *= increase each
time; then the fit has converged: no step along the damped Gauss-Newton direction lowers the loss).

The Jacobian comes from the backend's autodiff adapter (:mod:`mpmlab.core.autodiff`), the same way on
every backend: ``jacobian`` names a mode, the adapter's ``residual_functions`` computes it by AD if it
offers that mode (``jacobian_modes``), and ``central`` finite differences of its residuals work on any
backend. ``auto`` is the adapter's ``default_jacobian``:

* JAX: ``forward`` (``jax.jacfwd``: one batched rollout carrying P tangents); ``reverse``
  (``jax.jacrev``) and ``central`` on request.
* Warp: ``central`` (the tape has no forward mode: 2P forward rollouts; run the fit in fp64 --
  ``precision=fp64`` -- so that the differences are not round-off); ``reverse`` on request (one
  rollout, then one backward pass per residual the mask keeps). A backward pass costs 2-3 forward
  rollouts, so reverse mode pays off only with fewer residuals than about P. Measured on the CPU for
  the 32-particle, 400-step sliding block of ``tests/test_inverse_lm.py`` with P = 2 and 40 residuals:
  13 s per Jacobian against 0.8 s for central differences. JAX's ``jacrev`` takes 1.6 s against
  0.06 s for ``jacfwd`` at 40 residuals, and 46 s against 0.08 s at 640.

Select it as the optimiser of either backend::

    task.optimizer.jax:  {_target_: mpmlab.inverse.lm.LevenbergMarquardt}
    task.optimizer.warp: {_target_: mpmlab.inverse.lm.LevenbergMarquardt}

It has no learning rate: ``task.lr_schedule`` is not used.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..core.errors import ConfigError

JACOBIANS = ("auto", "forward", "reverse", "central")


@dataclass
class LevenbergMarquardt:
    damping: float = 1e-2        # initial lambda
    increase: float = 4.0        # lambda *= increase after a rejected trial step
    decrease: float = 3.0        # lambda /= decrease after an accepted one
    min_damping: float = 1e-9
    max_tries: int = 12          # rejected trial steps in a row before the fit counts as converged
    max_step: float = 2.0        # largest change of one raw (transformed) parameter per iteration
    jacobian: str = "auto"       # auto: the adapter's default (forward-mode AD on JAX, central differences on Warp)
    fd_step: float = 1e-3        # central differences: h = fd_step (1 + |x|) per raw parameter
    max_parameters: int = 64     # J^T J is P x P and the Jacobian costs ~P rollouts

    def __post_init__(self):
        where = "task.optimizer (LevenbergMarquardt)"
        if self.jacobian not in JACOBIANS:
            raise ConfigError(f"{where}: jacobian = '{self.jacobian}' unknown; use one of {JACOBIANS}.")
        for name in ("damping", "increase", "decrease", "max_step", "fd_step"):
            if not float(getattr(self, name)) > 0:
                raise ConfigError(f"{where}: {name} = {getattr(self, name)} must be positive.")
        if self.increase <= 1 or self.decrease <= 1:
            raise ConfigError(f"{where}: increase and decrease must be > 1 (got {self.increase}, {self.decrease}).")
        if int(self.max_tries) < 1:
            raise ConfigError(f"{where}: max_tries = {self.max_tries} must be >= 1.")

    def jacobian_kind(self, adapter) -> str:
        """The Jacobian mode on a backend: ``adapter`` is its autodiff adapter (or the backend's registry name)."""
        if isinstance(adapter, str):
            from ..core.autodiff import adapter_class

            adapter = adapter_class(adapter)
        if self.jacobian == "auto":
            return adapter.default_jacobian
        if self.jacobian != "central" and self.jacobian not in adapter.jacobian_modes:
            raise ConfigError(f"task.optimizer: LevenbergMarquardt jacobian = '{self.jacobian}' needs "
                              f"{self.jacobian}-mode AD, which backend '{adapter.name}' does not have; use "
                              f"jacobian: central (or auto).")
        return self.jacobian

    def propose(self, r: np.ndarray, J: np.ndarray, damping: float) -> np.ndarray:
        """The damped Gauss-Newton step for residuals ``r`` (N) and Jacobian ``J`` (N x P)."""
        A = J.T @ J
        g = J.T @ r
        D = np.diag(A).copy()
        # a parameter the data do not see (zero column) gets a floor, so that it simply does not move
        D = np.maximum(D, 1e-12 * max(float(D.max(initial=0.0)), 1e-300))
        try:
            dx = -np.linalg.solve(A + damping * np.diag(D), g)
        except np.linalg.LinAlgError:
            dx = -np.linalg.lstsq(A + damping * np.diag(D), g, rcond=None)[0]
        # per-parameter bound: a poorly seen parameter with a huge step does not shrink the others' steps
        return np.clip(dx, -self.max_step, self.max_step)

    def central_jacobian(self, residual: Callable[[np.ndarray], np.ndarray | None], x: np.ndarray) -> np.ndarray:
        """(r(x + h e_k) - r(x - h e_k)) / 2h per parameter; a diverged side falls back to a one-sided difference."""
        cols = []
        r0 = None
        for k in range(x.size):
            h = self.fd_step * (1.0 + abs(float(x[k])))
            e = np.zeros_like(x)
            e[k] = h
            rp, rm = residual(x + e), residual(x - e)
            if rp is not None and rm is not None:
                cols.append((rp - rm) / (2 * h))
                continue
            r0 = residual(x) if r0 is None else r0
            if rp is not None:
                cols.append((rp - r0) / h)
            elif rm is not None:
                cols.append((r0 - rm) / h)
            else:
                raise ConfigError(f"task.optimizer (LevenbergMarquardt): the rollout diverges on both sides of raw "
                                  f"parameter {k} (h = {h:.3g}); lower fd_step.")
        return np.stack(cols, axis=1)
