"""Hencky elasticity with Drucker-Prager plasticity (Klar et al. 2016; NCLaw App. B, Eqs. 14-16): SAND."""
from __future__ import annotations

from typing import ClassVar

from ...core.interfaces import AbstractConstitutiveLaw, ParamSpec
from .._common import (POISSON_RATIO, YOUNGS_MODULUS, builtin_implementations, p_wave_speed, DEFORMATION_GRADIENT,
                      OUT_OF_PLANE_STRAIN)
from . import reference as _reference


class Law(AbstractConstitutiveLaw):
    """tau = U (2 mu eps + lambda tr(eps) I) U^T in the Hencky strain eps = log(s), F = U diag(s) V^T
    (Eq. 14; the paper's "P" is this Kirchhoff stress, P = tau F^-T), with the Drucker-Prager return map
    of Eqs. 15-16: tension goes to the cone tip (F = U V^T, tau = 0); compression outside the cone is
    projected onto it along the deviatoric direction (volume kept).

    2D is plane strain (issue 18): a slice of a 3D body with total F_zz = 1. The state carries the elastic
    out-of-plane Hencky strain ``eps_zz`` = log(F^e_zz) besides the in-plane elastic F; the elastic trial
    keeps it (d_zz = 0) and the return map of Eqs. 15-16 runs on the three principal strains
    (eps_1, eps_2, eps_zz) with the 3D formulas (tr over three, eps_hat the 3D deviator, (3 lambda + 2 mu)
    in Eq. 15), storing the returned eps_zz (the cone tip sets it to 0). The in-plane Kirchhoff stress is
    2 mu eps_i + lambda (eps_1 + eps_2 + eps_zz); the out-of-plane one, tau_zz = 2 mu eps_zz + lambda tr,
    is derived (``reference.out_of_plane_stress``), not stored. This is the 3D law restricted to
    F = diag(F_2D, F_zz^e) exactly, so a 2D run agrees with a thin 3D slab with slip side walls
    (tests/test_plane_strain.py). Before issue 18, 2D used d = 2 (taichi_elements' ``sand_projection``):
    a 2D continuum without sigma_zz that ran out 33-46 % further than the slab (issue 18: d_n 0.515 / 1.279
    vs 0.387 / 0.878 at a = 0.5 / 1; material sand, dx = 10 mm, 0.8 s: 0.4225 / 1.0889 vs 0.2905 / 0.7477,
    which plane strain now gives in 2D too); ``reference.project`` on a 2x2 F is still that map. In 3D ``eps_zz``
    is carried unchanged (0). Singular values are clamped to >= 1e-4 before the log (inverted or
    collapsed particles).
    """

    name: ClassVar[str] = "hencky_drucker_prager"
    params = (
        YOUNGS_MODULUS,
        POISSON_RATIO,
        ParamSpec("friction_angle", "deg", 30.0, low=0.0, high=90.0, low_open=True, high_open=True,
                  doc="friction angle phi"),
    )
    state = (DEFORMATION_GRADIENT, OUT_OF_PLANE_STRAIN)
    #: deforms (and yields) within 50 steps of the mpmlab.testing scenes
    test_params = {"E": 2e4, "nu": 0.3, "friction_angle": 30.0}
    plastic = True
    reference = _reference
    implementations: ClassVar[dict] = builtin_implementations("hencky_drucker_prager")

    @classmethod
    def wave_speed(cls, params, density):
        return p_wave_speed(params, density)
