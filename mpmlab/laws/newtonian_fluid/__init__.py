"""Weakly compressible Newtonian fluid (JAX-MPM Sec. 2.3, Eqs. 19-20): dam breaks, water."""
from __future__ import annotations

from typing import ClassVar

from ...core.interfaces import AbstractConstitutiveLaw, ParamSpec
from .._common import builtin_implementations, VOLUME_RATIO, CAUCHY_STRESS
from . import reference as _reference


class Law(AbstractConstitutiveLaw):
    """sigma = -p I + 2 mu (D - tr(D)/3 I), p = max(c^2 (rho0 / J - rho0), min_pressure); a hypo-elastic, J-based fluid.

    State: ``J`` (volume ratio, J <- J det(I + dt grad_v)) and ``sigma`` (Cauchy stress, kept for
    output; it is recomputed from J and grad_v every step). Kirchhoff stress tau = J sigma.

    Deviations from the paper, on purpose:

    * Eq. 19 writes the viscous term with the strain *increment* Delta d = D dt, which is not a stress
      (Pa s times a dimensionless number); we use the strain *rate* D = sym(grad_v), the Newtonian law.
    * 2D is plane strain (issue 18; also the paper's convention): D_zz = 0 and the deviator uses tr(D)/3 in
      2D as well (the 3D deviator, as in Eq. 19), so a 2D isotropic expansion carries a small viscous
      stress; the pressure from J is the 3D one (J_3D = J_2D with F_zz = 1). The out-of-plane stress,
      sigma_zz = -p - 2 mu tr(D)/3, feeds nothing back (no yield surface) and is not stored.
    * Eq. 20's density update rho^{n+1} = rho^n / (1 + det(Delta d)) is read as the exact volume update
      rho = rho0 / J with J <- J det(I + dt grad_v).
    * **Tension cut-off** ``min_pressure`` (not in the paper): p <- max(p, min_pressure). Eq. 20 alone
      gives p < 0 (tension) whenever J > 1; a free-surface liquid cannot carry tension (it cavitates
      or separates), and weakly compressible SPH/MPM practice clamps p >= 0. The default is
      therefore 0 (no tension). For the paper's Eq. 20 as written pass a large negative value, e.g.
      ``min_pressure=-1e30``. Why it matters: in the Ritter dam break (benchmarks/validation.md, 3a)
      the unclamped law reaches J = 1.027, p = -33 kPa (30x the largest hydrostatic pressure) and
      the tension holds the thin front back by 30-80 %.
      At p == min_pressure exactly (e.g. a fluid at rest with min_pressure = 0) the JAX gradient is
      that of the unclamped branch (jnp.where(p >= min_pressure, ...)), so d p / d J = -c^2 rho0 / J^2
      is kept for a fluid at rest.
    """

    name: ClassVar[str] = "newtonian_fluid"
    params = (
        ParamSpec("sound_speed", "m/s", 35.0, low=0.0, low_open=True, doc="numerical sound speed c"),
        ParamSpec("viscosity", "Pa s", 1.01e-3, low=0.0, doc="dynamic viscosity mu"),
        ParamSpec("rest_density", "kg/m^3", None, low=0.0, low_open=True,
                  doc="reference density rho0 (defaults to the body density)"),
        ParamSpec("min_pressure", "Pa", 0.0, high=0.0,
                  doc="tension cut-off: p = max(p, min_pressure); 0 = no tension, -1e30 = Eq. 20 unclamped"),
    )
    state = (VOLUME_RATIO, CAUCHY_STRESS,)
    #: deforms (and yields) within 50 steps of the mpmlab.testing scenes
    test_params = {"sound_speed": 5.0, "viscosity": 0.1}
    plastic = False
    reference = _reference
    implementations: ClassVar[dict] = builtin_implementations("newtonian_fluid")

    @classmethod
    def default_from_density(cls, name, density):
        return density if name == "rest_density" else None

    @classmethod
    def wave_speed(cls, params, density):
        return float(params["sound_speed"])
