"""Hencky laws (NCLaw App. B, Eqs. 14-19): closed forms, return maps and invariances on the NumPy
reference, JAX and Warp (fp64), plus JAX derivatives at the rest state and Warp fp32 builds.

Closed forms (verification note row 6, E = 1e4, nu = 0.3), with tau the Kirchhoff stress and P = tau F^-T:

* uniaxial strain F = diag(s, 1, ..): P11 = (2 mu + lambda) ln s / s, P22 (= P33) = lambda ln s;
* simple shear F = I + gamma e1 (x) e2: tau12 = 2 mu asinh(gamma/2) / sqrt(1 + gamma^2/4), tau11 = -tau22
  = gamma/2 tau12, tau33 = 0 (tr eps = 0, so lambda drops out).

Drucker-Prager (row 6b): with alpha = sqrt(2/3) 2 sin(phi) / (3 - sin(phi)) and the return written for
d = dim (delta_gamma = |eps_hat| + (d lambda + 2 mu)/(2 mu) tr(eps) alpha), a compressive "shear case"
return (tr eps < 0, delta_gamma > 0) gives 2 mu |eps_hat_new| = -(d lambda + 2 mu) tr(eps) alpha while
tr(tau) = (d lambda + 2 mu) tr(eps), so the returned stress lies on the cone

    f(tau) = |dev tau| + alpha tr(tau) = 0     (Frobenius norm; dev and tr over d dimensions),

i.e. the cone constant in stress space is alpha itself. 2D is plane strain (issue 18): the state carries the
elastic out-of-plane strain eps_zz and the return acts on (eps_1, eps_2, eps_zz) with d = 3, so in 2D these
checks run on the three principal strains and the 3x3 stress diag(tau_2D, tau_zz) (``tau3``; before issue
18 they used d = 2, the old 2D continuum).
Von Mises (row 6c): the return keeps tr(eps), so det F (2D: det F e^eps_zz), and lands on |dev tau| = tau_Y
(Frobenius, over three components).
"""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mpmlab.core import registry
from mpmlab.laws._linalg_np import lame, polar_rotation

from .lawtools import EVAL, jax_law

DP = registry.laws.get("hencky_drucker_prager")
VM = registry.laws.get("hencky_von_mises")
BACKENDS = ("reference", "jax", "warp")
DIMS = (2, 3)
E, NU, PHI, TAU_Y = 1.0e4, 0.3, 30.0, 300.0
MU, LAM = lame(E, NU)
PRM_DP = np.array([E, NU, PHI])
PRM_VM = np.array([E, NU, TAU_Y])
ALPHA = np.sqrt(2.0 / 3.0) * 2.0 * np.sin(np.radians(PHI)) / (3.0 - np.sin(np.radians(PHI)))


def rotation(dim, rng):
    if dim == 3:
        return Rotation.random(random_state=int(rng.integers(1 << 31))).as_matrix()
    th = rng.uniform(0.0, 2.0 * np.pi)
    return np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])


def states(Fs, ezz=None):
    """Law states of the F's (eps_zz: the elastic out-of-plane strain, 0 unless given; unused in 3D)."""
    ezz = [0.0] * len(Fs) if ezz is None else ezz
    return [{"F": F, "eps_zz": np.asarray(float(z))} for F, z in zip(Fs, ezz)]


def tau(law, backend, Fs, prm, ezz=None):
    return np.asarray(EVAL[backend](law, len(Fs[0]), "kirchhoff", states(Fs, ezz), prm))


def project_full(law, backend, Fs, prm, ezz=None):
    """The return map alone: update with grad_v = 0, so F_trial = F: (F's, eps_zz's)."""
    dim = len(Fs[0])
    out = EVAL[backend](law, dim, "update", states(Fs, ezz), prm, np.zeros((len(Fs), dim, dim)), 1e-3)
    return np.array([o["F"] for o in out]), np.array([float(o["eps_zz"]) for o in out])


def project(law, backend, Fs, prm, ezz=None):
    return project_full(law, backend, Fs, prm, ezz)[0]


