"""Jaumann-rate Drucker-Prager law (JAX-MPM Eq. 21, App. A): return-map properties on the reference,
JAX and Warp (fp64). With grad_v = 0 the trial stress is the given stress, so (sigma_m, tau) pick the zone.

2D is plane strain (issue 18): a 2D state carries sigma_zz and the invariants are those of the 3x3 stress
diag(sigma, sigma_zz) (A.3 over three components), so the checks build and read 3x3 stresses (``full``,
``state_of``) in 2D and 3D alike, with grad_v embedded as diag(L, 0) (d_zz = 0, no spin about x or y)."""
import math
from functools import lru_cache

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mpmlab.core import registry
from mpmlab.core.errors import InvalidParameterError

from .lawtools import EVAL, jax_law

LAW = registry.laws.get("drucker_prager_jaumann")
REF = LAW.reference
BACKENDS = ("reference", "jax", "warp")
DIMS = (2, 3)
K, NU, PHI, PSI, COH = 1.0e6, 0.3, 30.0, 10.0, 2.0e3
Q, KPHI, QPSI = REF.cone_constants(PHI, PSI, COH)
ST = 0.5 * KPHI / Q
PRM = np.array([K, NU, PHI, PSI, COH, ST])
SCALE = 1e4   # stress scale of the test states [Pa]


@lru_cache(maxsize=None)
def _jax_update(dim):
    import jax

    from mpmlab.backends.jax import stepper  # noqa: F401  (enables x64)

    return jax.jit(jax.vmap(jax_law(LAW, dim).update, in_axes=(0, 0, None, 0)))


def update(backend, dim, states, L, dt, prm=PRM):
    if backend != "jax":
        return EVAL[backend](LAW, dim, "update", states, prm, np.asarray(L), dt)
    # jitted (the eager vmap of the branch-free return map is slow); one compile per (dim, count)
    st = {f: np.array([s[f] for s in states]) for f in LAW.state_fields}
    new = _jax_update(dim)(st, np.asarray(L), dt, np.tile(prm, (len(states), 1)))
    return [{k: np.asarray(v[i]) for k, v in new.items()} for i in range(len(states))]


def rotation(dim, rng):
    if dim == 3:
        return Rotation.random(random_state=int(rng.integers(1 << 31))).as_matrix()
    th = rng.uniform(0, 2 * np.pi)
    return np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])


def stress(dim, sm, tau, rng):
    """A symmetric 3x3 stress with mean stress sm and A.4 shear invariant tau, randomly oriented (2D: in the
    plane, block-diagonal diag(sigma, sigma_zz), the plane-strain stress)."""
    s = np.zeros((3, 3))
    s[0, 0], s[1, 1] = 1.0, -0.3
    s = rng.standard_normal() * s + rng.standard_normal((3, 3))
    s = 0.5 * (s + s.T)
    if dim == 2:
        s[:2, 2] = s[2, :2] = 0.0
    s -= np.trace(s) / 3 * np.eye(3)
    s *= tau / math.sqrt(0.5 * np.sum(s * s))
    return s + sm * np.eye(3)


def state_of(S, dim, J=1.0, eps_p=0.0):
    """The law state of a 3x3 stress S (2D: sigma = S[:2, :2], sigma_zz = S[2, 2])."""
    if dim == 2:
        return {"J": J, "sigma": S[:2, :2].copy(), "sigma_zz": np.asarray(S[2, 2]), "eps_p": eps_p}
    return {"J": J, "sigma": S, "sigma_zz": np.asarray(0.0), "eps_p": eps_p}


def full(st):
    """The 3x3 stress of a law state (2D: diag(sigma, sigma_zz))."""
    sig = np.asarray(st["sigma"])
    return REF.embed(sig, float(st["sigma_zz"])) if len(sig) == 2 else sig


def embed_L(L):
    """grad_v as a 3x3 velocity gradient (2D: diag(L, 0))."""
    out = np.zeros((3, 3))
    d = len(L)
    out[:d, :d] = L
    return out


def trial_full(st, L, dt):
    """The 3x3 trial stress of A.1-A.2 (2D: with sigma_zz's trial)."""
    return REF.jaumann_trial(full(st), embed_L(L), dt, PRM, st["J"])


