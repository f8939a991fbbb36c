"""Every registered law x backend against its NumPy float64 reference, and constitutive properties
(``mpmlab.testing``: built-in laws and installed plugin laws alike).

Deformation gradients: random, rotated, near-singular (a singular value of 1e-3) and large-strain
(stretch 3), and the other declared state fields generated from their ``StateField`` declarations
(``mpmlab.testing.states``); fp64 agreement to 1e-10 relative (issue #2). Properties (verification
note #6): zero stress at rest, rotation equivariance tau(R.s) = R tau(s) R^T and the same for the
state update, symmetric Kirchhoff stress P F^T. Parameters: the laws' declared defaults
(``params="defaults"``; ``test_params`` only for a parameter without a default).
"""
import pytest

from mpmlab import testing
from mpmlab.core import registry

LAWS = registry.laws.names()
DIMS = (2, 3)
BACKENDS = ("jax", "warp")


@pytest.mark.parametrize("dim", DIMS)
@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("name", LAWS)
def test_stress_matches_reference(name, backend, dim):
    testing.check_reference(name, dim, backend, what="kirchhoff", params="defaults", seed=1, tol=1e-10)


@pytest.mark.parametrize("dim", DIMS)
@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("name", LAWS)
def test_update_matches_reference(name, backend, dim):
    testing.check_reference(name, dim, backend, what="update", params="defaults", seed=2, dt=1e-2, tol=1e-10)


@pytest.mark.parametrize("dim", DIMS)
@pytest.mark.parametrize("name", LAWS)
def test_zero_stress_at_rest(name, dim):
    # the rest state has no stress and stays at rest under zero velocity gradient
    testing.check_rest_state(name, dim, ("reference",), params="defaults", dt=1e-3, tol=1e-12)


@pytest.mark.parametrize("dim", DIMS)
@pytest.mark.parametrize("name", LAWS)
def test_rotation_equivariance_and_symmetry(name, dim):
    # P F^T symmetric (1e-10), P(RF) = R P(F) and the update commutes with rotations (1e-9)
    testing.check_equivariance(name, dim, params="defaults", seed=3, dt=1e-2, tol=1e-9, sym_tol=1e-10)


@pytest.mark.parametrize("name", LAWS)
def test_parameters_declare_units_and_ranges(name):
    cls = registry.laws.get(name)
    law = type(cls.from_config(dict(cls.test_options), name))   # as configured (phase_change: a pair's class)
    # a law declares its parameters, or carries its constants in shared weights (a neural law)
    assert law.params or law.from_config(law.test_options, name).weight_shapes(2), \
        "a law must declare its parameters (or shared weights)"
    for p in law.params:
        assert p.unit, f"{name}.{p.name} has no unit"
        assert p.low < p.high
    assert law.state, "a law must declare its state fields"
    if registry.laws.provenance(name) == "mpmlab":      # the built-ins share the standard fields
        assert set(law.state_fields) <= {"F", "J", "sigma", "eps_p", "clock", "eps_zz", "sigma_zz"}  # _common's
    assert law.wave_speed(testing.resolve_params(law, "defaults"), 1000.0) > 0
    assert set(law.test_params) <= set(law.param_names()), f"{name}.test_params names unknown parameters"
    testing.resolve_params(law)  # its test_params are in range
