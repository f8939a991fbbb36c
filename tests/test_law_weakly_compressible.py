"""Weakly compressible fluid (NCLaw App. B, Eqs. 20-21) on its J-only state: the reference, JAX and Warp (fp64).

* tau = lambda J (J - 1) I, i.e. Eq. 20's P = lambda J (J - 1) F^-T times F^T for any F with det F = J;
* J <- J det(I + dt grad_v) equals F-tracking F <- (I + dt grad_v) F followed by Eq. 21's projection
  F <- J^(1/d) I, step after step;
* rigid rotation (note row 5c): det(I + dt W) = 1 + (omega dt)^2, so J grows as (1 + (omega dt)^2)^n;
* sound speed sqrt(lambda / rho).
"""
import numpy as np
import pytest

import mpmlab
from mpmlab.core import registry

from .lawtools import EVAL

LAW = registry.laws.get("weakly_compressible")
BACKENDS = ("reference", "jax", "warp")
DIMS = (2, 3)
K = 2.0e5
PRM = np.array([K])


def kirchhoff(backend, dim, Js):
    states = [{"J": float(j)} for j in Js]
    if backend == "reference":   # a scalar J carries no dimension: the reference takes it explicitly
        return np.array([LAW.reference.kirchhoff(s, PRM, dim=dim) for s in states])
    return np.asarray(EVAL[backend](LAW, dim, "kirchhoff", states, PRM))


def update(backend, dim, Js, Ls, dt):
    out = EVAL[backend](LAW, dim, "update", [{"J": float(j)} for j in Js], PRM, np.asarray(Ls), dt)
    return np.array([o["J"] for o in out])


def test_declares_j_state_only_and_sound_speed():
    assert LAW.state_fields == ("J",)
    prm = LAW.resolve_params({"bulk_modulus": K}, "test")
    assert LAW.wave_speed(prm, 1000.0) == pytest.approx(np.sqrt(K / 1000.0), rel=1e-15)
    with pytest.raises(mpmlab.InvalidParameterError):
        LAW.resolve_params({"bulk_modulus": 0.0}, "test")
    with pytest.raises(TypeError):
        LAW.reference.kirchhoff({"J": 1.0}, PRM)          # no silent default dimension


@pytest.mark.parametrize("dim", DIMS)
@pytest.mark.parametrize("backend", BACKENDS)
def test_stress_is_eq20(backend, dim):
    rng = np.random.default_rng(0)
    Js = np.array([1.0, 0.5, 0.9, 0.99, 1.0 + 1e-6, 1.1, 2.0])
    got = kirchhoff(backend, dim, Js)
    want = np.array([K * j * (j - 1.0) * np.eye(dim) for j in Js])
    assert np.max(np.abs(got - want)) <= 1e-14 * np.max(np.abs(want))
    assert np.all(got[0] == 0.0)                                        # rest: no stress
    assert np.all(np.diagonal(got, axis1=1, axis2=2)[Js < 1.0] < 0.0)   # compression: positive pressure
    # Eq. 20 on any F with det F = J: tau = P F^T = lambda J (J - 1) I (fixed corotated with mu = 0)
    for j, t in zip(Js, got):
        F = rng.standard_normal((dim, dim))
        if np.linalg.det(F) < 0.0:
            F[0] *= -1.0
        F *= (j / np.linalg.det(F)) ** (1.0 / dim)
        P = K * j * (j - 1.0) * np.linalg.inv(F).T
        assert np.max(np.abs(P @ F.T - t)) <= 1e-10 * max(np.max(np.abs(t)), K)


@pytest.mark.parametrize("dim", DIMS)
@pytest.mark.parametrize("backend", BACKENDS)
def test_j_update_equals_f_tracking_with_eq21_projection(backend, dim):
    rng = np.random.default_rng(1)
    n, steps, dt = 5, 20, 1e-2
    J = np.ones(n)
    F = np.repeat(np.eye(dim)[None], n, axis=0)
    for _ in range(steps):
        L = 2.0 * rng.standard_normal((n, dim, dim))
        J = update(backend, dim, J, L, dt)
        F = np.einsum("nij,njk->nik", np.eye(dim) + dt * L, F)
        F = np.array([np.linalg.det(f) ** (1.0 / dim) * np.eye(dim) for f in F])   # Eq. 21 (d = dim)
    J_f = np.array([np.linalg.det(f) for f in F])
    assert np.all(J_f > 0.0)
    assert np.max(np.abs(J - J_f) / J_f) <= 1e-12


@pytest.mark.parametrize("dim", DIMS)
@pytest.mark.parametrize("backend", BACKENDS)
def test_rigid_rotation_volume_drift(backend, dim):
    """Forward-Euler kinematics under a spin W: det(I + dt W) = 1 + (omega dt)^2 per step (note row 5c)."""
    w_dt, steps = 0.01, 50
    W = np.zeros((dim, dim))
    W[0, 1], W[1, 0] = -1.0, 1.0               # omega = 1 about z
    J = np.ones(1)
    for _ in range(steps):
        J = update(backend, dim, J, [W], w_dt)
    assert abs(J[0] - (1.0 + w_dt**2) ** steps) <= 1e-13


@pytest.mark.parametrize("dim", DIMS)
@pytest.mark.parametrize("backend", BACKENDS)
def test_rest_stays_at_rest(backend, dim):
    J = update(backend, dim, np.ones(2), np.zeros((2, dim, dim)), 1e-3)
    assert np.all(J == 1.0)
    assert np.all(kirchhoff(backend, dim, J) == 0.0)


def test_warp_fp32_builds_and_agrees():
    rng = np.random.default_rng(2)
    for dim in DIMS:
        Js = rng.uniform(0.8, 1.2, 6)
        states = [{"J": float(j)} for j in Js]
        t32 = np.asarray(EVAL["warp"](LAW, dim, "kirchhoff", states, PRM, precision="fp32"))
        want = kirchhoff("reference", dim, Js)
        assert np.max(np.abs(t32 - want)) <= 1e-5 * np.max(np.abs(want))
        L = rng.standard_normal((6, dim, dim))
        u32 = np.array([o["J"] for o in EVAL["warp"](LAW, dim, "update", states, PRM, L, 1e-2, precision="fp32")])
        assert np.max(np.abs(u32 - update("reference", dim, Js, L, 1e-2))) <= 1e-5
