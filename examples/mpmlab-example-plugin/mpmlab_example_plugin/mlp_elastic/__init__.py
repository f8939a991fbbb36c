"""A small neural hyperelastic law with shared (group-level) weights: the example of a law whose
weights are differentiable controls on both backends (``controls()["law_weights"]``).

With B = F F^T, J = det F and the invariant features z = (tr B - d, J - 1), which vanish at rest::

    tau = s [ (c_0 + b(z)) (B - I) + (c_1 (J - 1) + a(z)) I ],    (a, b) = W2 tanh(W1 z)

* rest-state exact: z = 0 at F = I, and the MLP has no biases, so tau(I) = 0 exactly;
* rotation-equivariant: tau(Q F) = Q tau(F) Q^T (B -> Q B Q^T, z unchanged): an isotropic tensor
  function of B;
* small strain: tau ~ 2 c_0 s eps + c_1 s tr(eps) I (+ the MLP's linear part), i.e. Lame mu = c_0 s,
  lambda = c_1 s: it can represent linear elasticity and learn the nonlinear rest.

Shared weights: ``W1`` [width, 2], ``W2`` [2, width], ``c`` [2] (dimensionless; 4 width + 2 numbers,
the same for every particle of the group). Per-particle parameter: the stress scale ``s`` [Pa].
Options (the instance's configuration, ``material.options``): ``width``, ``seed`` (initial weights)
and ``weights_file`` (a safetensors file with W1, W2, c: the one file both backends read).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from mpmlab.core.errors import ConfigError
from mpmlab.core.interfaces import AbstractConstitutiveLaw, ParamSpec, StateField

from . import reference as _reference


@dataclass(frozen=True)
class Law(AbstractConstitutiveLaw):
    name: ClassVar[str] = "mlp_elastic"
    params = (ParamSpec("stress_scale", "Pa", 1.0e4, low=0.0, low_open=True,
                        doc="stress scale s (Lame mu = c_0 s, lambda = c_1 s at small strain)"),)
    state = (StateField("F", ("D", "D"), "identity", doc="deformation gradient", check="positive_det"),)
    plastic = False
    reference = _reference
    test_params = {"stress_scale": 1.0e4}
    implementations: ClassVar[dict] = {
        "jax": "mpmlab_example_plugin.mlp_elastic.jax:make",
        "warp": "mpmlab_example_plugin.mlp_elastic.warp:make",
    }

    #: hidden width of the MLP
    width: int = 8
    #: seed of the initial weights (W1, W2 ~ N(0, 0.1^2); c = (0.5, 0.5))
    seed: int = 0
    #: a safetensors file with the arrays W1, W2 and c (overrides width's initial values and seed)
    weights_file: str = ""

    def __post_init__(self):
        if int(self.width) < 1:
            raise ConfigError(f"law '{self.name}': width = {self.width} must be >= 1.")

    @classmethod
    def wave_speed(cls, params, density):
        # the CFL bound assumes lambda + 2 mu <= 4 s (c_0, c_1 and the MLP of order one)
        return math.sqrt(4.0 * params["stress_scale"] / density)

    def weight_shapes(self, dim):
        return {"W1": (int(self.width), 2), "W2": (2, int(self.width)), "c": (2,)}

    def initial_weights(self, dim):
        if self.weights_file:
            from safetensors.numpy import load_file

            try:
                return {k: np.asarray(a, dtype=float) for k, a in load_file(self.weights_file).items()}
            except (OSError, ValueError) as e:
                raise ConfigError(f"law '{self.name}': cannot read weights_file '{self.weights_file}': {e}") from None
        rng = np.random.default_rng(int(self.seed))
        w = int(self.width)
        return {"W1": 0.1 * rng.standard_normal((w, 2)), "W2": 0.1 * rng.standard_normal((2, w)),
                "c": np.array([0.5, 0.5])}


def save_weights(path: str, weights) -> None:
    """Write ``{W1, W2, c}`` (numpy, JAX arrays or torch tensors) as a safetensors file."""
    from safetensors.numpy import save_file

    save_file({k: np.ascontiguousarray(np.asarray(getattr(a, "detach", lambda: a)(), dtype=np.float64))
               for k, a in weights.items()}, path)
