"""Gradients through Warp rollouts (issue #4): ``stepper.controls()`` / ``stepper.observe()``.

Central finite differences (fp64) against the autograd directional derivative along a random
direction, for every law x transfer, w.r.t. the initial positions, the initial velocities and the law
parameters (relative error <= 1e-6 at the best of a few step sizes h, the V-minimum of truncation vs
round-off). Scenes are tiny (36 particles, 15 steps) and start from a sheared, compressing velocity
field so the plastic laws yield (their yield parameters get non-zero gradients) while no particle
meets a wall. Friction (per segment, per node, plane), gravity, mass and volume are checked on a
block sliding on a floor; segmenting is checked bit-for-bit; observations against the NumPy oracle;
non-finite adjoints must raise ``GradientError`` naming the step and particle.
"""
from functools import lru_cache

import numpy as np
import pytest
import torch
import warp as wp

import mpmlab
from mpmlab.boundaries import FrictionWalls, Plane, Walls
from mpmlab.core import registry
from mpmlab.core.errors import GradientError, SimulationDiverged
from mpmlab.observations import Eulerian, Lagrangian, apply_numpy
from mpmlab.testing import options_of, params_of
from mpmlab.testing.gradients import HS, leaf, warp_fd_errors, with_leaf

LAWS = registry.laws.names()
TRANSFERS = registry.transfers.names()
STEPS = (7, 15)
#: initial velocity gradient added to the bodies' rigid motion: shear + compression, so the Hencky
#: and Drucker-Prager laws leave their elastic range within a few steps
SHEAR = {2: np.array([[0.5, 1.0], [0.3, -1.5]]),
         3: np.array([[0.5, 1.0, 0.2], [0.3, -1.5, 0.4], [-0.6, 0.1, 0.8]])}


def body(dim, lo, hi, law, velocity=None, ppc=None, params=None):
    """A box of ``law``; parameters: the law's own ``test_params`` unless given, options its ``test_options``."""
    return mpmlab.Body(shape={"kind": "box", "lo": lo, "hi": hi}, material=law,
                       params=params_of(law) if params is None else params, density=1000.0,
                       particles_per_cell=ppc or 2**dim, velocity=velocity, options=options_of(law))


def law_scene(law, dim=2):
    lo, hi = [0.4] * dim, [0.55 if dim == 2 else 0.5] * dim
    g = [0.0, -9.8] + [0.0] * (dim - 2)
    return mpmlab.Scene(dim=dim, dx=0.05, domain=([0.0] * dim, [1.0] * dim), bodies=[body(dim, lo, hi, law)],
                        gravity=g, boundaries=[Walls(default="separate", thickness=2)], dt=1e-3, name=f"grad_{law}")


@lru_cache(maxsize=None)
def stepper(scene_key, transfer):
    """A cached fp64 Warp stepper; scene_key = (factory name, *args) of a scene factory below."""
    name, *args = scene_key
    return mpmlab.build_stepper(globals()[name](*args), "warp", transfer, "fp64")


def sheared_controls(st):
    c = st.controls()
    x = c["x"]
    c["v"] = c["v"] + (x - x.mean(0)) @ torch.tensor(SHEAR[st.dim]).T
    return c


def fd_errors(st, c, obs, steps, keys, seed=0, scale=None):
    """{key: (min relative error over HS, autograd directional derivative)}, one random direction each
    (the conformance kit's finite-difference check, ``mpmlab.testing.gradients.warp_fd_errors``)."""
    return warp_fd_errors(st, c, obs, steps, keys, seed, scale or {})


# ---- every law x transfer ----------------------------------------------------------------------------
#: (law, transfer) pairs: every transfer, or the few a law declares (``test_transfers``: a neural law)
CASES = [(law, t) for law in LAWS for t in TRANSFERS
         if registry.laws.get(law).test_transfers is None or t in registry.laws.get(law).test_transfers]


