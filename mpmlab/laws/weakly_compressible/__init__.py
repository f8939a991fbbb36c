"""Weakly compressible fluid (Stomakhin et al. 2014; Tampubolon et al. 2017; NCLaw App. B, Eqs. 20-21): WATER."""
from __future__ import annotations

import math
from typing import ClassVar

from ...core.interfaces import AbstractConstitutiveLaw, ParamSpec
from .._common import builtin_implementations, VOLUME_RATIO
from . import reference as _reference


class Law(AbstractConstitutiveLaw):
    """Fixed corotated with mu = 0, P = lambda J (J - 1) F^-T (Eq. 20), i.e. tau = lambda J (J - 1) I, and
    the return map F <- J^(1/d) I (Eq. 21).

    The stress depends on F only through J = det F, and Eq. 21 keeps only J, so the state is J alone
    (DESIGN "J instead of F"): J <- J det(I + dt grad_v) is exactly F-tracking followed by Eq. 21.
    ``bulk_modulus`` is the lambda of Eq. 20 (the bulk modulus at J = 1: d(-p)/dJ = lambda); the sound
    speed is sqrt(lambda / rho). Weak compressibility needs c >= 10 |v|_max (density error ~ 1 %).

    2D is plane strain without extra state (issue 18): with F_zz = 1, J_3D = J_2D, and the stress is the
    isotropic tau = lambda J (J - 1) I in 3D too (tau_zz is the same pressure), so the 2D law is the 3D law
    on a slice; Eq. 21's F <- J^(1/d) I acts on nothing but J here.
    """

    name: ClassVar[str] = "weakly_compressible"
    params = (
        ParamSpec("bulk_modulus", "Pa", 1.0e5, low=0.0, low_open=True, doc="bulk modulus lambda"),
    )
    state = (VOLUME_RATIO,)
    #: deforms (and yields) within 50 steps of the mpmlab.testing scenes
    test_params = {"bulk_modulus": 2e4}
    plastic = True   # Eq. 21 is a return map; on the J state it is folded into the update
    reference = _reference
    implementations: ClassVar[dict] = builtin_implementations("weakly_compressible")

    @classmethod
    def wave_speed(cls, params, density):
        return math.sqrt(params["bulk_modulus"] / density)
