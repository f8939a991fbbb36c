"""Pieces the built-in law classes share: the isotropic elastic parameters and their P-wave speed,
and where a built-in law's backend implementations live."""
from __future__ import annotations

import math

from ..core.interfaces import ParamSpec, StateField, named_params  # noqa: F401  (the references use it)
from ._linalg_np import lame

YOUNGS_MODULUS = ParamSpec("E", "Pa", 1.0e5, low=0.0, low_open=True, doc="Young's modulus")
POISSON_RATIO = ParamSpec("nu", "-", 0.3, low=-1.0, high=0.5, low_open=True, high_open=True, doc="Poisson ratio")

#: the state fields the built-in laws share (each law declares the ones it carries)
DEFORMATION_GRADIENT = StateField("F", ("D", "D"), "identity", doc="deformation gradient F (elastic part for "
                                  "plastic laws)", check="positive_det")
VOLUME_RATIO = StateField("J", (), 1.0, doc="volume ratio J = det F", check="positive")
CAUCHY_STRESS = StateField("sigma", ("D", "D"), 0.0, unit="Pa", doc="Cauchy stress (tension positive)")
PLASTIC_STRAIN = StateField("eps_p", (), 0.0, doc="equivalent plastic strain")
#: plane strain in 2D (issue 18): the elastic out-of-plane Hencky strain log(F^e_zz) of the multiplicative
#: plasticity laws (the total F_zz is 1; plastic flow changes the elastic part). Unused in 3D (stays 0).
OUT_OF_PLANE_STRAIN = StateField("eps_zz", (), 0.0, doc="elastic out-of-plane Hencky strain log(Fe_zz) "
                                 "(2D plane strain; stays 0 in 3D)")
#: plane strain in 2D: the out-of-plane Cauchy stress sigma_zz of the hypo-elastic laws. Unused in 3D (stays 0).
OUT_OF_PLANE_STRESS = StateField("sigma_zz", (), 0.0, unit="Pa", doc="out-of-plane Cauchy stress sigma_zz "
                                 "(2D plane strain; stays 0 in 3D)")


def p_wave_speed(params, density: float) -> float:
    """c_p = sqrt((lambda + 2 mu)/rho) from E and nu (verification note #7: the CFL wave speed)."""
    mu, lam = lame(params["E"], params["nu"])
    return math.sqrt((lam + 2.0 * mu) / density)


def builtin_implementations(name: str) -> dict[str, str]:
    """``{backend: "module:make"}`` for a law folder ``mpmlab/laws/<name>/{jax,warp}.py``."""
    return {b: f"mpmlab.laws.{name}.{b}:make" for b in ("jax", "warp")}