def tau3(law, F, ezz, prm):
    """The 3x3 Kirchhoff stress of a state: 2D plane strain: the 3D stress of diag(F, e^eps_zz)."""
    if len(F) == 3:
        return DP.reference.kirchhoff({"F": F}, prm)
    F3 = np.eye(3)
    F3[:2, :2] = F
    F3[2, 2] = np.exp(ezz)
    t = DP.reference.kirchhoff({"F": F3}, prm)
    assert np.allclose(t[:2, :2], DP.reference.kirchhoff({"F": F, "eps_zz": ezz}, prm), rtol=0, atol=1e-9 * MU)
    return t


def vol(F, ezz):
    """The elastic volume ratio det F (2D: det F e^eps_zz)."""
    return np.linalg.det(F) * (np.exp(ezz) if len(F) == 2 else 1.0)


def ezz_of(dim, rng, scale):
    """Random elastic out-of-plane strains for 2D states (0 in 3D)."""
    return scale * rng.standard_normal() if dim == 2 else 0.0


def principal(eps, U, V):
    return U @ np.diag(np.exp(eps)) @ V.T


def dev(t):
    return t - np.trace(t) / len(t) * np.eye(len(t))


# ---- elasticity (Eqs. 14 / 17) ------------------------------------------------------------------------
@pytest.mark.parametrize("dim", DIMS)
@pytest.mark.parametrize("backend", BACKENDS)
def test_uniaxial_strain_closed_form(backend, dim):
    s = np.array([0.5, 0.8, 1.0, 1.5, 3.0])
    Fs = [np.diag([si] + [1.0] * (dim - 1)) for si in s]
    for law, prm in ((DP, PRM_DP), (VM, PRM_VM)):
        P = np.array([t @ np.linalg.inv(F).T for t, F in zip(tau(law, backend, Fs, prm), Fs)])
        want = np.zeros_like(P)
        want[:, 0, 0] = (2.0 * MU + LAM) * np.log(s) / s
        for k in range(1, dim):
            want[:, k, k] = LAM * np.log(s)
        assert np.max(np.abs(P - want)) <= 1e-10 * np.max(np.abs(want))


@pytest.mark.parametrize("dim", DIMS)
@pytest.mark.parametrize("backend", BACKENDS)
def test_simple_shear_closed_form(backend, dim):
    gammas = np.array([0.1, 0.5, 1.0, 2.0, 4.0])
    Fs = []
    for g in gammas:
        F = np.eye(dim)
        F[0, 1] = g
        Fs.append(F)
    got = tau(DP, backend, Fs, PRM_DP)
    want = np.zeros_like(got)
    t12 = 2.0 * MU * np.arcsinh(gammas / 2.0) / np.sqrt(1.0 + gammas**2 / 4.0)
    want[:, 0, 1] = want[:, 1, 0] = t12
    want[:, 0, 0] = gammas / 2.0 * t12
    want[:, 1, 1] = -gammas / 2.0 * t12
    assert np.max(np.abs(got - want)) <= 1e-10 * np.max(np.abs(want))


@pytest.mark.parametrize("dim", DIMS)
@pytest.mark.parametrize("backend", BACKENDS)
def test_rest_and_rigid_rotation_are_stress_free_and_stay(backend, dim):
    rng = np.random.default_rng(0)
    Fs = [np.eye(dim)] + [rotation(dim, rng) for _ in range(3)]
    for law, prm in ((DP, PRM_DP), (VM, PRM_VM)):
        assert np.max(np.abs(tau(law, backend, Fs[:1], prm))) <= 1e-12 * MU
        assert np.max(np.abs(tau(law, backend, Fs, prm))) <= 1e-12 * MU
        # eps = 0 is inside both yield surfaces (delta_gamma = 0 for DP): the return map leaves F alone
        assert np.max(np.abs(project(law, backend, Fs, prm) - np.array(Fs))) <= 1e-14


