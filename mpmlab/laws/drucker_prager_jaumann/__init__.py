"""Non-associated Drucker-Prager plasticity with tension cutoff on the Jaumann stress rate
(JAX-MPM Sec. 2.3 Eq. 21 and App. A, Eqs. A.1-A.19; after FLAC's Drucker-Prager model): granular flow."""
from __future__ import annotations

import math
from typing import ClassVar

from ...core.errors import InvalidParameterError
from ...core.interfaces import AbstractConstitutiveLaw, ParamSpec
from .._common import builtin_implementations, VOLUME_RATIO, CAUCHY_STRESS, PLASTIC_STRAIN, OUT_OF_PLANE_STRESS
from . import reference as _reference


class Law(AbstractConstitutiveLaw):
    """Hypo-elastic Drucker-Prager: Jaumann-rotated Kirchhoff stress + isotropic elastic increment, then the
    three-zone return map of JAX-MPM App. A (elastic / shear failure / tensile failure) on the Cauchy stress.

    State: ``J`` (volume ratio), ``sigma`` (Cauchy stress, tension positive), ``sigma_zz`` (2D: the
    out-of-plane Cauchy stress, see below) and ``eps_p`` (equivalent plastic strain, A.15 / A.18; never
    decreases). Kirchhoff stress tau = J sigma.

    Parameters: bulk modulus K and Poisson ratio nu (G = 3K(1-2nu)/(2(1+nu)), lambda = K - 2G/3),
    friction angle phi and dilation angle psi <= phi [deg], cohesion c and tension cutoff sigma_t, which
    must not exceed the cone apex k_phi / q_phi (q_phi, k_phi, q_psi as in App. A).

    Limitations:

    * 2D is plane strain (issue 18): the state carries the out-of-plane Cauchy stress ``sigma_zz``
      (unit Pa; carried unchanged, 0, in 3D). Its trial is A.1-A.2 in e_z with d_zz = 0 and no spin
      coupling (the 2D spin has no z components): tau_zz_trial = J sigma_zz + lambda tr(dd),
      sigma_zz_trial = tau_zz_trial / J_new; the return map (A.3-A.19) runs on the 3x3 stress
      diag(sigma_trial, sigma_zz_trial): sigma_m = tr/3 over three components (A.3), the deviator and
      tau = sqrt(s:s/2) (A.4) include s_zz, and the returned stress gives the new sigma_zz. The grid force
      uses the in-plane tau = J sigma. This is the 3D law on a body with d_zz = 0 exactly, so a 2D run
      agrees with a thin 3D slab with slip side walls (tests/test_plane_strain.py). Before issue 18, 2D was
      a 2D continuum (sigma_m = tr/2, deviator w.r.t. the 2x2 identity, no sigma_zz), which happened to
      run out within 0.05 % of the slab for the aluminium bars (d_n 0.4462 / 1.1720 vs 0.4460 / 1.1716 at
      a = 0.5 / 1, dx = 10 mm, 0.8 s); granular_collapse_2d (cpu, Warp, 0.65 s) d_n 0.706 -> 0.707.
    * The return map follows App. A except at one corner: in Zone II with f_t >= 0 and a trial mean
      stress beyond the apex, A.12-A.13 literally return to sigma_m > sigma_t with tau < 0 (the deviator
      flips sign and one step of spurious tension follows). mpmlab caps the returned sigma_m at sigma_t,
      i.e. returns to the corner (sigma_t, tau_P) of the shear surface and the tension cutoff.
    * The elastic trial (A.1-A.2, Eq. 21) is integrated on the Kirchhoff stress tau = J sigma, the stress
      the grid force uses: tau_trial = R tau_n R^T + lambda tr(dd) I + 2 G dd, sigma_trial = tau_trial / J_new
      (the Jaumann rate of tau with constant K, G), and R is the Hughes-Winget rotation
      (I - dw/2)^-1 (I + dw/2) instead of A.2's first-order I + dw. At J = 1 both agree with A.1-A.2 to
      first order in dt (Sec. 4.1.2's collapse: runout changed by 2e-5 m, particles by <= 0.38 mm at dx 5 mm;
      benchmarks/stress.md).
      Why: with A.1 on the Cauchy stress (constant K, G) a particle dilated to J has the grid stiffness
      J K per unit mass, i.e. the wave speed sqrt(J) c_p; a cohesionless body thrown apart reaches
      J = 10-800 and blew up once C sqrt(J) reached 2.6-4.3 (the sweep's C* was 0.19-0.20; now 1.6-1.73). A rigid
      rotation now rotates tau exactly (the first-order A.2 changes its invariants by O((w dt)^2) a step).
    * Zone III (A.17) keeps the trial deviator; in the wedge tau_P < tau <= tau_P + alpha_P (sigma_m - sigma_t)
      that h <= 0 admits, that leaves a stress outside the cone (c = sigma_t = 0: any tau > 0 at sigma_m = 0,
      a tensile principal stress, on most particles of a free-flying cohesionless body). mpmlab returns
      the wedge to the corner (sigma_t, tau_P), adding the shear part (tau - tau_P) / (G sqrt 3) (A.15 with
      q_psi = 0) to eps_p.
    """

    name: ClassVar[str] = "drucker_prager_jaumann"
    params = (
        ParamSpec("bulk_modulus", "Pa", 0.7e6, low=0.0, low_open=True, doc="bulk modulus K"),
        ParamSpec("nu", "-", 0.3, low=-1.0, high=0.5, low_open=True, high_open=True, doc="Poisson ratio"),
        ParamSpec("friction_angle", "deg", 19.8, low=0.0, high=90.0, high_open=True,
                  doc="internal friction angle phi"),
        ParamSpec("dilation_angle", "deg", 0.0, low=0.0, high=90.0, high_open=True, doc="dilation angle psi"),
        ParamSpec("cohesion", "Pa", 0.0, low=0.0, doc="cohesion c"),
        ParamSpec("tensile_strength", "Pa", 0.0, low=0.0, doc="tension cutoff sigma_t"),
    )
    state = (VOLUME_RATIO, CAUCHY_STRESS, OUT_OF_PLANE_STRESS, PLASTIC_STRAIN)
    #: deforms (and yields) within 50 steps of the mpmlab.testing scenes
    test_params = {"bulk_modulus": 2e4, "nu": 0.3, "friction_angle": 30.0}
    plastic = True
    reference = _reference
    # benchmarks/stress.md (--full): the thrown granular square used to diverge (J <= 0 after 400-900 steps)
    # above C = 0.19-0.20 with APIC, MLS and TPIC; with the Kirchhoff-rate integration (see above) its C* is
    # at or above the other laws' (0.89), so dt: auto keeps the library-wide C = 0.3 (no stable_cfl)
    stable_cfl: ClassVar[float | None] = None
    implementations: ClassVar[dict] = builtin_implementations("drucker_prager_jaumann")

    @classmethod
    def check_consistency(cls, params, where):
        phi, psi = params["friction_angle"], params["dilation_angle"]
        if psi > phi:
            raise InvalidParameterError(
                f"{where}: law '{cls.name}': dilation angle 'dilation_angle' = {psi:g} deg exceeds the friction "
                f"angle 'friction_angle' = {phi:g} deg; set dilation_angle <= friction_angle.")
        q_phi, k_phi, _ = _reference.cone_constants(phi, psi, params["cohesion"])
        st = params["tensile_strength"]
        if q_phi > 0.0 and st > k_phi / q_phi * (1.0 + 1e-12):
            raise InvalidParameterError(
                f"{where}: law '{cls.name}': tensile strength 'tensile_strength' = {st:g} Pa exceeds the "
                f"Drucker-Prager cone apex k_phi/q_phi = {k_phi / q_phi:g} Pa (cohesion {params['cohesion']:g} Pa, "
                f"friction angle {phi:g} deg); set tensile_strength <= {k_phi / q_phi:g} Pa or raise the cohesion.")

    @classmethod
    def wave_speed(cls, params, density):
        K = params["bulk_modulus"]
        G, _ = _reference.moduli(K, params["nu"])
        return math.sqrt((K + 4.0 * G / 3.0) / density)
