"""Weakly compressible Newtonian fluid (JAX-MPM Eqs. 19-20): closed forms on the reference, JAX and Warp (fp64)."""
import numpy as np
import pytest

from mpmlab.core.errors import InvalidParameterError
from mpmlab.core import registry

from .lawtools import EVAL

LAW = registry.laws.get("newtonian_fluid")
BACKENDS = ("reference", "jax", "warp")
DIMS = (2, 3)
C, MU, RHO0 = 20.0, 0.5, 997.0
NO_CUTOFF = -1e30        # min_pressure: Eq. 20 unclamped (the closed forms below include tension, J > 1)
PRM = np.array([C, MU, RHO0, NO_CUTOFF])


def update(backend, dim, states, L, dt, prm=PRM):
    return EVAL[backend](LAW, dim, "update", states, prm, np.asarray(L), dt)


def kirchhoff(backend, dim, states, prm=PRM):
    return EVAL[backend](LAW, dim, "kirchhoff", states, prm)


def scale():
    return C * C * RHO0


@pytest.mark.parametrize("dim", DIMS)
@pytest.mark.parametrize("backend", BACKENDS)
def test_rest_stays_stress_free(backend, dim):
    st = [{k: v[0] for k, v in LAW.initial_state(1, dim).items()}]
    for _ in range(3):
        st = update(backend, dim, st, np.zeros((1, dim, dim)), 1e-3)
    assert abs(st[0]["J"] - 1.0) == 0.0
    assert np.max(np.abs(st[0]["sigma"])) == 0.0
    assert np.max(np.abs(kirchhoff(backend, dim, st))) == 0.0


@pytest.mark.parametrize("dim", DIMS)
@pytest.mark.parametrize("backend", BACKENDS)
def test_hydrostatic_eos_closed_form(backend, dim):
    """Isotropic rate a I from J0: J = J0 (1 + a dt)^D, sigma = -c^2 rho0 (1/J - 1) I + 2 mu a (1 - D/3) I."""
    J0 = np.array([0.9, 1.0, 1.05, 1.2])
    rates = np.array([-3.0, 0.0, 2.0, 5.0])
    dt = 1e-2
    eye = np.eye(dim)
    states = [{"J": j, "sigma": np.zeros((dim, dim))} for j in J0]
    new = update(backend, dim, states, [a * eye for a in rates], dt)
    for j0, a, n in zip(J0, rates, new):
        J = j0 * (1.0 + a * dt) ** dim
        p = C * C * RHO0 * (1.0 / J - 1.0)
        want = (-p + 2.0 * MU * a * (1.0 - dim / 3.0)) * eye   # 1/3 deviator also in 2D (paper convention)
        assert abs(n["J"] - J) <= 1e-14 * J
        assert np.max(np.abs(n["sigma"] - want)) <= 1e-10 * scale()
    tau = kirchhoff(backend, dim, new)
    for n, t in zip(new, tau):
        assert np.max(np.abs(t - n["J"] * n["sigma"])) <= 1e-12 * scale()


@pytest.mark.parametrize("dim", DIMS)
@pytest.mark.parametrize("backend", BACKENDS)
def test_shear_rate_gives_viscous_deviator(backend, dim):
    """Simple shear L = g e_x (x) e_y keeps J = 1 (no pressure); sigma = 2 mu D = mu g (e_xy + e_yx)."""
    gs = np.array([-4.0, 0.5, 10.0])
    Ls = []
    for g in gs:
        L = np.zeros((dim, dim)); L[0, 1] = g
        Ls.append(L)
    states = [{"J": 1.0, "sigma": np.zeros((dim, dim))} for _ in gs]
    new = update(backend, dim, states, Ls, 1e-2)
    for g, L, n in zip(gs, Ls, new):
        D = 0.5 * (L + L.T)
        assert abs(n["J"] - 1.0) <= 1e-15
        assert np.max(np.abs(n["sigma"] - 2.0 * MU * D)) <= 1e-12 * MU * abs(g)


