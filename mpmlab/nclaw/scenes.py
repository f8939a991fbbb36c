"""NCLaw's evaluation scene set (Ma et al., ICML 2023, Sec. 4; release ``experiments/scripts/eval/*.py``)
and its metric.

:func:`eval_cases` lists, for one training material, the runs NCLaw evaluates a learned law on. Each
:class:`EvalCase` is a Hydra scene plus overrides; :meth:`EvalCase.truth` gives the ground-truth run's
overrides (the material's true law) and :meth:`EvalCase.learned` the learned run's (``material=nclaw``
with a weights file) -- the same scene, steps and frames, so an eval task runs both and compares
positions with :meth:`EvalCase.mse` (:func:`position_mse`)::

    for case in eval_cases("jelly"):
        truth = case.truth()                       # ["scene=nclaw_jelly", "material=jelly", "steps=1000", ...]
        learned = case.learned("ckpt/0300.safetensors")

| case | NCLaw | here |
|---|---|---|
| reconstruction | the training scene, 1000 steps, 20^3 | ``nclaw_<material>`` |
| time | (a) 2000 steps, 5000 for WATER | ``nclaw_<material>``, ``steps`` |
| velocity_seed1/7/8 | (b) ``sample_vel`` seeds 1, 7, 8 | ``nclaw_<material>`` + velocities (:func:`sample_velocity`) |
| geometry | (c) a mesh, ~30k particles, 32^3, 2000 steps, "mild" velocity | ``nclaw_geometry_<material>`` |
| incline | (d) WATER only, gravity (0, -1, 0.866), 128^3, 1500 steps (qualitative) | ``nclaw_incline`` |
| contact | Fig. 3b, four JELL-O toys, 32^3 | ``nclaw_contact`` (JELL-O only) |
| pool | Fig. 4a, a JELL-O body into WATER | ``jelly_pool_drop`` (JELL-O only; the water stays the true law) |
| melting | Fig. 4b, PLASTICINE turning into SAND bottom-up | ``nclaw_melting`` (PLASTICINE, with SAND's weights as partner) |

Meshes: spot and blub are Keenan Crane's (CC0), the armadillo, bunny, duck and dragon are stand-ins
(``mpmlab/assets/README.md``), so the geometry, incline and contact numbers are not the paper's. The
melting scene runs the ``phase_change`` law (a per-particle switch time by initial height): the truth
switches between the two true laws, the learned run between the PLASTICINE and the SAND networks, so
it needs both trainings' weights (``learned(weights, {"sand": file})``).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..core.errors import ConfigError

#: the four NCLaw training materials (``conf/material/<name>.yaml``, scenes ``nclaw_<name>``)
MATERIALS = ("jelly", "sand", "plasticine", "water")
#: NCLaw's seeds of task (b) (``experiments/scripts/eval/vel.py``)
VELOCITY_SEEDS = (1, 7, 8)
#: frames are kept every this many steps, the stride of NCLaw's metric (``diff_mse``: index % 5 == 0)
METRIC_EVERY = 5


@dataclass(frozen=True)
class EvalCase:
    """One evaluation run: ``scene`` (a ``conf/scene`` name), ``overrides`` on top of it (shared by the
    ground-truth and the learned run), ``steps``, the ``material`` whose true law is the ground truth,
    and a ``description``. Frames are kept every ``frame_every`` steps."""

    name: str
    scene: str
    overrides: tuple[str, ...]
    steps: int
    description: str
    material: str
    frame_every: int = METRIC_EVERY
    tags: tuple[str, ...] = field(default=())
    #: the ground truth's material config (default: ``material``); the learned run's
    truth_material: str = ""
    learned_material: str = "nclaw"
    #: where each material's trained weights go in the learned run: ``((material, override key), ...)``;
    #: default ``((material, "+material.options.weights_file"),)``. A case that mixes materials (melting)
    #: names several: the others are its ``partners``
    weight_keys: tuple[tuple[str, str], ...] = field(default=())

    def _common(self) -> list[str]:
        return [f"scene={self.scene}", *self.overrides, f"steps={self.steps}", f"frame_every={self.frame_every}"]

    @property
    def partners(self) -> tuple[str, ...]:
        """The other materials whose trained weights the learned run needs besides ``material``'s."""
        return tuple(m for m, _ in self.weight_keys if m != self.material)

    def truth(self) -> list[str]:
        """Hydra overrides of the ground-truth run (the material's true law)."""
        return [f"material={self.truth_material or self.material}", *self._common()]

    def learned(self, weights_file: str | None = None, partner_weights: dict | None = None) -> list[str]:
        """Hydra overrides of the learned run: ``material=nclaw`` (with ``weights_file``, a trained
        network; without it the untrained initialisation, NCLaw's "ours-init"); ``partner_weights``:
        ``{material: file}`` for the ``partners`` of a case that mixes materials."""
        out = [f"material={self.learned_material}", *self._common()]
        files = {**(partner_weights or {}), self.material: weights_file}
        for material, key in self.weight_keys or ((self.material, "+material.options.weights_file"),):
            if files.get(material):
                out.append(f"{key}={files[material]}")
        return out

    @property
    def metric_every(self) -> int:
        """The stride over this case's kept frames that gives NCLaw's every-5th-step metric."""
        return METRIC_EVERY // self.frame_every

    def mse(self, x_pred: np.ndarray, x_true: np.ndarray) -> float:
        """NCLaw's metric on two runs of this case, frames as kept (every ``frame_every`` steps)."""
        return position_mse(x_pred, x_true, every=self.metric_every)


