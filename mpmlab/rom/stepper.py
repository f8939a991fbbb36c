"""``ReducedStepper``: MPM time-stepping of the latent x_hat only (Chen et al. 2023, Sec. 3, Alg. 2):
each step evaluates the full-space kinematics from the deformation map g at quadrature points, runs
one MPM step (P2G, grid update, boundaries, G2P) at a few sample points M, and projects the trial
positions and velocities back onto the manifold.

Built on a full-order JAX stepper of the same scene (``build_stepper(scene, "jax", "pic", ...)``): its
own pure ``step_fn`` is the MPM step, fed with pseudo-particles -- positions g(X; x_hat), velocities
dg/dx_hat v_hat, deformation gradients F = dg/dX as the law state, and per-step masses and volumes --
so P2G, the grid update, every boundary, G2P and the law's ``kirchhoff`` are the backend's, not copies.

* **Quadrature** ``lagrangian`` (Alg. 3): the material points that share a grid node with a sample
  point (their B-spline stencils, base nodes within 2 cells per axis, overlap), with their own mass and
  volume; every other point gets zero mass, so the nodes the samples read carry exactly what the full
  P2G puts there. (``eulerian``, Alg. 4, is not built yet: asking for it says so.)
* **Projection** ``linear`` (Alg. 7, Eq. 23) or ``nonlinear`` (Alg. 6, Eqs. 21-22: Gauss-Newton with
  Armijo backtracking from 2 x_hat_n - x_hat_{n-1}); ``mpmlab.rom.manifold``.
* **Samples** M: ``samples`` points drawn anew every step, uniformly without replacement from a seeded
  key, plus at least ``per_boundary`` (5) points of each particle_velocity region (a kinematic
  boundary, Sec. 3.3).
* **Initial state** (Eq. 19): x_hat(0), v_hat(0) fitted to the scene's initial positions and
  velocities, from the encoder's latent when the weights have one (else zero).
* PIC only and hyperelastic laws only (F must be a function of the deformation map): others refused.

One reduced step is one compiled JAX program (``jax.jit``); ``rollout`` keeps x_hat and the points'
positions every ``every`` steps; ``to_numpy(state, X)`` gives x, F and v at any reference points.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ..core.errors import ConfigError
from ..core.interfaces import AbstractStepper
from . import manifold as Mf
from . import networks as N

QUADRATURES = ("lagrangian", "eulerian")
PROJECTIONS = ("linear", "nonlinear")


class ReducedState(NamedTuple):
    z: object        # [d_hat] latent x_hat_n
    zdot: object     # [d_hat] latent velocity v_hat_n
    z_prev: object   # [d_hat] x_hat_{n-1} (the nonlinear projection's extrapolation)
    t: object        # time [s]
    key: object      # PRNG key of the sample draws


class ReducedStepper(AbstractStepper):
    """The reduced model of a scene (module doc). ``fom``: a JAX full-order stepper of the scene with
    the ``pic`` transfer; ``weights``: ``mpmlab.rom.networks.RomWeights`` (``networks.load``)."""

    def __init__(self, fom, weights, *, samples: int = 50, quadrature: str = "lagrangian",
                 projection: str = "linear", per_boundary: int = 5, seed: int = 0):
        import jax
        import jax.numpy as jnp

        if getattr(fom, "backend_name", "") != "jax":
            raise ConfigError("ReducedStepper: the reduced step is built on the JAX backend so far (the Warp one is "
                              "not written yet); build the full-order stepper with backend 'jax'.")
        if fom.transfer.name != "pic":
            raise ConfigError(f"ReducedStepper: transfer '{fom.transfer.name}'; the reduced model uses PIC (Sec. 3, "
                              f"Alg. 5): build the full-order stepper with transfer 'pic'.")
        for g in fom.groups:
            if g.law.plastic or "F" not in g.law.state_fields or set(g.law.state_fields) != {"F"}:
                raise ConfigError(f"ReducedStepper: law '{g.law.name}' is not hyperelastic (its state {list(g.law.state_fields)}"
                                  f"{', plastic' if g.law.plastic else ''}); the deformation map gives F only, so only "
                                  f"laws whose whole state is F are supported (e.g. fixed_corotated).")
        if quadrature not in QUADRATURES:
            raise ConfigError(f"ReducedStepper: quadrature '{quadrature}'; choose {' or '.join(QUADRATURES)}.")
        if quadrature == "eulerian":
            raise ConfigError("ReducedStepper: the Eulerian quadrature (Alg. 4) is not built yet; use 'lagrangian'.")
        if projection not in PROJECTIONS:
            raise ConfigError(f"ReducedStepper: projection '{projection}'; choose {' or '.join(PROJECTIONS)}.")
        spec = weights.spec
        P = fom.particles
        n, d = P.x.shape
        if spec.dim != d:
            raise ConfigError(f"ReducedStepper: the weights are for {spec.dim}D, the scene is {d}D.")
        samples = int(samples)
        if not spec.latent <= samples <= n:
            raise ConfigError(f"ReducedStepper: samples = {samples}; it must be at least the latent size {spec.latent} "
                              f"and at most the {n} material points.")
        self.fom, self.weights, self.scene = fom, weights, fom.scene
        self.quadrature, self.projection = quadrature, projection
        self.dim, self.dt, self.dtype = d, float(fom.dt), fom.dtype
        self.backend_name = "jax"
        dt = fom.dtype
        self.params = N.to_jax(weights.params, dt)
        self.norm = N.to_jax(weights.norm, dt)
        self.X = jnp.asarray(P.x, dt)
        # kinematic boundaries: at least per_boundary samples each (Sec. 3.3)
        forced = []
        for b in self.scene.boundaries:
            if getattr(b, "stage", "") == "particle_velocity":
                idx = np.asarray(b.select(P.x))
                forced.append(idx[:max(0, min(int(per_boundary), len(idx)))] if len(idx) else idx)
        self._forced = np.unique(np.concatenate(forced)).astype(np.int64) if forced else np.zeros(0, np.int64)
        if len(self._forced) > samples:
            raise ConfigError(f"ReducedStepper: samples = {samples} is fewer than the {len(self._forced)} points the "
                              f"kinematic boundaries need ({per_boundary} each).")
        self.samples, self.seed = samples, int(seed)
        free = np.setdiff1d(np.arange(n), self._forced)
        self._free = jnp.asarray(free)
        self._forced_j = jnp.asarray(self._forced)
        self._n_random = samples - len(self._forced)
        self._base0 = fom._node_x[0]
        self._fom_params = dict(fom.params)          # made here, outside any trace (it is cached on the stepper)
        self._step = jax.jit(self._step_impl)

    # ---- state ------------------------------------------------------------------------------------
    def init(self):
        """Eq. 19 from the scene's initial positions and velocities."""
        import jax
        import jax.numpy as jnp

        P = self.fom.particles
        x0, v0 = jnp.asarray(P.x, self.dtype), jnp.asarray(P.v, self.dtype)
        if self.weights.spec.n_points == len(P.x) and "e_fc1_W" in self.params:
            guess = N.encode(self.params, self.norm, x0.T)
        else:
            guess = jnp.zeros(self.weights.spec.latent, self.dtype)
        s = Mf.initial_state(self.params, self.norm, self.X, x0, v0, guess)
        return ReducedState(s.z, s.zdot, s.z, jnp.asarray(0.0, self.dtype), jax.random.PRNGKey(self.seed))

    def _sample(self, key):
        import jax
        import jax.numpy as jnp

        pick = jax.random.choice(key, self._free.shape[0], (self._n_random,), replace=False)
        return jnp.concatenate([self._forced_j, self._free[pick]])

    def _step_impl(self, s: ReducedState):
        import jax
        import jax.numpy as jnp

        key, sub = jax.random.split(s.key)
        M = self._sample(sub)
        X = self.X
        # full-space kinematics at the quadrature points (Alg. 3): x = g, F = dg/dX, v = dg/dx_hat v_hat
        x, F, dxdz = N.g_jacobians(self.params, self.norm, X, s.z[None, :])
        v = jnp.einsum("pdk,k->pd", dxdz, s.zdot)
        base = jnp.floor((x - self._base0) / self.scene.dx - 0.5).astype(jnp.int32)
        near = jnp.all(jnp.abs(base[:, None, :] - base[M][None, :, :]) <= 2, axis=-1)   # [N, |M|]
        quad = jnp.any(near, axis=1).astype(self.dtype)
        prm = dict(self._fom_params)
        prm["mass"] = prm["mass"] * quad
        prm["volume"] = prm["volume"] * quad
        law = tuple({"F": F[g.start:g.stop]} for g in self.fom.groups)
        state = {"x": x, "v": v, "law": law, "t": s.t}
        new = self.fom.step_fn(state, prm)                      # Alg. 5: P2G over P, grid, G2P (PIC)
        x_tr, v_tr = new["x"][M], new["v"][M]
        XM = X[M]
        vhat = Mf.project_velocity(self.params, self.norm, XM, s.z, v_tr)            # Eqs. 21 / 23
        if self.projection == "linear":
            z = Mf.project_linear(s.z, vhat, self.dt)                                # Alg. 7
        else:
            z = Mf.project_nonlinear(self.params, self.norm, XM, x_tr, s.z, s.z_prev)  # Alg. 6, Eq. 22
        return ReducedState(z, vhat, s.z, s.t + self.dt, key)

    def step(self, state):
        return self._step(state)

    def rollout(self, state=None, steps: int = 100, every: int = 1, **kw):
        """Run ``steps`` reduced steps; returns ``{"z": [T, d_hat], "x": [T, N, d], "time": [T]}`` (frames
        every ``every`` steps, the first one the initial state), and the final state as ``"state"``."""
        import jax.numpy as jnp

        state = self.init() if state is None else state
        every = max(1, int(every))
        zs, ts = [np.asarray(state.z)], [float(state.t)]
        for k in range(1, int(steps) + 1):
            state = self.step(state)
            if k % every == 0 or k == steps:
                zs.append(np.asarray(state.z)); ts.append(float(state.t))
                if not np.all(np.isfinite(zs[-1])):
                    from ..core.errors import SimulationDiverged

                    raise SimulationDiverged(k, -1, "z", zs[-1].tolist(), "the reduced state is non-finite; lower "
                                                                          "the time step")
        z = np.stack(zs)
        x = np.asarray(N.g_apply(self.params, self.norm, self.X[None], jnp.asarray(z)[:, None, :]))
        return {"z": z, "x": x, "time": np.asarray(ts), "state": state}

    def to_numpy(self, state, X=None) -> dict[str, np.ndarray]:
        """x, F, v at reference points ``X`` [Q, d] (default: the scene's material points) and x_hat."""
        import jax.numpy as jnp

        Xq = self.X if X is None else jnp.asarray(X, self.dtype)
        x, F, dxdz = N.g_jacobians(self.params, self.norm, Xq, state.z[None, :])
        return {"x": np.asarray(x), "F": np.asarray(F), "v": np.asarray(jnp.einsum("pdk,k->pd", dxdz, state.zdot)),
                "z": np.asarray(state.z), "t": float(state.t)}
