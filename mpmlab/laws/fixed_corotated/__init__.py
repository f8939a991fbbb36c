"""Fixed corotated hyperelasticity (Stomakhin et al. 2012; NCLaw App. B, Eq. 12): JELL-O."""
from __future__ import annotations

from typing import ClassVar

from ...core.interfaces import AbstractConstitutiveLaw
from .._common import POISSON_RATIO, YOUNGS_MODULUS, builtin_implementations, p_wave_speed, DEFORMATION_GRADIENT
from . import reference as _reference


class Law(AbstractConstitutiveLaw):
    """P = 2 mu (F - R) + lambda J (J - 1) F^-T; no plasticity (Eq. 13: the return map is identity)."""

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