def sample_velocity(seed: int, lin_bound: tuple[float, float] = (0.0, 3.0),
                    ang_bound: tuple[float, float] = (0.0, 3.0)) -> tuple[np.ndarray, np.ndarray]:
    """NCLaw's ``sample_vel`` (task (b)): ``(v [m/s], omega [rad/s])`` from ``PCG64(seed)``.

    Draw order (as the release, ``nclaw/utils.py``): a direction U[-1, 1]^3, its y made <= 0 (negated
    when positive) and normalised; the speed U[0, 3]; omega U[0, 3]^3. Seed 1 gives v = (0.059, -2.233,
    -1.764), omega = (0.9355, 1.2700, 2.4831); seed 7 v = (0.169, -0.537, 0.373), omega = (0.9005,
    2.6207, 0.0158); seed 8 v = (-0.747, -2.104, -0.783), omega = (2.6097, 1.1733, 1.3136).
    """
    rng = np.random.Generator(np.random.PCG64(seed))
    direction = rng.uniform(-1.0, 1.0, size=3)
    if direction[1] > 0:
        direction[1] = -direction[1]
    direction /= np.linalg.norm(direction)
    v = direction * rng.uniform(*lin_bound)
    omega = rng.uniform(*ang_bound, size=3)
    return v, omega


def _vec(a) -> str:
    return "[" + ",".join(repr(float(x)) for x in a) + "]"


def eval_cases(material: str) -> list[EvalCase]:
    """NCLaw's evaluation runs for a law trained on ``material`` (jelly, sand, plasticine, water)."""
    if material not in MATERIALS:
        raise ConfigError(f"NCLaw evaluation: unknown material '{material}'; choose one of {', '.join(MATERIALS)}.")
    train = f"nclaw_{material}"
    cases = [
        EvalCase("reconstruction", train, (), 1000, "the training trajectory, rolled out from its initial state "
                 "without teacher forcing (1000 steps, 20^3)", material),
        EvalCase("time", train, (), 5000 if material == "water" else 2000,
                 "(a) extended time: the training scene run for 2000 steps (5000 for WATER, as the release)",
                 material),
    ]
    for seed in VELOCITY_SEEDS:
        v, w = sample_velocity(seed)
        cases.append(EvalCase(
            f"velocity_seed{seed}", train,
            (f"scene.bodies.cube.velocity={_vec(v)}", f"scene.bodies.cube.angular_velocity={_vec(w)}"), 1000,
            f"(b) unseen velocity, sample_vel seed {seed}: v = {np.round(v, 3).tolist()} m/s, "
            f"omega = {np.round(w, 3).tolist()} rad/s", material))
    cases.append(EvalCase(
        "geometry", f"nclaw_geometry_{material}", (), 2000,
        "(c) challenging geometry: a ~30k-particle mesh body, 32^3 grid, v = [1, -1.5, -1.5], omega = [1, 1, 1] "
        "(spot and blub are NCLaw's own meshes; the armadillo and bunny are stand-ins)", material))
    if material == "water":
        cases.append(EvalCase(
            "incline", "nclaw_incline", (), 1500,
            "(d) inclined plane: gravity (0, -1, 0.866), rho 5e3, 128^3 grid (qualitative, not in Tab. 2; "
            "a stand-in for the dragon)", material, tags=("qualitative",)))
    if material == "plasticine":
        cases.append(EvalCase(
            "melting", "nclaw_melting", (), 2000,
            "Fig. 4b: an ice cream of PLASTICINE turning into SAND bottom-up between 0.25 and 0.75 s (steps 500-1500), "
            "64^3 grid, the phase_change law of the two true laws / of the PLASTICINE and SAND nets (a stand-in shape)",
            material, tags=("qualitative",), truth_material="plasticine_to_sand",
            learned_material="nclaw_plasticine_to_sand",
            weight_keys=(("plasticine", "material.options.before.options.weights_file"),
                         ("sand", "material.options.after.options.weights_file"))))
    if material == "jelly":
        cases.append(EvalCase(
            "contact", "nclaw_contact", (), 1000,
            "Fig. 3b: four JELL-O toys thrown at each other, 32^3 grid", material, tags=("qualitative",)))
        cases.append(EvalCase(
            "pool", "jelly_pool_drop", ("scene.dt=5.0e-4",), 3000,
            "Fig. 4a: a JELL-O ball dropped into a WATER pool (the water keeps its true law), fixed dt 5e-4 s, "
            "3000 steps", material, tags=("qualitative",)))
    return cases


def position_mse(x_pred: np.ndarray, x_true: np.ndarray, every: int = METRIC_EVERY) -> float:
    """NCLaw's metric (``nclaw/utils.py diff_mse``): the mean over frames 0, every, 2 every, ... of the
    per-coordinate mean squared position error [m^2]; ``x_pred``, ``x_true``: ``[T, N, D]`` with frames
    as saved at every step (for frames kept every k steps, ``every = 5 // k``)."""
    a, b = np.asarray(x_pred, dtype=np.float64), np.asarray(x_true, dtype=np.float64)
    if a.shape != b.shape or a.ndim != 3:
        raise ConfigError(f"position_mse: x_pred {a.shape} and x_true {b.shape} must both be [T, N, D] of one shape "
                          f"(the same scene, steps and frame spacing).")
    if not (isinstance(every, (int, np.integer)) and every >= 1):
        raise ConfigError(f"position_mse: every = {every!r} must be an integer >= 1.")
    if a.shape[0] == 0:
        raise ConfigError("position_mse: the trajectories have no frame.")
    d = a[::every] - b[::every]
    return float(np.mean(np.mean(d * d, axis=(1, 2))))
