"""Shape functions on the JAX backend (issue 19 item 1): every transfer with the cubic B-spline, uGIMP and CPDI.

* Conservation (``mpmlab.testing.check_conservation``: a spinning, drifting block, no gravity, fp64):
  every built-in transfer and the example plugin's RPIC, 2D (30 steps) and 3D (15 steps), conserve
  linear momentum to 1e-11 with either shape; APIC, MLS and RPIC conserve angular momentum (counting the
  affine spin m eps : (C D_p)^T with the shape's own D_p) to 1e-11 with cubic B-splines, and to 1e-12
  with uGIMP. uGIMP's D_p varies with the particle's position in its cell, so G2P forms C = B D_p^-1 with
  D_p of the position the particle moves to, x + dt v_pic, where the next P2G applies C
  (``JaxStepper._Dinv_moved``; Jiang et al. 2015 store B and form C at P2G to the same effect), and RPIC
  takes the rotation whose angular momentum K omega (K = tr(D) I - D) is B's. Measured 2026-12-06,
  2D 30 steps: APIC 1.5e-16, MLS 5.8e-16, RPIC 7.3e-16; 3D 15 steps: 1.1e-15, 1.2e-15, 1.2e-15 (with D_p
  of the gather position: 7.9e-6, 9.2e-6, 1.1e-5 and 4.2e-7, 6.9e-7, 1.6e-6; PIC, which keeps no C,
  loses 8.5e-2 / 3.9e-2).
* CPDI (P2G / G2P over the corners of each particle's domain, ``JaxStepper._corners``) conserves linear
  momentum, and angular momentum with APIC / MLS counting D_p = ``cpdi.reference.inertia`` of the domain:
  measured 2D 30 steps 1.5e-16 (APIC), 2.9e-16 (MLS); 3D 15 steps 1.1e-15, 8.6e-16. Its domains turn
  without stretching under a rigid rotation and follow the material's F (R = F R0 to O(dt^2)); the guard
  stops a corner leaving the grid.
* The uGIMP D_p^-1 the stepper gives the schemes is the inverse of ``testing.inertia`` (NumPy).
* ``adjoints="custom"`` (hand-written transposes, width 4 for cubic) and ``"derived"``: one step's VJP
  w.r.t. the whole state and every parameter agrees to 1e-12 (as tests/test_jax_adjoints.py).
* Gradients through a cubic and a uGIMP rollout w.r.t. the initial velocity and the law parameters
  agree with central differences (``mpmlab.testing.check_gradients``, 1e-6).
* Quadratic stays the default: a stepper built without ``shape`` and one with ``shape="quadratic"``
  step bit-identically; the run metadata records the shape.
* The stability guard of a cubic stepper stops a particle leaving the region its 4-node window keeps on
  the grid (one cell from the edge), before a JAX gather would clip the window.
"""
from __future__ import annotations

import sys
from pathlib import Path

import jax
import numpy as np
import pytest

import mpmlab
from mpmlab import testing
from mpmlab.backends.jax import differentiable as JD
from mpmlab.core import registry
from mpmlab.testing import check_conservation
from mpmlab.transfers import BUILTIN

SHAPES = ("cubic", "ugimp", "cpdi")
PLUGIN = Path(__file__).resolve().parents[1] / "examples" / "mpmlab-example-plugin"


def _rpic():
    if "rpic" not in registry.transfers.names():
        sys.path.insert(0, str(PLUGIN))
        registry.transfers.register("rpic", "mpmlab_example_plugin.rpic:RPIC", provenance="tests")
    return "rpic"


#: measured drifts are <= 1.2e-15 (module docstring): round-off in fp64
UGIMP_ANGULAR_TOL = 1e-12


#: 3D by default for the schemes that conserve angular momentum (their D_p path); the others in 3D are full
CONSERVATION_CASES = [pytest.param(name, shape, dim, marks=(pytest.mark.full,) if dim == 3 and name not in ("apic", "mls")
                                   else ()) for dim in (2, 3) for shape in SHAPES for name in sorted(BUILTIN) + ["rpic"]]