def random_states(dim, n, rng):
    states = []
    for _ in range(n):
        S = stress(dim, rng.uniform(-3, 1) * SCALE, rng.uniform(0, 1.5) * SCALE, rng)
        states.append(state_of(S, dim, rng.uniform(0.9, 1.1), rng.uniform(0, 0.05)))
    return states


def zone_of(sig):
    sm, _, tau = REF.invariants(sig)
    return REF.zone(sm, tau, PRM)


@pytest.mark.parametrize("dim", DIMS)
@pytest.mark.parametrize("backend", BACKENDS)
def test_rest_stays_stress_free(backend, dim):
    st = [{k: v[0] for k, v in LAW.initial_state(1, dim).items()}]
    prm = LAW.resolve_params({}, "t", density=1800.0)
    prm = np.array([prm[k] for k in LAW.param_names()])
    for _ in range(3):
        st = update(backend, dim, st, np.zeros((1, dim, dim)), 1e-3, prm)
    assert st[0]["J"] == 1.0 and st[0]["eps_p"] == 0.0
    assert np.max(np.abs(st[0]["sigma"])) == 0.0 and float(st[0]["sigma_zz"]) == 0.0


@pytest.mark.parametrize("dim", DIMS)
@pytest.mark.parametrize("backend", BACKENDS)
def test_elastic_increment_zone1(backend, dim):
    """Zone I: the A.1-A.2 increment on the Kirchhoff stress, (R J sigma R^T + lambda tr(dd) I + 2 G dd) / J_new
    with the Hughes-Winget rotation R, no plastic strain; within O(dt^2 |L|^2 + tr(dd)) of A.2's literal
    first-order form at J = 1."""
    rng = np.random.default_rng(0)
    G, lam = REF.moduli(K, NU)
    sig = stress(dim, -2.0 * SCALE, 0.1 * SCALE, rng)
    L = 0.01 * rng.standard_normal((dim, dim))
    L3 = embed_L(L)                                                  # 2D: d_zz = 0, no out-of-plane spin
    dt = 1e-3
    dd, dw = 0.5 * (L3 + L3.T) * dt, 0.5 * (L3 - L3.T) * dt
    I = np.eye(3)
    R = np.linalg.solve(I - 0.5 * dw, I + 0.5 * dw)                 # Cayley, by a solve (the law: closed form)
    for J in (1.0, 0.93):
        J_new = J * np.linalg.det(I + dt * L3)
        want = (R @ (J * sig) @ R.T + lam * np.trace(dd) * I + 2 * G * dd) / J_new
        assert zone_of(want) == 1
        n = update(backend, dim, [state_of(sig, dim, J, 0.01)], [L], dt)[0]
        assert np.max(np.abs(full(n) - want)) <= 1e-12 * SCALE
        assert n["eps_p"] == 0.01
        assert abs(n["J"] - J_new) <= 1e-15
    literal = sig + sig @ dw.T + dw @ sig + lam * np.trace(dd) * I + 2 * G * dd    # A.1-A.2 as printed
    n = update(backend, dim, [state_of(sig, dim)], [L], dt)[0]
    assert np.max(np.abs(full(n) - literal)) <= 2.0 * np.max(np.abs(sig)) * (np.max(np.abs(L)) * dt * dim)