@pytest.mark.parametrize("law,transfer", CASES)
def test_fd_matches_autograd(law, transfer):
    st = stepper(("law_scene", law), transfer)
    c = sheared_controls(st)
    obs = Lagrangian(quantity="v")
    # the forward values are the fast path's (sorted, threaded) rollout
    with torch.no_grad():
        y = st.observe(c, Lagrangian(quantity="x"), (0,) + STEPS)
    state = st.init()
    state.v.assign(wp.array(c["v"].numpy(), dtype=st.T.vec))
    ref = st.rollout(state, steps=STEPS[-1], every=STEPS[0])
    np.testing.assert_allclose(y.numpy()[[0, 1]], ref.x[[0, 1]], rtol=0, atol=1e-12)
    np.testing.assert_allclose(y.numpy()[2], ref.x[-1], rtol=0, atol=1e-12)
    g = st.groups[0]
    keys = ("x", "v") + (("law",) if g.law.param_names() else ()) + (("law_weights",) if g.weights else ())
    errs = fd_errors(st, c, obs, STEPS, keys, scale={"x": 0.01})
    for k, (e, ad) in errs.items():
        assert abs(ad) > 1e-9, f"{k}: the directional derivative {ad:g} is too small to test anything"
        assert e <= 1e-6, f"{law}/{transfer}: d/d{k} autograd vs central differences, relative error {e:.2e}"


def test_plastic_parameters_get_gradients():
    """The law scenes really yield: the plastic parameters' gradients are non-zero."""
    plastic = {"hencky_drucker_prager": "friction_angle", "hencky_von_mises": "yield_stress",
               "drucker_prager_jaumann": "friction_angle"}
    for law, name in plastic.items():
        st = stepper(("law_scene", law), "mls")
        c = sheared_controls(st)
        prm = c["law"][0].clone().requires_grad_(True)
        y = st.observe(with_leaf(c, "law", prm), Lagrangian(quantity="v"), STEPS)
        (y * torch.tensor(np.random.default_rng(0).standard_normal(tuple(y.shape)))).sum().backward()
        j = st.groups[0].law.param_names().index(name)
        assert prm.grad[:, j].abs().max() > 0, f"{law}: no particle yielded, '{name}' has no gradient"


def test_fd_3d():
    st = stepper(("law_scene", "hencky_von_mises", 3), "apic")
    errs = fd_errors(st, sheared_controls(st), Lagrangian(quantity="v"), (5, 10), ("x", "v", "law"),
                     scale={"x": 0.01})
    for k, (e, ad) in errs.items():
        assert abs(ad) > 1e-9 and e <= 1e-6, (k, e, ad)