def test_matches_reference_on_random_states():
    rng = np.random.default_rng(0)
    for dim in DIMS:
        n = 32
        A = rng.standard_normal((n, dim, dim))
        states = [{"J": j, "sigma": 0.5 * (a + a.T) * 1e3} for j, a in zip(rng.uniform(0.8, 1.2, n), A)]
        L = 5.0 * rng.standard_normal((n, dim, dim))
        ref = update("reference", dim, states, L, 1e-3)
        for backend in ("jax", "warp"):
            got = update(backend, dim, states, L, 1e-3)
            for f in LAW.state_fields:
                a, b = np.array([g[f] for g in got]), np.array([r[f] for r in ref])
                assert np.max(np.abs(a - b)) <= 1e-10 * np.max(np.abs(b)), (backend, dim, f)


def test_parameters_density_default_and_wave_speed():
    prm = LAW.resolve_params({}, "t", density=1234.0)
    assert prm == {"sound_speed": 35.0, "viscosity": 1.01e-3, "rest_density": 1234.0, "min_pressure": 0.0}
    assert LAW.resolve_params({"rest_density": 1000.0}, "t", density=1234.0)["rest_density"] == 1000.0
    assert LAW.wave_speed(prm, 1234.0) == 35.0
    with pytest.raises(InvalidParameterError):
        LAW.resolve_params({"sound_speed": 0.0}, "t", density=1000.0)
    with pytest.raises(InvalidParameterError):
        LAW.resolve_params({"viscosity": -1.0}, "t", density=1000.0)
    with pytest.raises(InvalidParameterError):   # a cut-off above 0 would push a liquid apart at rest
        LAW.resolve_params({"min_pressure": 1.0}, "t", density=1000.0)


@pytest.mark.parametrize("dim", DIMS)
@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("pmin", (0.0, -500.0))
def test_tension_cutoff(backend, dim, pmin):
    """p = max(c^2 rho0 (1/J - 1), min_pressure): compression unchanged, tension clamped at min_pressure."""
    prm = np.array([C, MU, RHO0, pmin])
    J0 = np.array([0.95, 1.0, 1.0001, 1.01, 1.3])
    eye = np.eye(dim)
    states = [{"J": j, "sigma": np.zeros((dim, dim))} for j in J0]
    L = np.zeros((len(J0), dim, dim))
    new = update(backend, dim, states, L, 1e-3, prm)
    for j, n in zip(J0, new):
        p = max(C * C * RHO0 * (1.0 / j - 1.0), pmin)
        assert abs(n["J"] - j) <= 1e-14
        assert np.max(np.abs(n["sigma"] + p * eye)) <= 1e-10 * scale()
    # J = 1.0001 is a small tension (-39.9 Pa): clamped by 0, kept by -500 Pa
    assert new[2]["sigma"][0, 0] == (0.0 if pmin == 0.0 else pytest.approx(C * C * RHO0 * (1 - 1 / 1.0001), rel=1e-9))
    tau = kirchhoff(backend, dim, new, prm)
    for n, t in zip(new, tau):
        assert np.max(np.abs(t - n["J"] * n["sigma"])) <= 1e-12 * scale()


def test_tension_cutoff_jax_gradient():
    """JAX stays differentiable through the cut-off: d sigma_xx / d J is c^2 rho0 / J^2 in compression and
    at rest (p == min_pressure == 0 keeps the unclamped branch), 0 where the tension is clamped."""
    import jax
    import jax.numpy as jnp

    from .lawtools import jax_law

    jax.config.update("jax_enable_x64", True)
    f = jax_law(LAW, 2)

    def sxx(J):
        st = {"J": J, "sigma": jnp.zeros((2, 2))}
        return f.update(st, jnp.zeros((2, 2)), 1e-3, jnp.array([C, MU, RHO0, 0.0]))["sigma"][0, 0]

    g = jax.grad(sxx)
    for J, want in ((0.9, C * C * RHO0 / 0.81), (1.0, C * C * RHO0), (1.1, 0.0)):
        assert float(g(J)) == pytest.approx(want, rel=1e-12)
