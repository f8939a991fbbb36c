"""The conformance kit (``mpmlab.testing``) passes on a built-in law and catches broken ones, each with
one line naming the law, the backend, the quantity and the error against its tolerance.

The broken laws are small ``AbstractConstitutiveLaw`` subclasses borrowing fixed_corotated's
declarations, with one thing wrong: a JAX stress off by a factor 1.001, a reference with a residual
stress at rest, a reference that is not rotation-equivariant; a trajectory off by 1e-6; a JAX stress
whose derivative is dropped. Only JAX runs them (no extra Warp kernels to compile)."""
from __future__ import annotations

import copy
import importlib
import subprocess
import sys
from types import SimpleNamespace
from typing import ClassVar

import numpy as np
import pytest

from mpmlab import testing
from mpmlab.core.interfaces import AbstractConstitutiveLaw
from mpmlab.laws import fixed_corotated as fc
from mpmlab.laws.fixed_corotated import reference as fc_ref

FC = fc.Law


def _borrow(name, reference=fc_ref, jax="tests.test_testing_kit:_jax_scaled"):
    """A law class with fixed_corotated's parameters and state, and the given reference and JAX code."""
    return type(name, (AbstractConstitutiveLaw,), {
        "name": name, "params": FC.params, "state": FC.state, "test_params": FC.test_params,
        "reference": reference, "implementations": {"jax": jax},
        "wave_speed": classmethod(lambda cls, p, rho: FC.wave_speed(p, rho)), "__module__": __name__})


def _jax_scaled(law, dim):
    impl = importlib.import_module("mpmlab.laws.fixed_corotated.jax").make(law, dim)
    factor = getattr(type(law), "factor", 1.0)
    return SimpleNamespace(kirchhoff=lambda s, p, w: factor * impl.kirchhoff(s, p, w), update=impl.update)


def _jax_no_stress_gradient(law, dim):
    import jax

    impl = _jax_scaled(law, dim)
    return SimpleNamespace(kirchhoff=lambda s, p, w: jax.lax.stop_gradient(impl.kirchhoff(s, p, w)),
                           update=impl.update)


Scaled = _borrow("kit_test_scaled_jax_stress")
Scaled.factor = 1.001
Faithful = _borrow("kit_test_faithful")         # fixed_corotated's own JAX code under another class
AtRestStressed = _borrow("kit_test_stress_at_rest", SimpleNamespace(
    kirchhoff=lambda s, p, w=None: fc_ref.kirchhoff(s, p) + 1e-3 * np.eye(len(s["F"])), update=fc_ref.update))
Anisotropic = _borrow("kit_test_anisotropic", SimpleNamespace(
    kirchhoff=lambda s, p, w=None: fc_ref.kirchhoff(s, p) + 1e2 * (s["F"][0, 0] - 1.0) * np.diag([1.0, 0.0]),
    update=fc_ref.update))
NoStressGradient = _borrow("kit_test_no_stress_gradient", jax="tests.test_testing_kit:_jax_no_stress_gradient")