@pytest.mark.parametrize("dim", DIMS)
@pytest.mark.parametrize("backend", BACKENDS)
def test_rotation_equivariance(backend, dim):
    """tau(R F) = R tau(F) R^T and tau(F Q) = tau(F) (i.e. P(RF) = R P(F), P(FQ) = P(F) Q); the return
    maps commute the same way: proj(R F Q) = R proj(F) Q."""
    rng = np.random.default_rng(1)
    Fs = [np.eye(dim) + 0.3 * rng.standard_normal((dim, dim)) for _ in range(6)]
    Fs = [F if np.linalg.det(F) > 0 else -F if dim == 3 else F[::-1] for F in Fs]
    Rs = [rotation(dim, rng) for _ in Fs]
    Qs = [rotation(dim, rng) for _ in Fs]
    RFQ = [R @ F @ Q for R, F, Q in zip(Rs, Fs, Qs)]
    for law, prm in ((DP, PRM_DP), (VM, PRM_VM)):
        t, t_r = tau(law, backend, Fs, prm), tau(law, backend, RFQ, prm)
        want = np.array([R @ a @ R.T for R, a in zip(Rs, t)])
        assert np.max(np.abs(t_r - want)) <= 1e-10 * np.max(np.abs(t))
        assert np.max(np.abs(t - np.transpose(t, (0, 2, 1)))) <= 1e-10 * np.max(np.abs(t))   # P F^T symmetric
        p, p_r = project(law, backend, Fs, prm), project(law, backend, RFQ, prm)
        want = np.array([R @ a @ Q for R, a, Q in zip(Rs, p, Qs)])
        assert np.max(np.abs(p_r - want)) <= 1e-10


@pytest.mark.parametrize("dim", DIMS)
def test_first_piola_is_the_energy_derivative(dim):
    """psi = mu |eps|^2 + lambda/2 tr(eps)^2: dpsi/dF = P = tau F^-T, so Eq. 14's "P" is the Kirchhoff stress."""
    rng = np.random.default_rng(2)
    ref = DP.reference
    for _ in range(4):
        F = rotation(dim, rng) @ np.diag(rng.uniform(0.6, 1.6, dim)) @ rotation(dim, rng)
        h = 1e-6
        fd = np.zeros((dim, dim))
        for i in range(dim):
            for j in range(dim):
                dF = np.zeros((dim, dim))
                dF[i, j] = h
                fd[i, j] = (ref.energy(F + dF, PRM_DP) - ref.energy(F - dF, PRM_DP)) / (2.0 * h)
        P = ref.first_piola(F, PRM_DP)
        assert np.max(np.abs(fd - P)) <= 1e-6 * np.max(np.abs(P))
        assert np.allclose(P @ F.T, ref.kirchhoff({"F": F}, PRM_DP), rtol=0, atol=1e-10 * np.max(np.abs(P)))
    Fs = np.array([np.eye(dim) + 0.2 * rng.standard_normal((dim, dim)) for _ in range(3)])
    assert np.allclose(ref.energy(Fs, PRM_DP), [ref.energy(F, PRM_DP) for F in Fs], rtol=1e-14)


# ---- Drucker-Prager return (Eqs. 15-16) ----------------------------------------------------------------
def test_dp_alpha_value():
    assert abs(DP.reference.alpha(30.0) - 0.3266) < 1e-4     # note row 6b
    assert abs(DP.reference.alpha(PHI) - ALPHA) <= 1e-15


def shear_case_gradients(dim, rng, n=6):
    """F = U exp(eps) V^T (2D: with eps_zz) with tr(eps) < 0 and delta_gamma > 0 (outside the cone,
    compressive); the principal strains are three in 2D (plane strain) and 3D."""
    Fs, zs = [], []
    while len(Fs) < n:
        eps = rng.normal(0.0, 0.15, 3)
        eps -= eps.mean() + rng.uniform(0.005, 0.05)           # tr(eps) < 0
        hat = eps - eps.mean()
        dg = np.linalg.norm(hat) + (3 * LAM + 2.0 * MU) / (2.0 * MU) * eps.sum() * ALPHA
        if dg > 1e-3:
            Fs.append(principal(eps[:dim], rotation(dim, rng), rotation(dim, rng)))
            zs.append(eps[2] if dim == 2 else 0.0)
    return Fs, zs


@pytest.mark.parametrize("dim", DIMS)
@pytest.mark.parametrize("backend", BACKENDS)
def test_dp_shear_return_lands_on_cone(backend, dim):
    rng = np.random.default_rng(3)
    Fs, zs = shear_case_gradients(dim, rng)
    Fn, zn = project_full(DP, backend, Fs, PRM_DP, zs)
    for F, z, G, w in zip(Fs, zs, Fn, zn):
        t = tau3(DP, G, w, PRM_DP)
        tr = np.trace(t)
        assert tr < 0.0
        f = np.linalg.norm(dev(t)) + ALPHA * tr
        assert abs(f) <= 1e-9 * abs(tr)
        assert abs(vol(G, w) / vol(F, z) - 1.0) <= 1e-12   # volume kept (tr eps unchanged)
        assert np.max(np.abs(polar_rotation(G) - polar_rotation(F))) <= 1e-10   # same rotation, same axes


