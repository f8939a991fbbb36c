"""drucker_prager_jaumann at ordinary time steps (issue 17 item 3; benchmarks/stress.md, "Why the
Jaumann Drucker-Prager law had C* = 0.2").

The law integrated A.1-A.2 (JAX-MPM Eq. 21) on the Cauchy stress with constant K, G while the grid force
uses the Kirchhoff stress J sigma: a particle dilated to J (a cohesionless body thrown apart: J = 10-800
in the stress sweep's thrown square) then has the grid stiffness J K per unit mass, a wave speed
sqrt(J) c_p, and blew up once C sqrt(J) reached 2.6-4.3. Zone III (A.17) also left a deviator outside the cone
(with c = sigma_t = 0 any tau > 0 at sigma_m = 0). The law now integrates the Jaumann rate of the
Kirchhoff stress with a Hughes-Winget rotation and returns Zone III's wedge to the corner. Each test
below fails on the previous integration (checked against commit f277f7d)."""
import math

import numpy as np
import pytest

import mpmlab
from mpmlab.core import registry
from mpmlab.core.errors import SimulationDiverged

from .lawtools import EVAL, jax_law

LAW = registry.laws.get("drucker_prager_jaumann")
REF = LAW.reference
BACKENDS = ("reference", "jax", "warp")


def _prm(**kw):
    p = LAW.resolve_params(kw, "t", density=1000.0)
    return np.array([p[k] for k in LAW.param_names()])


def _update(backend, dim, states, L, dt, prm):
    if backend == "jax":
        import jax

        from mpmlab.backends.jax import stepper  # noqa: F401  (enables x64)

        st = {f: np.array([s[f] for s in states]) for f in LAW.state_fields}
        f = jax.jit(jax.vmap(jax_law(LAW, dim).update, in_axes=(0, 0, None, 0)))
        new = f(st, np.asarray(L), dt, np.tile(prm, (len(states), 1)))
        return [{k: np.asarray(v[i]) for k, v in new.items()} for i in range(len(states))]
    return EVAL[backend](LAW, dim, "update", states, prm, np.asarray(L), dt)


def _state(S, dim):
    """The law state of a 3x3 stress (2D plane strain: sigma = S[:2, :2], sigma_zz = S[2, 2])."""
    if dim == 2:
        return {"J": 1.0, "sigma": S[:2, :2].copy(), "sigma_zz": S[2, 2], "eps_p": 0.0}
    return {"J": 1.0, "sigma": S, "sigma_zz": 0.0, "eps_p": 0.0}


def _full(st):
    """The 3x3 stress of a law state (2D: diag(sigma, sigma_zz))."""
    sig = np.asarray(st["sigma"])
    return REF.embed(sig, float(st["sigma_zz"])) if len(sig) == 2 else sig


def _thrown_square(dt):
    """benchmarks/stress.py's falling_cube scene for this law: a cohesionless 0.3 m square thrown at
    (1, -2) m/s with spin 2 rad/s onto slip walls, E 1e4, nu 0.3, phi 30 deg (c_p = 3.67 m/s)."""
    body = mpmlab.Body(shape={"kind": "box", "lo": [0.35, 0.4], "hi": [0.65, 0.7]}, material="drucker_prager_jaumann",
                       params={"bulk_modulus": 1e4 / 1.2, "nu": 0.3, "friction_angle": 30.0}, density=1000.0,
                       particles_per_cell=4, velocity=[1.0, -2.0], angular_velocity=2.0)
    return mpmlab.Scene(dim=2, dx=0.05, domain=([0.0, 0.0], [1.0, 1.0]), bodies=[body], gravity=[0.0, -9.8],
                        boundaries=[mpmlab.boundaries.Walls(default="slip", thickness=2)], dt=dt, cfl_limit=1.0,
                        name="thrown_granular")