@pytest.mark.parametrize("dim", DIMS)
@pytest.mark.parametrize("backend", BACKENDS)
def test_zone2_returns_onto_shear_surface(backend, dim):
    """Both Zone II branches (f_t < 0, and f_t >= 0 with h > 0) end on f_s = 0 with A.15's eps_p increment."""
    rng = np.random.default_rng(1)
    G, _ = REF.moduli(K, NU)
    trials = []
    for sm in (-3.0 * SCALE, -0.5 * SCALE, 0.0, 0.5 * ST):          # compressive / mild: f_t < 0
        trials.append(stress(dim, sm, KPHI - Q * sm + rng.uniform(0.1, 1.0) * SCALE, rng))
    for sm in (ST, 1.2 * ST, 1.6 * ST):                             # f_t >= 0, h > 0
        tau_p, alpha_p = KPHI - Q * ST, math.sqrt(1 + Q * Q) - Q
        trials.append(stress(dim, sm, tau_p + alpha_p * (sm - ST) + 0.2 * SCALE, rng))
    assert all(zone_of(t) == 2 for t in trials)
    new = update(backend, dim, [state_of(t, dim) for t in trials], np.zeros((len(trials), dim, dim)), 1e-3)
    for t, n in zip(trials, new):
        sm, s, tau = REF.invariants(full(n))
        assert sm <= KPHI / Q                                      # returned below the apex (tau >= 0)
        assert abs(tau - KPHI + Q * sm) <= 1e-9 * SCALE            # f_s = 0
        sm_t, s_t, tau_t = REF.invariants(t)
        assert np.max(np.abs(s * tau_t - s_t * tau)) <= 1e-9 * SCALE * tau_t   # radial: same deviator direction
        dl = (tau_t - KPHI + Q * sm_t) / (G + K * Q * QPSI)
        assert abs(n["eps_p"] - dl * math.sqrt(1 / 3 + 2 / 9 * QPSI ** 2)) <= 1e-12 * max(n["eps_p"], 1e-3)
        assert abs(sm - (sm_t - K * QPSI * dl)) <= 1e-9 * SCALE    # A.12


@pytest.mark.parametrize("dim", DIMS)
@pytest.mark.parametrize("backend", BACKENDS)
def test_zone3_caps_mean_stress_at_tensile_strength(backend, dim):
    rng = np.random.default_rng(2)
    trials = [stress(dim, sm, tau, rng) for sm, tau in
              ((1.1 * ST, 0.0), (1.5 * ST, 0.1 * (KPHI - Q * ST)), (5.0 * ST, 0.5 * (KPHI - Q * ST)))]
    assert all(zone_of(t) == 3 for t in trials)
    new = update(backend, dim, [state_of(t, dim) for t in trials], np.zeros((len(trials), dim, dim)), 1e-3)
    for t, n in zip(trials, new):
        sm, s, _ = REF.invariants(full(n))
        sm_t, s_t, _ = REF.invariants(t)
        assert abs(sm - ST) <= 1e-12 * SCALE                        # A.17: sigma_m = sigma_t
        assert np.max(np.abs(s - s_t)) <= 1e-12 * SCALE            # deviator untouched
        assert abs(n["eps_p"] - math.sqrt(2) / 3 * (sm_t - ST) / K) <= 1e-15   # A.18-A.19


@pytest.mark.parametrize("dim", DIMS)
@pytest.mark.parametrize("backend", BACKENDS)
def test_jaumann_objectivity(backend, dim):
    """update(R sigma R^T, R L R^T) = R update(sigma, L) R^T, in all three zones."""
    rng = np.random.default_rng(3)
    states = random_states(dim, 24, rng)
    L = 20.0 * rng.standard_normal((len(states), dim, dim))
    dt = 1e-3
    R = [rotation(dim, rng) for _ in states]
    a = update(backend, dim, states, L, dt)
    rs = [dict(s, sigma=r @ s["sigma"] @ r.T) for s, r in zip(states, R)]
    b = update(backend, dim, rs, [r @ l @ r.T for r, l in zip(R, L)], dt)
    zones = set()
    for s, l, r, x, y in zip(states, L, R, a, b):
        zones.add(zone_of(trial_full(s, l, dt)))
        assert np.max(np.abs(r @ x["sigma"] @ r.T - y["sigma"])) <= 1e-9 * SCALE
        assert abs(float(x["sigma_zz"]) - float(y["sigma_zz"])) <= 1e-9 * SCALE
        assert abs(x["eps_p"] - y["eps_p"]) <= 1e-12
        assert abs(x["J"] - y["J"]) <= 1e-13
    assert zones == {1, 2, 3}


@pytest.mark.parametrize("dim", DIMS)
def test_backends_match_reference_and_eps_p_never_decreases(dim):
    rng = np.random.default_rng(4)
    states = random_states(dim, 64, rng)
    L = 20.0 * rng.standard_normal((len(states), dim, dim))
    ref = update("reference", dim, states, L, 1e-3)
    assert {zone_of(trial_full(s, l, 1e-3)) for s, l in zip(states, L)} == {1, 2, 3}
    for backend in ("reference", "jax", "warp"):
        got = update(backend, dim, states, L, 1e-3)
        assert all(g["eps_p"] >= s["eps_p"] for g, s in zip(got, states))
        for f in LAW.state_fields:
            x, y = np.array([g[f] for g in got]), np.array([r[f] for r in ref])
            assert np.max(np.abs(x - y)) <= 1e-10 * np.max(np.abs(y)), (backend, f)