@pytest.mark.parametrize("dim", DIMS)
@pytest.mark.parametrize("backend", BACKENDS)
def test_dp_tension_returns_to_cone_tip(backend, dim):
    rng = np.random.default_rng(4)
    Fs, zs = [], []
    for _ in range(5):
        eps = rng.normal(0.0, 0.2, 3)
        eps += 0.02 - eps.mean()                                  # tr(eps) > 0 (over three in 2D)
        Fs.append(principal(eps[:dim], rotation(dim, rng), rotation(dim, rng)))
        zs.append(eps[2] if dim == 2 else 0.0)
    Fn, zn = project_full(DP, backend, Fs, PRM_DP, zs)
    assert np.all(zn == 0.0)                                      # the tip: eps_zz = 0 too
    for F, G in zip(Fs, Fn):
        assert np.max(np.abs(G - polar_rotation(F))) <= 1e-12             # F <- U V^T
        assert np.max(np.abs(G.T @ G - np.eye(dim))) <= 1e-13
    # tau = 0 at the tip, up to the round-off of an SVD of a rotation (log(1 + O(1e-16)))
    assert np.max(np.abs(tau(DP, backend, list(Fn), PRM_DP))) <= 1e-12 * MU


@pytest.mark.parametrize("dim", DIMS)
@pytest.mark.parametrize("backend", BACKENDS)
def test_dp_inside_cone_is_elastic(backend, dim):
    rng = np.random.default_rng(5)
    Fs, zs = [], []
    for _ in range(5):
        eps = -rng.uniform(0.02, 0.2) * np.ones(3) + rng.normal(0.0, 0.003, 3)   # compression, little shear
        Fs.append(principal(eps[:dim], rotation(dim, rng), rotation(dim, rng)))
        zs.append(eps[2] if dim == 2 else 0.0)
    Fn, zn = project_full(DP, backend, Fs, PRM_DP, zs)
    assert np.array_equal(Fn, np.array(Fs)) and np.array_equal(zn, np.array(zs))


# ---- von Mises return (Eqs. 18-19) -----------------------------------------------------------------------
@pytest.mark.parametrize("dim", DIMS)
@pytest.mark.parametrize("backend", BACKENDS)
def test_von_mises_return_is_isochoric_onto_yield_surface(backend, dim):
    rng = np.random.default_rng(6)
    Fs, zs = [], []
    for _ in range(6):
        eps = rng.normal(0.0, 0.2, 3)                            # |2 mu eps_hat| >> tau_Y = 300 Pa
        Fs.append(principal(eps[:dim], rotation(dim, rng), rotation(dim, rng)))
        zs.append(eps[2] if dim == 2 else 0.0)
    Fn, zn = project_full(VM, backend, Fs, PRM_VM, zs)
    for F, z, G, w in zip(Fs, zs, Fn, zn):
        t, a = tau3(VM, G, w, PRM_VM), tau3(VM, F, z, PRM_VM)
        assert abs(vol(G, w) / vol(F, z) - 1.0) <= 1e-12
        assert abs(np.linalg.norm(dev(t)) - TAU_Y) <= 1e-10 * TAU_Y       # Frobenius |dev tau| = tau_Y
        assert abs(np.trace(t) - np.trace(a)) <= 1e-10 * np.max(np.abs(a))  # pressure untouched
    # below yield: unchanged
    small = [principal(1e-3 * rng.normal(0.0, 1.0, dim), rotation(dim, rng), rotation(dim, rng)) for _ in range(4)]
    assert all(np.linalg.norm(dev(t)) < TAU_Y for t in tau(VM, "reference", small, PRM_VM))
    assert np.array_equal(project(VM, backend, small, PRM_VM), np.array(small))