@pytest.mark.parametrize("backend", ("jax", "warp"))
def test_thrown_granular_square_stable_at_C_0_5(backend):
    """C = 0.5 (fixed dt, APIC, fp64), 400 steps: the old integration reached J <= 0 at step 100 (particle 11,
    JAX and Warp); now finite, J > 0, kinetic energy below the initial + gravity's work."""
    probe = _thrown_square("auto")
    c, v0 = probe.wave_speed(), float(np.max(np.linalg.norm(probe.particles().v, axis=1)))
    scene = _thrown_square(0.5 * probe.dx / (c + v0))
    st = mpmlab.build_stepper(scene, backend, "apic", "fp64", check_every=10)
    traj = st.rollout(steps=400, every=50, fields=("J",))          # raises SimulationDiverged on J <= 0
    assert np.all(np.isfinite(traj.x)) and np.all(traj.fields["J"] > 0.0)
    P = st.particles
    ke = 0.5 * np.einsum("n,tnd->t", traj.mass, traj.v ** 2)
    available = 0.5 * np.sum(P.mass * np.sum(P.v ** 2, axis=1)) + np.sum(P.mass) * 9.8 * 1.0
    assert ke.max() <= available


@pytest.mark.parametrize("dim", (2, 3))
@pytest.mark.parametrize("backend", BACKENDS)
def test_kirchhoff_stiffness_independent_of_J(backend, dim):
    """The grid sees tau = J sigma: its elastic increment for a strain increment dd must be C:dd whatever J
    is (the old law gave J_new C:dd: a dilated particle was J times stiffer per unit mass)."""
    prm = _prm(bulk_modulus=1e6, nu=0.3, friction_angle=30.0, cohesion=1e6)   # elastic (Zone I) here
    G, lam = REF.moduli(1e6, 0.3)
    rng = np.random.default_rng(0)
    L = -1.0 * np.eye(dim) + 0.2 * rng.standard_normal((dim, dim))
    L = 0.5 * (L + L.T)                                                      # no spin: R = I
    dt = 1e-4
    dd = L * dt
    want = lam * np.trace(dd) * np.eye(dim) + 2 * G * dd
    sig0 = -100.0 * np.eye(dim)
    for J in (1.0, 8.0, 50.0, 0.2):
        n = _update(backend, dim, [{"J": J, "sigma": sig0, "sigma_zz": -100.0, "eps_p": 0.0}], [L], dt, prm)[0]
        dtau = n["J"] * n["sigma"] - J * sig0
        assert np.max(np.abs(dtau - want)) <= 1e-9 * np.max(np.abs(want)), J
        if dim == 2:   # plane strain: d_zz = 0, so d tau_zz = lambda tr(dd)
            assert abs(n["J"] * n["sigma_zz"] + J * 100.0 - lam * np.trace(dd)) <= 1e-9 * np.max(np.abs(want)), J


@pytest.mark.parametrize("dim", (2, 3))
@pytest.mark.parametrize("backend", BACKENDS)
def test_rigid_rotation_rotates_the_stress_exactly(backend, dim):
    """A prestressed particle under a pure spin (grad_v skew, 400 steps of 0.05 rad): the Kirchhoff stress
    J sigma is rotated exactly (invariants to 1e-12; it equals R^n tau_0 R^n^T with R the Cayley rotation).
    The old first-order A.2 rotation (and tau = J sigma with J's (1 + (w dt)^2) per step drift) moved the
    eigenvalues by 3-5.6x the initial stress here."""
    prm = _prm(bulk_modulus=1e6, nu=0.3, friction_angle=30.0, cohesion=1e6)
    rng = np.random.default_rng(1)
    a = rng.standard_normal((dim, dim))
    sig0 = 1e4 * 0.5 * (a + a.T) - 3e4 * np.eye(dim)
    w = rng.standard_normal((dim, dim))
    W = 50.0 * 0.5 * (w - w.T) / np.linalg.norm(0.5 * (w - w.T)) * math.sqrt(2.0)   # |axial| = 50 rad/s
    dt = 1e-3
    state = {"J": 1.0, "sigma": sig0, "sigma_zz": -3e4, "eps_p": 0.0}   # sigma_zz: 2D plane strain (3D: unused)
    steps = 400
    if backend == "jax":      # one vmapped call per step is slow to dispatch: jit the loop
        import jax

        from mpmlab.backends.jax import stepper  # noqa: F401

        upd = jax_law(LAW, dim).update
        loop = jax.jit(lambda s: jax.lax.fori_loop(0, steps, lambda i, x: upd(x, W, dt, prm), s))
        state = {k: np.asarray(v) for k, v in loop({k: np.asarray(v, float) for k, v in state.items()}).items()}
    else:
        for _ in range(steps):
            state = _update(backend, dim, [state], [W], dt, prm)[0]
    tau = state["J"] * state["sigma"]
    ev0, ev = np.linalg.eigvalsh(sig0), np.linalg.eigvalsh(tau)
    assert np.max(np.abs(ev - ev0)) <= 1e-12 * np.max(np.abs(ev0)) * steps
    I = np.eye(dim)
    R = np.linalg.matrix_power(np.linalg.solve(I - 0.5 * W * dt, I + 0.5 * W * dt), steps)
    assert np.max(np.abs(tau - R @ sig0 @ R.T)) <= 1e-10 * np.max(np.abs(sig0))
    assert state["eps_p"] == 0.0
    if dim == 2:   # an in-plane spin leaves tau_zz alone
        assert abs(state["J"] * state["sigma_zz"] + 3e4) <= 1e-10 * 3e4


