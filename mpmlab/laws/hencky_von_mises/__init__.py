"""Hencky elasticity with von Mises plasticity (NCLaw App. B, Eqs. 17-19; Hu et al. 2018): PLASTICINE."""
from __future__ import annotations

import math
from typing import ClassVar

from ...core.interfaces import AbstractConstitutiveLaw, ParamSpec
from .. import _linalg_np
from . import reference as _reference


class Law(AbstractConstitutiveLaw):
    """tau = U (2 mu eps + lambda tr(eps) I) U^T in the Hencky strain (Eq. 17, a Kirchhoff stress; P = tau F^-T)
    with the isochoric von Mises return map of Eqs. 18-19.

    ``yield_stress`` is tau_Y of Eq. 18: the yield limit on the Frobenius norm of the deviatoric Kirchhoff
    stress, |dev tau| <= tau_Y. For a uniaxial yield stress sigma_y (von Mises sqrt(3/2)|dev tau| <= sigma_y),
    tau_Y = sqrt(2/3) sigma_y. In 2D the deviator is taken over d = 2 dimensions.
    """

    name: ClassVar[str] = "hencky_von_mises"
    params = (
        ParamSpec("E", "Pa", 1.0e5, low=0.0, low_open=True, doc="Young's modulus"),
        ParamSpec("nu", "-", 0.3, low=-1.0, high=0.5, low_open=True, high_open=True, doc="Poisson ratio"),
        ParamSpec("yield_stress", "Pa", 3.0e3, low=0.0, low_open=True,
                  doc="yield stress tau_Y (Frobenius norm of the deviatoric Kirchhoff stress, = sqrt(2/3) sigma_y)"),
    )
    state_fields = ("F",)
    plastic = True
    reference = _reference
    implementations: ClassVar[dict] = {
        "jax": "mpmlab.laws.hencky_von_mises.jax:make",
        "warp": "mpmlab.laws.hencky_von_mises.warp:make",
    }

    @classmethod
    def wave_speed(cls, params, density):
        mu, lam = _linalg_np.lame(params["E"], params["nu"])
        return math.sqrt((lam + 2.0 * mu) / density)