# ---- JAX derivatives at the rest state (the SVD's own JVP is NaN there) ------------------------------------
@pytest.mark.parametrize("dim", DIMS)
def test_jax_derivatives_at_rest(dim):
    import jax
    import jax.numpy as jnp

    from mpmlab.backends.jax import stepper  # noqa: F401  (enables x64)

    for law, prm in ((DP, PRM_DP), (VM, PRM_VM)):
        L = jax_law(law, dim)
        P = jnp.asarray(prm)
        # d tau / d F at F = I is the small-strain elasticity tensor: d tau = 2 mu sym(dF) + lambda tr(dF) I
        z0 = jnp.zeros(())
        J = np.asarray(jax.jit(jax.jacrev(lambda F: L.kirchhoff({"F": F, "eps_zz": z0}, P)))(jnp.eye(dim)))
        eye = np.eye(dim)
        want = (MU * (np.einsum("ik,jl->ijkl", eye, eye) + np.einsum("il,jk->ijkl", eye, eye))
                + LAM * np.einsum("ij,kl->ijkl", eye, eye))
        assert np.max(np.abs(J - want)) <= 1e-10 * MU
        # the return map at rest is the identity in F (elastic), and its parameter derivative is zero
        upd = lambda F, p: L.update({"F": F, "eps_zz": z0}, jnp.zeros((dim, dim)), 1e-3, p)["F"]
        JF, Jp = jax.jit(jax.jacrev(upd, argnums=(0, 1)))(jnp.eye(dim), P)
        assert np.max(np.abs(np.asarray(JF) - np.einsum("ik,jl->ijkl", eye, eye))) <= 1e-12
        assert np.all(np.asarray(Jp) == 0.0)


@pytest.mark.parametrize("dim", DIMS)
def test_jax_plastic_derivatives_match_finite_differences(dim):
    """Repeated singular values (a plastic stretch along one axis) on the plastic branches."""
    import jax
    import jax.numpy as jnp

    from mpmlab.backends.jax import stepper  # noqa: F401

    rng = np.random.default_rng(7)
    R = rotation(dim, rng)
    cases = ((DP, PRM_DP, np.diag([1.2] + [0.85] * (dim - 1))),    # compressive shear case
             (DP, PRM_DP, np.diag([1.3] + [1.0] * (dim - 1))),     # tension: tip
             (VM, PRM_VM, np.diag([1.2] + [0.9] * (dim - 1))))
    for law, prm, S in cases:
        L = jax_law(law, dim)
        F0 = R @ S @ R.T
        upd = jax.jit(lambda F: L.update({"F": F, "eps_zz": jnp.zeros(())}, jnp.zeros((dim, dim)), 1e-3,
                                         jnp.asarray(prm))["F"])
        JF = np.asarray(jax.jit(jax.jacrev(upd))(jnp.asarray(F0)))
        h = 1e-6
        fd = np.zeros_like(JF)
        for i in range(dim):
            for j in range(dim):
                dF = np.zeros((dim, dim))
                dF[i, j] = h
                fd[..., i, j] = (np.asarray(upd(jnp.asarray(F0 + dF))) - np.asarray(upd(jnp.asarray(F0 - dF)))) / (2 * h)
        assert np.all(np.isfinite(JF))
        assert np.max(np.abs(JF - fd)) <= 1e-7 * np.max(np.abs(fd))


# ---- Warp fp32 builds ------------------------------------------------------------------------------------
@pytest.mark.parametrize("dim", DIMS)
def test_warp_fp32_builds_and_agrees(dim):
    rng = np.random.default_rng(8)
    Fs = [principal(rng.normal(0.0, 0.2, dim), rotation(dim, rng), rotation(dim, rng)) for _ in range(8)]
    Ls = 0.5 * rng.standard_normal((len(Fs), dim, dim))
    sts = states(Fs, [ezz_of(dim, rng, 0.1) for _ in Fs])
    for law, prm in ((DP, PRM_DP), (VM, PRM_VM)):
        t32 = EVAL["warp"](law, dim, "kirchhoff", sts, prm, precision="fp32")
        t64 = EVAL["reference"](law, dim, "kirchhoff", sts, prm)
        assert np.max(np.abs(t32 - t64)) <= 1e-4 * np.max(np.abs(t64))
        u32 = EVAL["warp"](law, dim, "update", sts, prm, Ls, 1e-2, precision="fp32")
        u64 = EVAL["reference"](law, dim, "update", sts, prm, Ls, 1e-2)
        assert max(np.max(np.abs(a["F"] - b["F"])) for a, b in zip(u32, u64)) <= 1e-4
        assert max(abs(float(a["eps_zz"]) - float(b["eps_zz"])) for a, b in zip(u32, u64)) <= 1e-4
