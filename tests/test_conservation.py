"""Conservation and transfer exactness (verification note #5, 5b), on both backends in fp64."""
import numpy as np
import pytest

import mpmlab
from mpmlab.core import registry

BACKENDS = ("jax", "warp")
TRANSFERS = registry.transfers.names()


def free_body(dim, gravity=False, E=1e4, omega=3.0, velocity=0.4, walls=False, dt=5e-4):
    c = 0.5
    body = mpmlab.Body(shape={"kind": "box", "lo": [c - 0.1] * dim, "hi": [c + 0.1] * dim}, material="fixed_corotated",
                       params={"E": E, "nu": 0.3}, density=1000.0, particles_per_cell=2**dim,
                       velocity=[velocity] + [0.1] * (dim - 1), angular_velocity=omega if dim == 2 else [0.0, 0.0, omega])
    g = [0.0, -9.8] + [0.0] * (dim - 2) if gravity else None
    return mpmlab.Scene(dim=dim, dx=0.05, domain=([0.0] * dim, [1.0] * dim), bodies=[body], gravity=g,
                        boundaries=[mpmlab.boundaries.Walls()] if walls else [], dt=dt, name="free_body")


def momentum(traj):
    return np.einsum("n,tnd->td", traj.mass, traj.v)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("transfer", TRANSFERS)
@pytest.mark.parametrize("dim", (2, 3))
def test_linear_momentum_free_body(backend, transfer, dim):
    steps = 1000 if dim == 2 else 300
    traj = mpmlab.simulate(free_body(dim), steps, steps // 4, backend, transfer, "fp64")
    P = momentum(traj)
    assert np.max(np.abs(P - P[0])) <= 1e-10 * np.max(np.abs(P[0]))
    assert np.all(traj.mass == traj.mass[0])  # mass is carried by particles: exact


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("transfer", ("pic", "mls"))
def test_momentum_under_gravity(backend, transfer):
    traj = mpmlab.simulate(free_body(2, gravity=True), 400, 100, backend, transfer, "fp64")
    P = momentum(traj)
    M = traj.mass.sum()
    expected = P[0] + M * np.array([0.0, -9.8]) * traj.time[:, None]   # P(t) = P0 + M g t
    assert np.max(np.abs(P - expected)) <= 1e-10 * np.max(np.abs(expected))


def angular_momentum_2d(traj, dx):
    x, v, C = traj.x, traj.v, traj.fields["C"]
    orbital = np.einsum("n,tn->t", traj.mass, x[..., 0] * v[..., 1] - x[..., 1] * v[..., 0])
    # APIC spin: m (B^T : eps) with B = C D, D = dx^2/4 I (Jiang et al. 2015)
    spin = np.einsum("n,tn->t", traj.mass, (dx * dx / 4.0) * (C[..., 1, 0] - C[..., 0, 1]))
    return orbital + spin


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("transfer", ("apic", "mls"))
def test_apic_angular_momentum(backend, transfer):
    scene = free_body(2, omega=4.0)
    traj = mpmlab.simulate(scene, 400, 100, backend, transfer, "fp64", fields=("C",))
    L = angular_momentum_2d(traj, scene.dx)
    assert abs(L[0]) > 1e-3
    assert np.max(np.abs(L - L[0])) <= 1e-10 * abs(L[0])


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("transfer", ("apic", "mls"))
@pytest.mark.parametrize("dim", (2, 3))
def test_affine_field_survives_round_trip(backend, transfer, dim):
    """v = A x + b with C = A goes P2G -> G2P unchanged (stress-free first step, no gravity)."""
    scene = free_body(dim, omega=0.0, velocity=0.0)
    st = mpmlab.build_stepper(scene, backend, transfer, "fp64")
    rng = np.random.default_rng(0)
    A = rng.standard_normal((dim, dim)); b = rng.standard_normal(dim)
    s0 = st.init()
    x0 = scene.particles().x
    v0 = x0 @ A.T + b
    if backend == "jax":
        import jax.numpy as jnp
        s0 = dict(s0, v=jnp.asarray(v0), C=jnp.broadcast_to(jnp.asarray(A), (len(x0), dim, dim)))
    else:
        import warp as wp
        s0.v.assign(wp.array(v0, dtype=s0.v.dtype)); s0.C.assign(wp.array(np.broadcast_to(A, (len(x0), dim, dim)).copy(), dtype=s0.C.dtype))
    s1 = st.to_numpy(st.step(s0))
    assert np.max(np.abs(s1["v"] - v0)) <= 1e-12 * np.max(np.abs(v0))
    assert np.max(np.abs(s1["C"] - A)) <= 1e-11 * np.max(np.abs(A))


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("transfer", ("pic", "apic"))
def test_pic_apic_never_create_kinetic_energy(backend, transfer):
    """With negligible stiffness the transfers alone act: kinetic energy must never rise (note 5b)."""
    scene = free_body(2, E=1e-9, omega=5.0)
    fields = ("C",) if transfer == "apic" else ()
    traj = mpmlab.simulate(scene, 200, 1, backend, transfer, "fp64", fields=fields)
    ke = 0.5 * np.einsum("n,tnd->t", traj.mass, traj.v**2)
    if transfer == "apic":
        # APIC's kinetic energy includes the affine modes: 1/2 m tr(C D C^T), D = dx^2/4 I (Jiang et al. 2015)
        ke = ke + 0.5 * (scene.dx**2 / 4.0) * np.einsum("n,tnij->t", traj.mass, traj.fields["C"] ** 2)
    assert np.all(np.diff(ke) <= 1e-12 * ke[0])
    assert ke[-1] < ke[0]  # PIC/APIC dissipate a spinning field