@pytest.mark.parametrize("dim", (2, 3))
@pytest.mark.parametrize("law", ("fixed_corotated", "hencky_von_mises"))
def test_stress_adjoint_at_repeated_singular_values(law, dim):
    """The rest state and rigid rotations have repeated singular values, where the SVD's own derivative
    is undefined; the spectral maps' adjoints (U V^T, the Hencky stress) must match central differences
    there and next to it (the divided-difference limit branch, |s_i - s_j| < eps^(1/3))."""
    from mpmlab.backends.warp.kernels import law_kernels

    cls = registry.laws.get(law)
    st = stepper(("law_scene", law, dim), "apic")
    T = st.T
    K = law_kernels(cls(), dim, "fp64")
    k, L = K.stress, K.types
    rng = np.random.default_rng(0)

    def rot(a):
        R = np.eye(dim)
        R[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
        return R

    near = np.eye(dim) * 1.02
    near[0, 0] += 1e-9
    Fs = np.array([np.eye(dim), 1.01 * rot(0.4), rot(0.3) @ near @ rot(-1.1).T])
    prm = np.tile(st.groups[0].params[0], (len(Fs), 1))
    w = rng.standard_normal((len(Fs), dim, dim))

    def tau(F, grad=False):
        Fa = wp.array(F, dtype=T.mat, requires_grad=grad)
        out = wp.zeros(len(F), dtype=T.mat, requires_grad=grad)
        # the law's other declared state fields (e.g. the plane-strain out-of-plane strain) at their start values
        rest = {f.name: wp.array(f.initial(len(F), dim), dtype=d) for f, (_, d, _) in zip(cls.state, L.fields)
                if f.name != "F"}
        tape = wp.Tape()
        with tape:
            wp.launch(k, dim=len(F), inputs=[L.state_arrays({"F": Fa, **rest}), wp.array(prm, dtype=T.scalar),
                                             L.weights({}), 0, out])
        if not grad:
            return out.numpy()
        out.grad = wp.array(w, dtype=T.mat)
        tape.backward()
        return Fa.grad.numpy()

    adj = tau(Fs, grad=True)
    assert np.all(np.isfinite(adj))
    for i in range(len(Fs)):
        d = rng.standard_normal((dim, dim))
        h = 1e-6
        e = np.zeros_like(Fs)
        e[i] = h * d
        fd = ((tau(Fs + e) - tau(Fs - e)) * w).sum() / (2 * h)
        assert abs(fd - (adj[i] * d).sum()) <= 1e-6 * max(abs(fd), 1.0), (i, fd, (adj[i] * d).sum())


# ---- boundaries, gravity, mass, volume -----------------------------------------------------------------
def friction_scene(kind):
    floorless = Walls(default="slip", faces={"y-": "none"}, thickness=2)   # the friction wall is the floor
    if kind == "plane":
        bcs = [Walls(default="slip", thickness=2), Plane(point=[0.5, 0.29], normal=[0.0, 1.0], friction=0.3)]
        bodies = [body(2, [0.4, 0.3], [0.6, 0.4], "fixed_corotated", velocity=[1.0, -0.3],
                       params={"E": 5e4, "nu": 0.3})]
    else:
        mu = [0.2, 0.4] if kind == "segments" else list(np.linspace(0.1, 0.5, 21))
        bcs = [floorless, FrictionWalls(face="y-", mu=mu, along="x", thickness=2, per_node=kind == "per_node")]
        # the block straddles the two segments (x = 0.5)
        bodies = [body(2, [0.4, 0.1], [0.6, 0.2], "fixed_corotated", velocity=[1.5, 0.0], params={"E": 5e4, "nu": 0.3})]
    return mpmlab.Scene(dim=2, dx=0.05, domain=([0.0, 0.0], [1.0, 1.0]), bodies=bodies, gravity=[0.0, -9.8],
                        boundaries=bcs, dt=5e-4, name=f"friction_{kind}")


@pytest.mark.parametrize("transfer", ("apic", "flip"))
@pytest.mark.parametrize("kind", ("segments", "per_node", "plane"))
def test_friction_gradient(kind, transfer):
    st = stepper(("friction_scene", kind), transfer)
    c = st.controls()
    key = ("boundary", 1, "friction" if kind == "plane" else "mu")
    errs = fd_errors(st, c, Lagrangian(quantity="v"), (10, 20), (key, "gravity", "mass", "volume"))
    for k, (e, ad) in errs.items():
        assert abs(ad) > 1e-9 and e <= 1e-6, (k, e, ad)
    # every friction segment the block touches gets a gradient
    mu = leaf(c, key).clone().requires_grad_(True)
    y = st.observe(with_leaf(c, key, mu), Lagrangian(quantity="v"), (10, 20))
    y.sum().backward()
    if kind == "segments":
        assert torch.all(mu.grad != 0)
    elif kind == "per_node":
        assert int((mu.grad != 0).sum()) >= 4


@pytest.mark.parametrize("transfer", ("apic", "flip"))
@pytest.mark.parametrize("kind", ("walls", "particle_velocity", "particle_rigid_motion", "grid_velocity", "particle_load",
                                  "box_obstacle"))
def test_boundary_gradients(kind, transfer):
    """Domain walls in contact (sticky x-, slip x+, separate y-), a prescribed particle velocity, a rigid
    grid grip (grid_velocity), a particle load (active from step 21) and a box obstacle: gradients w.r.t.
    their data and v."""
    keys = {"walls": ("v", "x"), "particle_velocity": (("boundary", 1, "velocity"), "v"),
            "particle_rigid_motion": (("boundary", 1, "velocity"), ("boundary", 1, "angular_velocity"), "v"),
            "grid_velocity": (("boundary", 1, "velocity"), ("boundary", 1, "angular_velocity"), "v"),
            "particle_load": (("boundary", 0, "force"), "v"), "box_obstacle": ("v",)}[kind]
    st = stepper(("boundary_scene", kind), transfer)
    steps = (20, 40) if kind in ("particle_load", "box_obstacle") else (10, 20)
    errs = fd_errors(st, st.controls(), Lagrangian(quantity="v"), steps, keys, scale={"x": 0.01})
    for k, (e, ad) in errs.items():
        assert abs(ad) > 1e-9 and e <= 1e-6, (k, e, ad)


def boundary_scene(kind):
    from .test_boundaries import scene_for

    return scene_for(kind, 2)


def test_segments_do_not_change_gradients():
    """segment = 3 recomputes 4 segments from saved states; the gradients equal one 10-step segment's."""
    st = stepper(("friction_scene", "segments"), "flip")
    obs = Lagrangian(quantity="x")

    def grads(segment):
        c = st.controls()
        leaves = [c["x"], c["v"], c["law"][0], c["boundary"][1]["mu"], c["gravity"], c["mass"], c["volume"]]
        for a in leaves:
            a.requires_grad_(True)
        y = st.observe(c, obs, (4, 10), segment=segment)
        (y * torch.linspace(-1.0, 1.0, y.numel(), dtype=y.dtype).reshape(y.shape)).sum().backward()
        return y.detach(), [a.grad for a in leaves]

    y3, g3 = grads(3)
    y10, g10 = grads(10)
    assert torch.equal(y3, y10)
    for a, b in zip(g3, g10):
        assert torch.all(torch.isfinite(a)) and a.abs().max() > 0
        assert (a - b).abs().max() <= 1e-12 * b.abs().max()


# ---- observations --------------------------------------------------------------------------------------
def hand_state(x, v, grad=False):
    from types import SimpleNamespace

    T = stepper(("law_scene", "fixed_corotated"), "pic").T
    return SimpleNamespace(x=wp.array(x, dtype=T.vec, requires_grad=grad),
                           v=wp.array(v, dtype=T.vec, requires_grad=grad))


def run_obs(obs, state):
    st = stepper(("law_scene", "fixed_corotated"), "pic")
    impl = obs.implementation("warp", "observation")(obs, st)
    out = wp.zeros(impl.shape[0], dtype=st.T.vec, requires_grad=True)
    tape = wp.Tape()
    with tape:
        impl.launch(state, out)
    return impl, out, tape


def test_observations_match_numpy_oracle():
    st = stepper(("law_scene", "fixed_corotated"), "pic")
    n = st.particles.count
    x = np.full((n, 2), 0.9)                    # far from both monitors
    x[:3] = [[0.10, 0.10], [0.12, 0.09], [0.30, 0.30]]
    v = np.arange(2 * n, dtype=float).reshape(n, 2)
    state = hand_state(x, v)
    for q, z in (("x", x), ("v", v)):
        lag = Lagrangian(quantity=q, particles=[2, 0])
        _, out, _ = run_obs(lag, state)
        np.testing.assert_array_equal(out.numpy(), z[[2, 0]])
        np.testing.assert_array_equal(out.numpy(), apply_numpy(lag, {"x": x, "v": v}))
        eul = Eulerian(centers=[[0.11, 0.1], [0.5, 0.5]], half_size=0.02, quantity=q)
        _, out, _ = run_obs(eul, state)
        hand = np.array([(z[0] + z[1]) / 2, [0.0, 0.0]])     # particles 0, 1 in the first; none in the second
        np.testing.assert_allclose(out.numpy(), hand, rtol=0, atol=1e-15)
        np.testing.assert_allclose(out.numpy(), apply_numpy(eul, {"x": x, "v": v}), rtol=0, atol=1e-15)


def test_observation_adjoints():
    """Lagrangian: identity on the picked rows; Eulerian: 1/count on the members' averaged quantity and
    nothing through membership (JAX-MPM Eq. 27)."""
    st = stepper(("law_scene", "fixed_corotated"), "pic")
    n = st.particles.count
    x = np.full((n, 2), 0.9)
    x[:3] = [[0.10, 0.10], [0.12, 0.09], [0.30, 0.30]]
    v = np.ones((n, 2))
    for obs in (Lagrangian(quantity="v", particles=[2, 0]),
                Eulerian(centers=[[0.11, 0.1]], half_size=0.02, quantity="v")):
        state = hand_state(x, v, grad=True)
        impl, out, tape = run_obs(obs, state)
        seed = np.arange(1, 2 * impl.shape[0] + 1, dtype=float).reshape(impl.shape)
        out.grad = wp.array(seed, dtype=st.T.vec)
        tape.backward()
        want = np.zeros((n, 2))
        if isinstance(obs, Lagrangian):
            want[2], want[0] = seed[0], seed[1]
        else:
            want[0] = want[1] = seed[0] / 2
        np.testing.assert_allclose(state.v.grad.numpy(), want, rtol=0, atol=1e-15)
        assert not state.x.grad.numpy().any()


def test_lagrangian_on_sorted_fast_path_state():
    """Fast-path states keep particles sorted by cell; the gather maps scene indices to storage."""
    st = stepper(("law_scene", "fixed_corotated"), "mls")
    s = st._advance(st.init(), 3)
    assert s.order.perm is not None and np.any(s.order.perm != np.arange(st.particles.count))
    obs = Lagrangian(quantity="v", particles=[0, 5, 17])
    impl = obs.implementation("warp", "observation")(obs, st)
    out = wp.zeros(3, dtype=st.T.vec)
    impl.launch(s, out)
    np.testing.assert_array_equal(out.numpy(), apply_numpy(obs, st.to_numpy(s)))


# ---- non-finite adjoints and diverging forwards ---------------------------------------------------------------
def two_body_scene():
    return mpmlab.Scene(dim=2, dx=0.05, domain=([0.0, 0.0], [1.0, 1.0]), gravity=[0.0, -9.8], dt=1e-3,
                        bodies=[body(2, [0.2, 0.4], [0.35, 0.55], "fixed_corotated", velocity=[0.3, -0.2]),
                                body(2, [0.6, 0.4], [0.75, 0.55], "hencky_von_mises", velocity=[0.3, -0.2])],
                        boundaries=[Walls(default="separate", thickness=2)], name="two_bodies")


def test_nan_law_parameter_raises_gradient_error():
    """A NaN yield stress keeps its particle elastic (the forward stays finite) but its derivative is
    0 * NaN: the error names the last step (the first one the backward pass meets), the particle in
    scene order and the control."""
    st = stepper(("two_body_scene",), "apic")
    c = st.controls()
    g = st.groups[1]
    prm = c["law"][1].clone()
    prm[5, g.law.param_names().index("yield_stress")] = float("nan")
    c["law"] = (c["law"][0], prm.requires_grad_(True))
    y = st.observe(c, Lagrangian(quantity="v"), (4, 10), segment=3)
    assert torch.isfinite(y).all()
    with pytest.raises(GradientError) as err:
        (y ** 2).sum().backward()
    assert (err.value.step, err.value.particle, err.value.field) == (10, g.start + 5, "law[1]")


def test_overflowing_adjoint_names_step_and_particle():
    """An adjoint that overflows at an intermediate observation (step 4, across segment boundaries)
    is caught in that step's backward pass, at a particle of the body it was seeded on (the other
    body is far away: its adjoints stay finite)."""
    st = stepper(("two_body_scene",), "apic")
    g = st.groups[1]
    c = st.controls()
    c["v"].requires_grad_(True)
    y = st.observe(c, Lagrangian(quantity="v", particles=list(range(g.start, g.stop))), (4, 10), segment=3)
    seed = torch.zeros_like(y)
    seed[0] = 1e308
    with pytest.raises(GradientError) as err:
        y.backward(seed)
    assert err.value.step == 4 and g.start <= err.value.particle < g.stop
    assert err.value.field in ("x", "v", "C", "F", "tau")


def test_non_finite_loss_gradient_is_reported():
    st = stepper(("two_body_scene",), "apic")
    c = st.controls()
    c["v"].requires_grad_(True)
    y = st.observe(c, Lagrangian(quantity="v"), (4, 10))
    seed = torch.zeros_like(y)
    seed[1, 3, 1] = float("nan")
    with pytest.raises(GradientError) as err:
        y.backward(seed)
    assert err.value.step == 10 and "loss" in str(err.value)


def test_diverging_forward_raises_before_indexing_the_grid():
    st = stepper(("two_body_scene",), "apic")
    c = st.controls()
    c["v"] = c["v"].clone()
    c["v"][40, 0] = 1e6                  # leaves the domain in one step
    with pytest.raises(SimulationDiverged) as err:
        st.observe(c, Lagrangian(quantity="x"), (5,))
    g = st.groups[1]                      # the kick spreads to its neighbours through the grid, not further
    assert err.value.step == 1 and g.start <= err.value.particle < g.stop


# ---- torch optimiser ----------------------------------------------------------------------------------
def test_adam_fits_initial_velocity_scale():
    """JAX-MPM Sec. 5.1 in miniature: recover the scale alpha of an initial velocity field
    v0 = alpha * u(x) from Lagrangian positions, with torch.optim.Adam driving the Warp rollout."""
    st = stepper(("law_scene", "weakly_compressible"), "apic")
    c = st.controls()
    x = c["x"]
    u = torch.stack([0.4 - x[:, 1], x[:, 0] - 0.45], dim=1)         # a swirl, no wall contact
    obs = Lagrangian(quantity="x", particles=12, seed=3)
    steps = (10, 20)

    def predict(alpha):
        return st.observe(with_leaf(c, "v", alpha * u), obs, steps)

    with torch.no_grad():
        target = predict(torch.tensor(2.0, dtype=torch.float64))
    alpha = torch.tensor(1.0, dtype=torch.float64, requires_grad=True)
    opt = torch.optim.Adam([alpha], lr=0.1, betas=(0.5, 0.9))     # light momentum: no overshoot on 1 scalar
    for _ in range(40):
        opt.zero_grad()
        loss = ((predict(alpha) - target) ** 2).sum()
        loss.backward()
        opt.step()
    assert abs(alpha.item() - 2.0) < 1e-4, alpha.item()
