"""Drucker-Prager sand with hardening (Klar et al. 2016, "Drucker-Prager Elastoplasticity for Sand
Animation", Sec. 7.3): the example of a law that adds a state field of its own, written without
touching any file of mpmlab.

State: the elastic deformation gradient ``F`` and the hardening state ``q`` (the accumulated plastic
Hencky strain). Each step, with the trial elastic F and its principal Hencky strains eps (tr, the
deviator eps_hat and its norm n):

* friction angle phi_F = h0 + (h1 q - h3) exp(-h2 q) [deg], alpha = sqrt(2/3) 2 sin phi_F / (3 - sin phi_F);
* the Drucker-Prager return map of mpmlab's ``hencky_drucker_prager`` with that angle (NCLaw Eq. 16,
  called by name with ``friction_angle = phi_F``);
* dq = |eps_trial - eps_new|: the plastic multiplier dg = n + c tr alpha on the cone, |eps| at the
  tip (tension), 0 when elastic; q <- q + dq.

The stress is the Hencky Kirchhoff stress of the elastic F (as hencky_drucker_prager). Klar et al.'s
sand: h0 = 35, h1 = 9, h2 = 0.2, h3 = 10 (phi_F = 25 deg at q = 0, rising towards 35 deg).
"""
from __future__ import annotations

import math
from typing import ClassVar

from mpmlab.core.interfaces import AbstractConstitutiveLaw, ParamSpec, StateField

from . import reference as _reference


class Law(AbstractConstitutiveLaw):
    name: ClassVar[str] = "dp_hardening"
    params = (
        ParamSpec("E", "Pa", 3.537e5, low=0.0, low_open=True, doc="Young's modulus"),
        ParamSpec("nu", "-", 0.3, low=-1.0, high=0.5, low_open=True, high_open=True, doc="Poisson ratio"),
        ParamSpec("h0", "deg", 35.0, low=0.0, high=90.0, doc="hardening h0 (Klar et al. 2016)"),
        ParamSpec("h1", "deg", 9.0, low=0.0, high=90.0, doc="hardening h1"),
        ParamSpec("h2", "-", 0.2, low=0.0, doc="hardening h2"),
        ParamSpec("h3", "deg", 10.0, low=0.0, high=90.0, doc="hardening h3"),
    )
    state = (
        StateField("F", ("D", "D"), "identity", doc="elastic deformation gradient", check="positive_det"),
        StateField("q", (), 0.0, doc="hardening state q (accumulated plastic Hencky strain)"),
    )
    plastic = True
    reference = _reference
    #: 30 deg at q = 0 (as hencky_drucker_prager's test friction angle), hardening to 35 deg
    test_params = {"E": 2e4, "nu": 0.3, "h0": 35.0, "h1": 9.0, "h2": 0.2, "h3": 5.0}
    implementations: ClassVar[dict] = {
        "jax": "mpmlab_example_plugin.dp_hardening.jax:make",
        "warp": "mpmlab_example_plugin.dp_hardening.warp:make",
    }

    @classmethod
    def check_consistency(cls, params, where):
        from mpmlab.core.errors import InvalidParameterError

        lo = params["h0"] - params["h3"]        # phi_F at q = 0; phi_F(q) stays in [lo, h0 + h1 e^-1 / h2]
        if not 0.0 < lo < 90.0:
            raise InvalidParameterError(f"{where}: law 'dp_hardening': h0 - h3 = {lo:g} deg is the friction angle "
                                        f"at q = 0 and must lie in (0, 90) deg; lower h3 or raise h0.")

    @classmethod
    def wave_speed(cls, params, density):
        E, nu = params["E"], params["nu"]
        mu = E / (2.0 * (1.0 + nu))
        lam = E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
        return math.sqrt((lam + 2.0 * mu) / density)