@pytest.mark.parametrize("name,shape,dim", CONSERVATION_CASES)
def test_every_transfer_conserves_with_every_shape(name, shape, dim):
    if name == "rpic":
        _rpic()
    declared = set(registry.transfers.get(name).conserves)
    r = check_conservation(name, dim, "jax", shape=shape, steps=30 if dim == 2 else 15, quantities=declared)
    assert r["drift"]["linear_momentum"] <= 1e-11
    if "angular_momentum" in declared:
        tol = 1e-11 if shape == "cubic" else UGIMP_ANGULAR_TOL      # uGIMP, CPDI: D_p of x + dt v_pic
        assert r["drift"]["angular_momentum"] <= tol, r["drift"]


def test_ugimp_inertia_is_the_reference_one():
    import jax.numpy as jnp

    scene = testing.conservation_scene(2)
    st = mpmlab.build_stepper(scene, "jax", "apic", "fp64", shape="ugimp")
    x = np.asarray(st.init()["x"]) + 0.013 * np.random.default_rng(0).standard_normal((st.particles.count, 2))
    Xp = (x - scene.origin) / scene.dx
    fx = Xp - np.floor(Xp - st.shape.offset)
    w1, _ = st._shape_fns.weights(jnp.asarray(fx), jnp.asarray(st._lp))
    Dinv = np.asarray(st._Dinv(w1, jnp.asarray(fx), 1.0 / scene.dx))
    D = testing.transfers.inertia("ugimp", x, scene.origin, scene.dx, st._lp)
    assert np.abs(np.einsum("nij,njk->nik", Dinv, D) - np.eye(2)).max() <= 1e-12
    # lp: half the particles' initial width (2 x 2 particles per cell: a quarter cell)
    assert np.allclose(st._lp, 0.25) and st.meta()["shape"] == "ugimp"


# ---- custom vs derived adjoints -------------------------------------------------------------------------------
def step_vjps(scene, transfer, shape, warm=4):
    """(custom VJP, derived VJP, next states) of one step after ``warm`` steps (tests/test_jax_adjoints.py)."""
    from tests.test_jax_adjoints import FAST_COMPILE, _random_like

    custom, derived = [mpmlab.build_stepper(scene, "jax", transfer, "fp64", adjoints=a, shape=shape)
                       for a in ("custom", "derived")]
    s, p = JD.split_controls(derived, derived.controls())
    fns = [jax.jit(lambda s_, p_, ct, st=st: (lambda y, pull: (y, pull(ct)))(*jax.vjp(st.step_fn, s_, p_)),
                   compiler_options=FAST_COMPILE) for st in (custom, derived)]
    ct = _random_like(jax.eval_shape(derived.step_fn, s, p), 1)
    for _ in range(warm):
        s = fns[1](s, p, ct)[0]
    (yc, gc), (yd, gd) = (f(s, p, ct) for f in fns)
    return gc, gd, yc, yd


ADJOINT_CASES = [("apic", "cubic", 2), ("flip", "cubic", 2), ("mls", "ugimp", 2), ("pic", "ugimp", 3),
                 ("apic", "cpdi", 2), ("flip", "cpdi", 2), ("mls", "cpdi", 3)]


@pytest.mark.parametrize("transfer,shape,dim", ADJOINT_CASES)
def test_custom_and_derived_adjoints_agree(transfer, shape, dim):
    from tests.test_jax_adjoints import assert_close

    gc, gd, yc, yd = step_vjps(testing.law_scene(["fixed_corotated", "weakly_compressible"], dim), transfer, shape)
    assert_close(yc, yd, f"forward step ({shape})", tol=1e-14)
    assert_close(gc, gd, f"{transfer} x {shape} x {dim}D (whole state and every parameter)")


