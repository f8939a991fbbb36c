"""Observation operators (JAX-MPM Sec. 3.2, Eqs. 26-28): what an instrument sees of a state.

An observation is a backend-neutral description; each names its JAX and Warp implementation, like a
law. Applied to a state it gives an array ``[L, d]`` (L observed indices, d components):

* :class:`Lagrangian` -- Eq. 26: the positions or velocities of a set of particles (all, a random
  subset of a given size, or given indices).
* :class:`Eulerian` -- Eq. 27: the average velocity (or position) of the particles inside fixed
  square/cube monitor regions Omega_l (half-size ``half_size`` around ``centers``). Membership is an
  indicator of the particle position, so gradients flow through the averaged quantity only (the region
  boundary is not differentiable, as in the paper). A region with no particle reads 0 (and its mask
  entry is what a loss should use to skip it: ``Eulerian.empty`` on the host side).

Time masks and noise are shared by every observation (``ObservationSchedule``): the steps at which
it is taken, an optional binary mask m_{l,t} (Eq. 28), and Gaussian noise added to *reference*
observations only (a fit compares noisy data with noise-free predictions).

Backends: ``implementation("jax", "observation")(obs, stepper)`` returns an object with
``fn(state) -> jnp [L, d]`` (pure, differentiable); ``implementation("warp", "observation")(obs,
stepper)`` returns an object whose ``launch(state, out)`` records Warp kernels (on the active tape)
writing ``out`` (a ``wp.array`` of L vectors of length d).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar, Mapping, Sequence

import numpy as np

from ..core.errors import ConfigError
from ..core.interfaces import AbstractObservation

QUANTITIES = ("x", "v")


def _impl(name: str) -> dict[str, str]:
    return {"jax": f"mpmlab.observations.jax:{name}", "warp": f"mpmlab.observations.warp:{name}"}


def _check_quantity(kind: str, q: str) -> None:
    if q not in QUANTITIES:
        raise ConfigError(f"observation '{kind}': quantity '{q}' unknown; use one of {QUANTITIES} (positions, velocities).")


@dataclass(frozen=True)
class Lagrangian(AbstractObservation):
    """Positions (``quantity="x"``) or velocities (``"v"``) of tracked particles (JAX-MPM Eq. 26).

    ``particles``: None or ``"all"`` = every particle; an int n = n particles drawn without replacement
    with ``seed`` (JAX-MPM Sec. 5.1-5.3 "randomly selected"); a list = those scene indices.
    """

    name: ClassVar[str] = "lagrangian"
    implementations: ClassVar[dict] = _impl("lagrangian")
    gradients: ClassVar[tuple] = ("jax", "warp")
    quantity: str = "x"
    particles: Any = None
    seed: int = 0

    def indices(self, n_particles: int) -> np.ndarray:
        """The observed particle indices (scene order), sorted."""
        _check_quantity(self.name, self.quantity)
        p = self.particles
        if p is None or (isinstance(p, str) and p == "all"):
            return np.arange(n_particles)
        if isinstance(p, (int, np.integer)) and not isinstance(p, bool):
            if not 1 <= p <= n_particles:
                raise ConfigError(f"observation 'lagrangian': particles = {p} must be in [1, {n_particles}] "
                                  f"(the scene has {n_particles} particles).")
            return np.sort(np.random.default_rng(self.seed).choice(n_particles, size=int(p), replace=False))
        idx = np.asarray(p, dtype=np.int64).reshape(-1)
        if idx.size == 0 or idx.min() < 0 or idx.max() >= n_particles:
            raise ConfigError(f"observation 'lagrangian': particle indices must lie in [0, {n_particles - 1}].")
        return idx

    def output_shape(self, scene) -> tuple[int, int]:
        return (len(self.indices(scene.particles().count)), scene.dim)


@dataclass(frozen=True)
class ParticleState(Lagrangian):
    """A matrix state of tracked particles (``particles``, ``seed`` as :class:`Lagrangian`), flattened
    row-major to D^2 numbers: ``quantity="C"`` (the APIC/MLS affine matrix) or ``"F"`` (the deformation
    gradient every material group's law carries). What a strain gauge reads; NCLaw's kinematics-only
    teacher forcing (``mpmlab.inverse.teacher``) carries C and F across a position reset with it.
    Scene-order (differentiable-path) states only."""

    name: ClassVar[str] = "particle_state"
    implementations: ClassVar[dict] = _impl("particle_state")
    quantity: str = "F"

    def indices(self, n_particles: int) -> np.ndarray:
        if self.quantity not in ("C", "F"):
            raise ConfigError(f"observation 'particle_state': quantity '{self.quantity}' unknown; use C or F.")
        return Lagrangian(quantity="x", particles=self.particles, seed=self.seed).indices(n_particles)

    def output_shape(self, scene) -> tuple[int, int]:
        return (len(self.indices(scene.particles().count)), scene.dim * scene.dim)


@dataclass(frozen=True)
class Eulerian(AbstractObservation):
    """Average ``quantity`` of the particles inside square/cube monitors (JAX-MPM Eq. 27 / Eq. 34).

    ``centers``: [L, D] monitor centres; ``half_size``: half the side of each monitor (JAX-MPM Sec. 5.1
    uses 0.01 m and a 3 x 3 grid of centres {0.2, 0.3, 0.4} x {0.1, 0.2, 0.3})."""

    name: ClassVar[str] = "eulerian"
    implementations: ClassVar[dict] = _impl("eulerian")
    gradients: ClassVar[tuple] = ("jax", "warp")
    centers: Sequence[Sequence[float]] = ()
    half_size: float = 0.01
    quantity: str = "v"

    def centers_array(self, dim: int) -> np.ndarray:
        _check_quantity(self.name, self.quantity)
        c = np.asarray(self.centers, dtype=float)
        if c.ndim != 2 or c.shape[0] == 0 or c.shape[1] != dim:
            raise ConfigError(f"observation 'eulerian': centers must be a non-empty list of {dim}D points, got shape {c.shape}.")
        if not self.half_size > 0:
            raise ConfigError(f"observation 'eulerian': half_size = {self.half_size} must be > 0.")
        return c

    def output_shape(self, scene) -> tuple[int, int]:
        return (len(self.centers_array(scene.dim)), scene.dim)

    def empty(self, x: np.ndarray) -> np.ndarray:
        """[L] bool: monitors with no particle at positions ``x`` [N, D] (NumPy, host side)."""
        c = self.centers_array(x.shape[1])
        inside = np.all(np.abs(x[None, :, :] - c[:, None, :]) <= self.half_size, axis=-1)
        return ~inside.any(axis=1)


def apply_numpy(obs: AbstractObservation, state: Mapping[str, np.ndarray]) -> np.ndarray:
    """The observation of a NumPy state (``stepper.to_numpy`` / a trajectory frame): the oracle the
    backend implementations are tested against."""
    x = np.asarray(state["x"], float)
    z = np.asarray(state[obs.quantity], float)
    if isinstance(obs, ParticleState):
        return z[obs.indices(len(x))].reshape(-1, x.shape[1] ** 2)
    if isinstance(obs, Lagrangian):
        return z[obs.indices(len(x))]
    if isinstance(obs, Eulerian):
        c = obs.centers_array(x.shape[1])
        inside = np.all(np.abs(x[None, :, :] - c[:, None, :]) <= obs.half_size, axis=-1)   # [L, N]
        cnt = inside.sum(axis=1)
        return (inside.astype(float) @ z) / np.maximum(cnt, 1)[:, None]
    raise ConfigError(f"observation '{getattr(obs, 'name', obs)}' has no NumPy oracle.")


@dataclass(frozen=True)
class ObservationSchedule:
    """When an observation is taken and how reference data are perturbed.

    ``steps``: the simulation steps after which the state is observed (0 = the initial state), sorted,
    unique. ``mask``: optional [T, L] binary m_{l,t} (JAX-MPM Eq. 28); None = all ones.
    ``noise``: standard deviation of Gaussian noise added to reference observations (``seed``)."""

    steps: Sequence[int]
    mask: Any = None
    noise: float = 0.0
    seed: int = 0

    def steps_array(self, total_steps: int | None = None) -> np.ndarray:
        s = np.asarray(self.steps, dtype=np.int64).reshape(-1)
        if s.size == 0:
            raise ConfigError("observation schedule: no observation steps given.")
        if np.any(np.diff(s) <= 0) or s[0] < 0:
            raise ConfigError("observation schedule: steps must be non-negative and strictly increasing.")
        if total_steps is not None and s[-1] > total_steps:
            raise ConfigError(f"observation schedule: step {int(s[-1])} is after the last simulated step {total_steps}.")
        return s

    @staticmethod
    def last_frames(total_steps: int, frames: int, every: int) -> "ObservationSchedule":
        """The last ``frames`` observations, ``every`` steps apart, ending at ``total_steps`` (JAX-MPM
        Sec. 5.1: the final 100 frames sampled from the last 1000 steps)."""
        s = total_steps - every * np.arange(frames)[::-1]
        if s[0] < 0:
            raise ConfigError(f"observation schedule: {frames} frames {every} steps apart do not fit in {total_steps} steps.")
        return ObservationSchedule(steps=tuple(int(v) for v in s))

    def mask_array(self, shape: tuple[int, int]) -> np.ndarray:
        if self.mask is None:
            return np.ones(shape)
        m = np.asarray(self.mask, float)
        if m.shape != shape:
            raise ConfigError(f"observation schedule: mask has shape {m.shape}, expected {shape} (frames x observed indices).")
        return m

    def add_noise(self, values: np.ndarray) -> np.ndarray:
        if not self.noise:
            return np.asarray(values, float)
        rng = np.random.default_rng(self.seed)
        return np.asarray(values, float) + self.noise * rng.standard_normal(np.shape(values))


def make_observation(spec: Mapping[str, Any]) -> AbstractObservation:
    """Build an observation from a config mapping ``{kind: NAME, ...options}``."""
    from ..core import registry

    return registry.observations.build(spec)
