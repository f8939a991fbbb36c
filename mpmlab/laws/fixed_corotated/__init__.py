"""Fixed corotated hyperelasticity (Stomakhin et al. 2012; NCLaw App. B, Eq. 12): JELL-O."""
from __future__ import annotations

from typing import ClassVar

from ...core.interfaces import AbstractConstitutiveLaw
from .._common import POISSON_RATIO, YOUNGS_MODULUS, builtin_implementations, p_wave_speed, DEFORMATION_GRADIENT
from . import reference as _reference


class Law(AbstractConstitutiveLaw):
    """P = 2 mu (F - R) + lambda J (J - 1) F^-T; no plasticity (Eq. 13: the return map is identity).

    2D is plane strain without extra state (issue 18): the 3D energy psi = mu sum_i (s_i - 1)^2 +
    lambda/2 (J - 1)^2 restricted to F = diag(F_2D, 1) (s_3 = 1, J_3D = J_2D) is the 2D energy, so the
    in-plane P and tau are the 3D ones; the out-of-plane stress, tau_zz = lambda J (J - 1) (P_zz with
    F_zz = R_zz = 1), feeds nothing back (no yield surface) and is not stored.
    """

    name: ClassVar[str] = "fixed_corotated"
    params = (
        YOUNGS_MODULUS,
        POISSON_RATIO,
    )
    state = (DEFORMATION_GRADIENT,)
    #: deforms (and yields) within 50 steps of the mpmlab.testing scenes
    test_params = {"E": 2e4, "nu": 0.3}
    plastic = False
    reference = _reference
    implementations: ClassVar[dict] = builtin_implementations("fixed_corotated")

    @classmethod
    def wave_speed(cls, params, density):
        return p_wave_speed(params, density)