# ---- gradients against central differences ----------------------------------------------------------------
@pytest.mark.parametrize("transfer,shape", [("apic", "cubic"), ("mls", "ugimp"), ("apic", "cpdi"), ("flip", "cpdi")])
def test_gradients_match_central_differences(transfer, shape):
    r = testing.check_gradients("fixed_corotated", "jax", transfer, 2, keys=("v", "law"), shape=shape)
    assert set(r) == {"v", "law"} and all(e["error"] <= 1e-6 for e in r.values())


# ---- the default -------------------------------------------------------------------------------------------------
def test_quadratic_is_the_default_and_unchanged():
    scene = testing.law_scene(["fixed_corotated"], 2)
    a = mpmlab.build_stepper(scene, "jax", "mls", "fp64")
    b = mpmlab.build_stepper(scene, "jax", "mls", "fp64", shape="quadratic")
    assert a.shape.name == b.shape.name == "quadratic" and a.meta()["shape"] == "quadratic"
    sa, sb = a._advance(a.init(), 5), b._advance(b.init(), 5)
    for k in ("x", "v", "C"):
        assert np.array_equal(np.asarray(sa[k]), np.asarray(sb[k]))


def thrown_block():
    """A block thrown at 5 m/s towards the lower x edge of a wall-less domain (the guard tests, both backends)."""
    body = mpmlab.Body(shape={"kind": "box", "lo": [0.1, 0.4], "hi": [0.2, 0.5]}, material="fixed_corotated",
                       params={"E": 1e4, "nu": 0.3}, density=1000.0, velocity=[-5.0, 0.0], particles_per_cell=4)
    return mpmlab.Scene(dim=2, dx=0.05, domain=([0.0, 0.0], [1.0, 1.0]), bodies=[body], dt=1e-3)


def test_cubic_guard_stops_a_particle_leaving_its_window_region():
    """The stability guard uses the cubic window's region (a cell from the edge), not the scene's half cell:
    a block thrown at the lower x edge (no walls) is stopped when its first particle passes x = dx."""
    from mpmlab.core.errors import SimulationDiverged

    scene = thrown_block()
    st = mpmlab.build_stepper(scene, "jax", "apic", "fp64", shape="cubic", check_every=1)
    with pytest.raises(SimulationDiverged) as info:
        st.rollout(steps=40, every=10)
    e = info.value
    assert e.field == "x (outside the domain)" and 0.025 < e.value[0] < 0.05, (e.field, e.value)


# ---- CPDI: the particle domains ------------------------------------------------------------------------------------
def _spinning_disc(omega=2.0, dt=1e-3):
    """A disc spinning rigidly (APIC's C = the spin from the start, a soft law), no gravity, no walls."""
    W = [[0.0, -omega], [omega, 0.0]]
    body = mpmlab.Body(shape={"kind": "sphere", "center": [0.5, 0.5], "radius": 0.15}, material="fixed_corotated",
                       params={"E": 1.0, "nu": 0.3}, density=1000.0, angular_velocity=omega, C=W,
                       particles_per_cell=4)
    return mpmlab.Scene(dim=2, dx=0.05, domain=([0.0, 0.0], [1.0, 1.0]), bodies=[body], gravity=[0.0, 0.0], dt=dt)