def test_import_needs_neither_jax_nor_warp():
    code = ("import sys, mpmlab.testing as t; t.check_law, t.law_scene\n"
            "print(sorted(m for m in ('jax', 'warp', 'torch') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


def test_kit_passes_on_a_builtin_law():
    r = testing.check_law("fixed_corotated", dims=(2,), backends=("jax", "warp"), transfers=("apic",),
                          gradients=("warp",))
    assert r["failures"] == [] and r["law"] == "fixed_corotated"
    c = r["checks"]
    assert set(c) == {"reference[jax,2d]", "reference[warp,2d]", "rest_state[2d]", "equivariance[2d]",
                      "backends_agree[apic,2d]", "gradients[warp,apic,2d]"}
    assert c["reference[warp,2d]"]["kirchhoff"] <= 1e-10 and c["reference[jax,2d]"]["update"]["F"] <= 1e-10
    assert c["rest_state[2d]"]["warp"]["tau"] == 0.0
    assert c["backends_agree[apic,2d]"]["moved"] > 1e-3 and c["backends_agree[apic,2d]"]["F"] <= 1e-9
    assert set(c["gradients[warp,apic,2d]"]) == {"x", "v", "law"}    # no shared weights: that key is skipped
    assert all(g["error"] <= 1e-6 for g in c["gradients[warp,apic,2d]"].values())


def test_a_law_under_another_class_passes_the_reference_check():
    """Control for the broken laws below: the same borrowed declarations, unbroken, pass."""
    r = testing.check_reference(Faithful, 2, "jax")
    assert r["kirchhoff"] <= 1e-10 and r["update"]["F"] <= 1e-10


def test_stress_off_by_a_factor_is_caught():
    msg = (r"^law 'kit_test_scaled_jax_stress' 2D jax: kirchhoff vs the NumPy reference: relative error "
           r"1\.000e-03 > tolerance 1e-10 \(worst: state \d+, [a-z-]+ F\)$")
    with pytest.raises(AssertionError, match=msg):
        testing.check_reference(Scaled, 2, "jax")
    # check_law goes on after a failure and names every failed check in one line
    with pytest.raises(AssertionError, match=r"^law 'kit_test_scaled_jax_stress': 1 of 3 checks failed: law "
                                             r"'kit_test_scaled_jax_stress' 2D jax: kirchhoff"):
        testing.check_law(Scaled, backends=("jax",), gradients=False)
    r = testing.check_law(Scaled, backends=("jax",), gradients=False, raise_on_failure=False)
    assert r["checks"]["reference[jax,2d]"] is None and r["checks"]["rest_state[2d]"]["jax"]["tau"] == 0.0


def test_stress_at_rest_is_caught():
    with pytest.raises(AssertionError, match=r"^law 'kit_test_stress_at_rest' 2D reference: the declared initial "
                                             r"state is not at rest: max \|tau\| = 1\.000e-03 Pa > tolerance 1e-12 Pa$"):
        testing.check_rest_state(AtRestStressed, 2)
    with pytest.raises(AssertionError, match=r"kit_test_stress_at_rest' 2D jax: kirchhoff vs the NumPy reference"):
        testing.check_reference(AtRestStressed, 2, "jax")


def test_broken_rotation_equivariance_is_caught():
    testing.check_rest_state(Anisotropic, 2)        # at rest it is fine ...
    with pytest.raises(AssertionError, match=r"^law 'kit_test_anisotropic' 2D reference: kirchhoff is not "
                                             r"rotation-equivariant: .* = \d\.\d+e-\d+ > tolerance 1e-09 \(state \d+"):
        testing.check_equivariance(Anisotropic, 2)  # ... but it has a preferred direction


def test_trajectory_mismatch_and_a_body_at_rest_are_caught():
    a = testing.rollout(["fixed_corotated"], "jax", "apic", 2)
    testing.compare_trajectories(a, a, "fixed_corotated")
    b = copy.deepcopy(a)
    b.fields["F"][-1] *= 1.0 + 1e-6
    with pytest.raises(AssertionError, match=r"^law 'fixed_corotated': field 'F' after 50 steps differs: relative "
                                             r"error 1\.000e-06 > tolerance 1e-09$"):
        testing.compare_trajectories(b, a, "fixed_corotated")
    still = copy.deepcopy(a)
    still.x[-1] = still.x[0]
    with pytest.raises(AssertionError, match=r"the body moved only 0\.000e\+00 m"):
        testing.compare_trajectories(still, still, "fixed_corotated")


def test_wrong_gradient_is_caught():
    # one observation after 4 steps: one JAX compile of 8 s instead of 13 s; the stress reaches v from step 2
    with pytest.raises(AssertionError, match=r"^law 'kit_test_no_stress_gradient' 2D jax apic: d loss / d x: AD "
                                             r".* vs central differences, relative error .* > tolerance 1e-06"):
        testing.check_gradients(NoStressGradient, "jax", "apic", 2, keys=("x",), steps=(4,))


def test_states_and_rotations_follow_the_declarations():
    """Hard states and rotation rules for arbitrary declared fields (no backend involved)."""
    from mpmlab.core.interfaces import StateField, ParamSpec

    cls = type("kit_test_fields", (AbstractConstitutiveLaw,), {
        "name": "kit_test_fields", "__module__": __name__,
        "params": (ParamSpec("G", "Pa", 3e5, low=0.0), ParamSpec("k", "-", 1.0)),
        "state": (StateField("Fe", ("D", "D"), "identity", check="positive_det"),
                  StateField("Fp", ("D", "D"), "identity"), StateField("J", (), 1.0, check="positive"),
                  StateField("s", ("D", "D"), 0.0, unit="Pa"), StateField("n", ("D",), 0.0),
                  StateField("h", (3,), 0.5), StateField("d", (), 0.0)),
        "test_rotation": {"Fp": "invariant"},
        "wave_speed": classmethod(lambda cls, p, rho: 1.0)})
    rng = np.random.default_rng(0)
    states = testing.hard_states(cls, 3, rng, {"G": 3e5, "k": 1.0})
    assert len(states) == 16 and all(set(s) == set(cls.state_fields) for s in states)
    Fs = testing.deformation_gradients(3, np.random.default_rng(0))
    for s, F in zip(states, Fs):
        assert np.array_equal(s["Fe"], F) and np.linalg.det(s["Fp"]) > 0 and s["J"] == abs(np.linalg.det(F))
        assert np.allclose(s["s"], s["s"].T) and 1e4 < np.abs(s["s"]).max() < 1e7   # the scale of G
        assert s["n"].shape == (3,) and s["h"].shape == (3,) and np.abs(s["h"] - 0.5).max() < 0.1 and s["d"] >= 0
    rules = testing.rotation_rules(cls, 3)
    assert rules == {"Fe": "left", "Fp": "invariant", "J": "invariant", "s": "conjugate", "n": "vector",
                     "h": "invariant", "d": "invariant"}
    Q = testing.rotation(3, rng)
    r = testing.rotate_state(states[0], Q, rules)
    assert np.allclose(r["Fe"], Q @ states[0]["Fe"]) and np.array_equal(r["Fp"], states[0]["Fp"])
    assert np.allclose(r["s"], Q @ states[0]["s"] @ Q.T) and np.allclose(r["n"], Q @ states[0]["n"])
    cls.test_rotation = {"Fp": "sideways"}
    with pytest.raises(ValueError, match="kit_test_fields.*test_rotation.*Fp"):
        testing.rotation_rules(cls, 3)
