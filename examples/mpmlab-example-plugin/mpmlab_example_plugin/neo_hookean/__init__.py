"""Compressible Neo-Hookean hyperelasticity (Bonet & Wood, Nonlinear Continuum Mechanics, Eq. 6.28):

    psi = mu/2 (tr(F^T F) - d) - mu log J + lambda/2 (log J)^2
    tau = P F^T = mu (F F^T - I) + lambda log(J) I

No plasticity: the state is F, advanced by F <- (I + dt grad_v) F.
"""
from __future__ import annotations

import math
from typing import ClassVar

from mpmlab.core.interfaces import AbstractConstitutiveLaw, ParamSpec, StateField

from . import reference as _reference


class Law(AbstractConstitutiveLaw):
    name: ClassVar[str] = "neo_hookean"
    params = (
        ParamSpec("E", "Pa", 5.0e4, low=0.0, low_open=True, doc="Young's modulus"),
        ParamSpec("nu", "-", 0.3, low=-1.0, high=0.5, low_open=True, high_open=True, doc="Poisson ratio"),
    )
    state = (StateField("F", ("D", "D"), "identity", doc="deformation gradient", check="positive_det"),)
    test_params = {"E": 2e4, "nu": 0.3}
    plastic = False
    reference = _reference
    implementations: ClassVar[dict] = {
        "jax": "mpmlab_example_plugin.neo_hookean.jax:make",
        "warp": "mpmlab_example_plugin.neo_hookean.warp:make",
    }

    @classmethod
    def wave_speed(cls, params, density):
        E, nu = params["E"], params["nu"]
        mu = E / (2.0 * (1.0 + nu))
        lam = E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
        return math.sqrt((lam + 2.0 * mu) / density)