def test_cpdi_rigid_rotation_keeps_the_domains_rotated():
    """A rigid rotation turns every domain without stretching it. The body is held to the exact rigid motion
    (x turned by omega t about the centre, v = W (x - c), C = W, a stress-free law state, reset before each
    step; only the domains are carried): P2G then puts the exact rigid field on the grid, the corners'
    gradient sum_i v_i grad S_ip^T is W by linear completeness, and the Cayley update turns R by
    2 atan(dt omega / 2) a step, R^T R unchanged to round-off (measured 2.1e-14 relative, angle 2.8e-15 rad
    after 200 steps). The explicit (I + dt W) R would have grown R^T R by (1 + dt^2 omega^2)^n - 1 = 8e-4. (Left
    free, a soft disc does not stay rigid under symplectic Euler: v_p lags the turned x_p by dt omega^2 r,
    so the grid field gains an expansion rate dt omega^2 a step and the body, and its domains, swell.)"""
    import jax.numpy as jnp

    omega, dt, n = 2.0, 1e-3, 200
    st = mpmlab.build_stepper(_spinning_disc(omega, dt), "jax", "apic", "fp64", shape="cpdi")
    s0, p = st.init(), st.params
    W = jnp.array([[0.0, -omega], [omega, 0.0]])
    step = jax.jit(lambda s: st.step_fn(s, p))
    c = jnp.array([0.5, 0.5])
    s = dict(s0)
    for k in range(n):
        a = omega * dt * k
        x = c + (s0["x"] - c) @ jnp.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]).T
        s = step(dict(s, x=x, v=(x - c) @ W.T, C=jnp.broadcast_to(W, s0["C"].shape), law=s0["law"]))
    assert_turned_rigidly(np.asarray(s0["domain"]), np.asarray(s["domain"]), omega, dt, n)


def assert_turned_rigidly(R0, R, omega, dt, n):
    """R^T R unchanged to round-off and every domain turned by the Cayley angle 2 n atan(dt omega / 2), which is
    omega n dt to 1e-6 rad (the rigid-rotation tests, both backends)."""
    gram = lambda A: np.einsum("nji,njk->nik", A, A)               # noqa: E731
    assert np.abs(gram(R) - gram(R0)).max() <= 1e-12 * np.abs(gram(R0)).max()
    Q = np.einsum("nij,njk->nik", R, np.linalg.inv(R0))            # the rotation each domain went through
    angle = np.arctan2(Q[:, 1, 0], Q[:, 0, 0])
    assert np.abs(angle - n * 2 * np.arctan(dt * omega / 2)).max() <= 1e-12
    assert np.abs(angle - omega * n * dt).max() <= 1e-6


@pytest.mark.parametrize("transfer", ["apic", "pic"])
def test_cpdi_domains_follow_the_material(transfer):
    """In a free run the domain is CPDI1's r = F r0: R and the law's F R0 integrate the same velocity
    gradient (APIC, PIC: sum_i v_i grad S_ip^T), Cayley against explicit Euler, so they agree to O(dt^2 |L|^2)
    a step: measured 2.5e-3 (APIC) and 1.2e-3 (PIC) of |R0| after 100 steps of the law scene, where F moved
    0.43 and 0.28 from I."""
    st = mpmlab.build_stepper(testing.law_scene(["fixed_corotated"], 2), "jax", transfer, "fp64", shape="cpdi")
    traj = st.rollout(steps=100, every=100, fields=("domain", "F"))
    R0, R, F = traj.fields["domain"][0], traj.fields["domain"][-1], traj.fields["F"][-1]
    assert np.abs(F - np.eye(2)).max() > 0.2                          # the body did deform
    assert np.abs(R - np.einsum("nij,njk->nik", F, R0)).max() <= 5e-3 * np.abs(R0).max()


@pytest.mark.parametrize("backend", ["jax", "warp"])
def test_cpdi_guard_names_a_corner_leaving_the_grid(backend):
    """The guard watches the domain's corners, not only the particle (JAX: ``_bad_impl``; Warp:
    ``corner_guard_kernel``): a block thrown at the lower x edge is stopped when a corner (half a particle
    spacing ahead of its particle) leaves the grid."""
    from mpmlab.core.errors import SimulationDiverged

    scene = thrown_block()
    st = mpmlab.build_stepper(scene, backend, "apic", "fp64", shape="cpdi", check_every=1)
    with pytest.raises(SimulationDiverged) as info:
        st.rollout(steps=40, every=10)
    e = info.value
    assert e.field == "domain (a CPDI corner outside the domain)" and -0.0051 < e.value[0] < 0.0, (e.field, e.value)
