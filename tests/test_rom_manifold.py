"""The reduced model's maps (mpmlab.rom.manifold; ROM paper Sec. 3): the inverse map, the projections
and the initial state, on a random deformation map (fp64)."""
from __future__ import annotations

import jax
import numpy as np
import pytest

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402

from mpmlab.rom import manifold as M  # noqa: E402
from mpmlab.rom import networks as N  # noqa: E402


@pytest.fixture(scope="module")
def g():
    """A random g of d_hat = 2 on a 4 x 1 x 1 cm bar, displacements ~2 mm (F - I ~ 0.1)."""
    spec = N.RomSpec(dim=3, latent=2)
    params = N.to_jax(N.init_params(spec, seed=3), jnp.float64)
    norm = N.to_jax({"X_min": np.zeros(3), "X_max": np.array([0.04, 0.01, 0.01]), "u_mean": np.zeros(3),
                     "u_std": np.full(3, 2e-3)}, jnp.float64)
    rng = np.random.default_rng(0)
    X = jnp.asarray(rng.uniform([0, 0, 0], [0.04, 0.01, 0.01], size=(60, 3)))
    return params, norm, X


def test_inverse_map_residual_and_flags(g):
    params, norm, X = g
    z = jnp.array([0.4, -0.7])
    x = N.g_apply(params, norm, X, z[None, :])
    shift = jnp.mean(x - X, axis=0)
    out = M.inverse_map(params, norm, x, z, x - shift)
    assert bool(jnp.all(out.converged)) and float(out.residual.max()) <= 1e-10
    np.testing.assert_allclose(np.asarray(out.X), np.asarray(X), rtol=0, atol=1e-9)
    # a point no reference position maps to within the Newton budget (far outside): flagged, not silent
    far = M.inverse_map(params, norm, jnp.array([[5.0, 5.0, 5.0]]), z, jnp.array([[0.0, 0.0, 0.0]]), iterations=3)
    assert not bool(far.converged[0])


def test_on_manifold_states_are_fixed_points_of_the_projections(g):
    params, norm, X = g
    z, zd = jnp.array([0.3, 0.2]), jnp.array([1.5, -0.4])
    XM = X[:20]
    x, v = N.g_velocity(params, norm, XM, z[None, :], zd[None, :])
    np.testing.assert_allclose(np.asarray(M.project_velocity(params, norm, XM, z, v)), np.asarray(zd), atol=1e-10)
    # nonlinear (Eq. 22) from a perturbed extrapolation; linear (Alg. 7) is exact for its own step
    z_prev = z - jnp.array([0.01, -0.02])
    got = M.project_nonlinear(params, norm, XM, x, z + 0.02, z_prev + 0.02)
    np.testing.assert_allclose(np.asarray(got), np.asarray(z), atol=1e-9)
    np.testing.assert_allclose(np.asarray(M.project_linear(z, zd, 1e-3)), np.asarray(z + 1e-3 * zd), atol=1e-15)


def test_initial_state_recovers_latent_and_latent_velocity(g):
    params, norm, X = g
    z, zd = jnp.array([-0.5, 0.8]), jnp.array([0.3, 2.0])
    x0, v0 = N.g_velocity(params, norm, X, z[None, :], zd[None, :])
    s = M.initial_state(params, norm, X, x0, v0, jnp.zeros(2))
    np.testing.assert_allclose(np.asarray(s.z), np.asarray(z), atol=1e-9)
    np.testing.assert_allclose(np.asarray(s.zdot), np.asarray(zd), atol=1e-8)
    assert float(s.misfit) < 1e-20