@pytest.mark.parametrize("dim", (2, 3))
@pytest.mark.parametrize("backend", BACKENDS)
def test_returned_stress_is_admissible_in_every_zone(backend, dim):
    """After the return map f_s <= 0 and f_t <= 0, for trials in all three zones and in Zone III's wedge
    tau_P < tau <= tau_P + alpha_P (sigma_m - sigma_t), which A.17 alone leaves outside the cone; the wedge
    goes to the corner (sigma_t, tau_P). Cohesionless (the stress sweep's material) and cohesive."""
    rng = np.random.default_rng(2)
    for coh, st_frac in ((0.0, 0.0), (2e3, 0.5)):
        q, k, qpsi = REF.cone_constants(30.0, 10.0, coh)
        st = st_frac * (k / q)
        prm = _prm(bulk_modulus=1e6, nu=0.3, friction_angle=30.0, dilation_angle=10.0, cohesion=coh,
                   tensile_strength=st)
        tau_p, alpha_p = k - q * st, math.sqrt(1 + q * q) - q
        trials, wedge = [], []
        for _ in range(40):
            sm = rng.uniform(-3e4, 2e4)
            trials.append((sm, rng.uniform(0, 3e4)))
        for f in (0.1, 0.5, 0.99):                                  # Zone III wedge: tau_P < tau <= h-line
            sm = st + rng.uniform(1e3, 1e4)
            wedge.append((sm, tau_p + f * alpha_p * (sm - st)))
        sigs = []   # 3x3 stresses (2D: plane strain, diag(sigma, sigma_zz); the invariants are over three)
        for sm, tau in trials + wedge:
            s = rng.standard_normal((3, 3)); s = 0.5 * (s + s.T)
            if dim == 2:
                s[:2, 2] = s[2, :2] = 0.0
            s -= np.trace(s) / 3 * np.eye(3)
            sigs.append(s * tau / math.sqrt(0.5 * np.sum(s * s)) + sm * np.eye(3))
        zones = [REF.zone(*REF.invariants(s)[::2], prm) for s in sigs]
        assert set(zones) == {1, 2, 3} and all(z == 3 for z in zones[-len(wedge):])
        new = _update(backend, dim, [_state(s, dim) for s in sigs], np.zeros((len(sigs), dim, dim)), 1e-3, prm)
        new = [dict(n, sigma=_full(n)) for n in new]
        scale = 3e4
        for s, z, n in zip(sigs, zones, new):
            sm, _, tau = REF.invariants(n["sigma"])
            assert tau - k + q * sm <= 1e-9 * scale, (coh, z)              # f_s <= 0
            assert sm - st <= 1e-9 * scale, (coh, z)                       # f_t <= 0
            assert n["eps_p"] >= 0.0
        for (sm_t, tau_t), n in zip(wedge, new[-len(wedge):]):
            sm, _, tau = REF.invariants(n["sigma"])
            assert abs(sm - st) <= 1e-9 * scale and abs(tau - tau_p) <= 1e-9 * scale     # the corner
            G, _ = REF.moduli(1e6, 0.3)
            want = math.sqrt(2) / 3 * (sm_t - st) / 1e6 + (tau_t - tau_p) / G / math.sqrt(3)
            assert abs(n["eps_p"] - want) <= 1e-12 + 1e-9 * want
