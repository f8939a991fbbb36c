"""Fixed corotated hyperelasticity (Stomakhin et al. 2012; NCLaw App. B, Eq. 12): JELL-O."""
from __future__ import annotations

import math
from typing import ClassVar

from ...core.interfaces import AbstractConstitutiveLaw, ParamSpec
from .. import _linalg_np
from . import reference as _reference


class Law(AbstractConstitutiveLaw):
    """P = 2 mu (F - R) + lambda J (J - 1) F^-T; no plasticity (Eq. 13: the return map is identity)."""

    name: ClassVar[str] = "fixed_corotated"
    params = (
        ParamSpec("E", "Pa", 1.0e5, low=0.0, low_open=True, doc="Young's modulus"),
        ParamSpec("nu", "-", 0.3, low=-1.0, high=0.5, low_open=True, high_open=True, doc="Poisson ratio"),
    )
    state_fields = ("F",)
    plastic = False
    reference = _reference
    implementations: ClassVar[dict] = {
        "jax": "mpmlab.laws.fixed_corotated.jax:make",
        "warp": "mpmlab.laws.fixed_corotated.warp:make",
    }

    @classmethod
    def wave_speed(cls, params, density):
        mu, lam = _linalg_np.lame(params["E"], params["nu"])
        return math.sqrt((lam + 2.0 * mu) / density)
