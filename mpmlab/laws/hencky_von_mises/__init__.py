"""Hencky elasticity with von Mises plasticity (NCLaw App. B, Eqs. 17-19; Hu et al. 2018): PLASTICINE."""
from __future__ import annotations

from typing import ClassVar

from ...core.interfaces import AbstractConstitutiveLaw, ParamSpec
from .._common import (POISSON_RATIO, YOUNGS_MODULUS, builtin_implementations, p_wave_speed, DEFORMATION_GRADIENT,
                      OUT_OF_PLANE_STRAIN)
from . import reference as _reference


class Law(AbstractConstitutiveLaw):
    """tau = U (2 mu eps + lambda tr(eps) I) U^T in the Hencky strain (Eq. 17, a Kirchhoff stress; P = tau F^-T)
    with the isochoric von Mises return map of Eqs. 18-19.

    ``yield_stress`` is tau_Y of Eq. 18: the yield limit on the Frobenius norm of the deviatoric Kirchhoff
    stress, |dev tau| <= tau_Y. For a uniaxial yield stress sigma_y (von Mises sqrt(3/2)|dev tau| <= sigma_y),
    tau_Y = sqrt(2/3) sigma_y.

    2D is plane strain (issue 18), as in ``hencky_drucker_prager``: the state carries the elastic
    out-of-plane Hencky strain ``eps_zz`` (total F_zz = 1), the stress is 2 mu eps_i + lambda
    (eps_1 + eps_2 + eps_zz) in the plane, and the return of Eqs. 18-19 runs on (eps_1, eps_2, eps_zz) with
    the 3D deviator (d = 3; the returned eps_zz is stored). Before issue 18 the deviator was taken over
    d = 2 (a 2D continuum without sigma_zz). In 3D ``eps_zz`` is carried unchanged (0).
    """

    name: ClassVar[str] = "hencky_von_mises"
    params = (
        YOUNGS_MODULUS,
        POISSON_RATIO,
        ParamSpec("yield_stress", "Pa", 3.0e3, low=0.0, low_open=True,
                  doc="yield stress tau_Y (Frobenius norm of the deviatoric Kirchhoff stress, = sqrt(2/3) sigma_y)"),
    )
    state = (DEFORMATION_GRADIENT, OUT_OF_PLANE_STRAIN)
    #: deforms (and yields) within 50 steps of the mpmlab.testing scenes
    test_params = {"E": 2e4, "nu": 0.3, "yield_stress": 20.0}
    plastic = True
    reference = _reference
    implementations: ClassVar[dict] = builtin_implementations("hencky_von_mises")

    @classmethod
    def wave_speed(cls, params, density):
        return p_wave_speed(params, density)
