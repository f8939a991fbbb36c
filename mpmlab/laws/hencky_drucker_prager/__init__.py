"""Hencky elasticity with Drucker-Prager plasticity (Klar et al. 2016; NCLaw App. B, Eqs. 14-16): SAND."""
from __future__ import annotations

from typing import ClassVar

from ...core.interfaces import AbstractConstitutiveLaw, ParamSpec
from .._common import POISSON_RATIO, YOUNGS_MODULUS, builtin_implementations, p_wave_speed, DEFORMATION_GRADIENT
from . import reference as _reference


class Law(AbstractConstitutiveLaw):
    """tau = U (2 mu eps + lambda tr(eps) I) U^T in the Hencky strain eps = log(s), F = U diag(s) V^T
    (Eq. 14; the paper's "P" is this Kirchhoff stress, P = tau F^-T), with the Drucker-Prager return map
    of Eqs. 15-16: tension goes to the cone tip (F = U V^T, tau = 0); compression outside the cone is
    projected onto it along the deviatoric direction (volume kept).

    In 2D the cone and return use d = 2 (tr over two singular values, (2 lambda + 2 mu) in Eq. 15), with
    the 3D Lame constants from E and nu, as in taichi_elements' ``sand_projection``. Singular values are
    clamped to >= 1e-4 before the log (inverted or collapsed particles).
    """

    name: ClassVar[str] = "hencky_drucker_prager"
    params = (
        YOUNGS_MODULUS,
        POISSON_RATIO,
        ParamSpec("friction_angle", "deg", 30.0, low=0.0, high=90.0, low_open=True, high_open=True,
                  doc="friction angle phi"),
    )
    state = (DEFORMATION_GRADIENT,)
    #: deforms (and yields) within 50 steps of the mpmlab.testing scenes
    test_params = {"E": 2e4, "nu": 0.3, "friction_angle": 30.0}
    plastic = True
    reference = _reference
    implementations: ClassVar[dict] = builtin_implementations("hencky_drucker_prager")

    @classmethod
    def wave_speed(cls, params, density):
        return p_wave_speed(params, density)
