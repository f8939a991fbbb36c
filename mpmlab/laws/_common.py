"""Pieces the built-in law classes share: the isotropic elastic parameters and their P-wave speed,
and where a built-in law's backend implementations live."""
from __future__ import annotations

import math

from ..core.interfaces import ParamSpec
from ._linalg_np import lame

YOUNGS_MODULUS = ParamSpec("E", "Pa", 1.0e5, low=0.0, low_open=True, doc="Young's modulus")
POISSON_RATIO = ParamSpec("nu", "-", 0.3, low=-1.0, high=0.5, low_open=True, high_open=True, doc="Poisson ratio")


def p_wave_speed(params, density: float) -> float:
    """c_p = sqrt((lambda + 2 mu)/rho) from E and nu (verification note #7: the CFL wave speed)."""
    mu, lam = lame(params["E"], params["nu"])
    return math.sqrt((lam + 2.0 * mu) / density)


def builtin_implementations(name: str) -> dict[str, str]:
    """``{backend: "module:make"}`` for a law folder ``mpmlab/laws/<name>/{jax,warp}.py``."""
    return {b: f"mpmlab.laws.{name}.{b}:make" for b in ("jax", "warp")}