@pytest.mark.parametrize("dim", DIMS)
def test_jax_gradients_finite_at_rest(dim):
    import jax
    import jax.numpy as jnp

    from mpmlab.backends.jax import stepper  # noqa: F401  (enables x64)

    impl = jax_law(LAW, dim)

    def loss(prm, L):
        st = {"J": jnp.array(1.0), "sigma": jnp.zeros((dim, dim)), "sigma_zz": jnp.array(0.0), "eps_p": jnp.array(0.0)}
        for _ in range(2):
            st = impl.update(st, L, 1e-3, prm)
        return jnp.sum(st["sigma"] ** 2) + st["sigma_zz"] ** 2 + st["eps_p"]

    grad = jax.jit(jax.grad(loss, argnums=(0, 1)))
    for L in (np.zeros((dim, dim)), 30.0 * np.eye(dim), 50.0 * np.ones((dim, dim))):
        g = grad(jnp.asarray(PRM), jnp.asarray(L))
        assert all(bool(jnp.all(jnp.isfinite(x))) for x in g)


def test_parameters_checks_and_wave_speed():
    prm = LAW.resolve_params({}, "t", density=1800.0)
    assert prm["bulk_modulus"] == 0.7e6 and prm["friction_angle"] == 19.8 and prm["tensile_strength"] == 0.0
    G, lam = REF.moduli(K, NU)
    assert math.isclose(lam, K - 2 * G / 3) and math.isclose(K, lam + 2 * G / 3)
    assert math.isclose(G, K * 3 * (1 - 2 * NU) / (2 * (1 + NU)))
    assert math.isclose(LAW.wave_speed(dict(zip(LAW.param_names(), PRM)), 2000.0), math.sqrt((K + 4 * G / 3) / 2000.0))
    with pytest.raises(InvalidParameterError, match="dilation"):
        LAW.resolve_params({"friction_angle": 20.0, "dilation_angle": 25.0}, "t")
    with pytest.raises(InvalidParameterError, match="apex"):
        LAW.resolve_params({"tensile_strength": 1.0}, "t")           # cohesionless: apex at 0
    LAW.resolve_params({"cohesion": COH, "friction_angle": PHI, "tensile_strength": KPHI / Q}, "t")
    LAW.resolve_params({"friction_angle": 0.0, "cohesion": 10.0, "tensile_strength": 1e9}, "t")  # q_phi = 0
    with pytest.raises(InvalidParameterError):
        LAW.resolve_params({"friction_angle": 90.0}, "t")


@pytest.mark.parametrize("backend", ("reference", "jax", "warp"))
def test_zone2_return_beyond_apex_goes_to_the_corner(backend):
    """A trial far in tension beyond the apex (the literal A.12-A.13 flip the deviator there) ends at
    sigma_m = sigma_t with a non-negative tau on the shear surface, on every backend."""
    from mpmlab.core import registry

    from .lawtools import EVAL, jax_law

    law = registry.laws.get("drucker_prager_jaumann")
    prm = np.array([law.resolve_params({"friction_angle": 30.0, "dilation_angle": 0.0}, "t")[k]
                    for k in law.param_names()])
    sig = np.diag([3000.0, -1000.0])
    state = [{"J": 1.0, "sigma": sig, "sigma_zz": np.asarray(0.0), "eps_p": 0.0}]   # plane strain: sigma_m = 667 Pa
    out = EVAL[backend](law, 2, "update", state, prm, np.zeros((1, 2, 2)), 1e-3)[0]
    new = full(out)
    sm = np.trace(new) / 3
    s = new - sm * np.eye(3)
    assert sm <= 1e-9                      # sigma_t = 0: no tension survives the return
    assert np.sqrt(0.5 * np.sum(s * s)) <= 1e-9 + 1e-9 * abs(sig).max()
