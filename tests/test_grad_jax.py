"""Gradients through JAX rollouts (issue #4), fp64. AD against central finite differences (FD): every
law on APIC (one six-law scene), every other transfer on a hencky_drucker_prager block, 3D
(fixed_corotated and hencky_drucker_prager), walls of each kind in contact, friction per segment and
per node; segmenting invariance, JAX = Warp gradients, observation operators, NaN localisation."""
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import mpmlab
from mpmlab.backends.jax import differentiable as D
from mpmlab.boundaries import FrictionWalls, Walls
from mpmlab.core.errors import ConfigError, GradientError
from mpmlab.observations import Eulerian, Lagrangian, apply_numpy
from mpmlab.simulator import build_stepper

from .scenes import LAW_PARAMS

TRANSFERS = ("pic", "flip", "apic", "mls", "tpic")
LAWS = tuple(LAW_PARAMS)
STEPS = [4, 8]
#: the transfer whose FD checks run every law: APIC's P2G and G2P use the most terms of the built-in
#: schemes (affine momentum m C and the grad-w force; the first moment B and the velocity gradient: the
#: capability table); PIC, MLS and TPIC use subsets of them, FLIP alone its split force and grid-velocity
#: increment (mpmlab/transfers/*/jax.py)
ALL_LAWS_TRANSFER = "apic"
#: the law(s) of the scene each other transfer's FD checks run on (every law on every transfer cost a
#: 17-24 s compile of the six-law scene's gradient per transfer in CI): plastic, so the transfer's
#: adjoint runs through an elastic stress (Hencky) and the yield return map (its friction angle active)
OTHER_TRANSFER_LAWS = ("hencky_drucker_prager",)
#: (transfer, law) pairs of the 2D FD checks: every law on APIC, OTHER_TRANSFER_LAWS on every other transfer
FD_CASES = [(t, law) for t in TRANSFERS for law in (LAWS if t == ALL_LAWS_TRANSFER else OTHER_TRANSFER_LAWS)]


#: the laws' test parameters, with hencky_drucker_prager's friction angle at 25 deg: in plane strain (issue 18:
#: the 2D return uses the three principal strains) the OTHER_TRANSFER_LAWS block's plastic particles at 30 deg
#: all sit at the cone tip within STEPS (the friction angle inactive: d loss / d phi = 0 on flip, mls, tpic);
#: at 25 deg some are on the cone (measured on flip: d loss / d phi * phi = 0.032)
GRAD_PARAMS = {**LAW_PARAMS, "hencky_drucker_prager": {**LAW_PARAMS["hencky_drucker_prager"], "friction_angle": 25.0}}


def grad_scene(dim, laws=LAWS):
    """One small block per law, apart from each other and from the domain faces for the whole horizon."""
    bodies = []
    for k, name in enumerate(laws):
        c = np.full(dim, 0.5)
        c[0] = 0.1 + 0.16 * k
        h = 0.05
        bodies.append(mpmlab.Body(shape={"kind": "box", "lo": (c - h).tolist(), "hi": (c + h).tolist()},
                                  material=name, params=GRAD_PARAMS[name], density=1000.0,
                                  particles_per_cell=2 ** dim, name=name))
    g = np.zeros(dim)
    g[1] = -9.8
    return mpmlab.Scene(dim=dim, dx=0.05, domain=([-0.1] * dim, [1.1] * dim), bodies=bodies, gravity=g.tolist(),
                        dt=1e-3, name=f"grad_{dim}d")


def smooth_controls(stepper, rate=3.0):
    """Controls with a non-rigid initial velocity per body (compression + shear + spin): every law is
    loaded away from its rest state, so the dynamics are smooth in the controls (a rigid motion would
    sit at the apex of the Drucker-Prager cones, a non-smooth point, tested separately)."""
    c = stepper.controls()
    x = np.asarray(c["x"])
    v = np.zeros_like(x)
    A = rate * np.array([[-0.6, 0.9, 0.2], [0.2, -0.4, 0.1], [0.1, -0.3, -0.5]])[: x.shape[1], : x.shape[1]]
    for g in stepper.groups:
        sl = slice(g.start, g.stop)
        xc = x[sl].mean(axis=0)
        v[sl] = (x[sl] - xc) @ A.T + 0.2
    c["v"] = jnp.asarray(v)
    return c


_GRADS = {}


def grad_of(loss, c):
    """The AD gradient of ``loss`` at ``c``, computed once per (loss, controls) of a fixture."""
    k = (id(loss), id(c))
    if k not in _GRADS:
        _GRADS[k] = (loss, c, jax.jit(jax.grad(loss))(c))   # keeps loss and c alive: ids stay unique
    return _GRADS[k][2]


def fd_check(loss, c, key, direction, hs=(1e-5, 1e-6, 1e-7)):
    """Relative error of the AD directional derivative against central differences, best over h (the
    V-shaped error curve: truncation for large h, round-off for small h)."""
    g = grad_of(loss, c)

    def along(tree, d):
        if key == "law":
            gi, arr = d
            return jnp.sum(tree["law"][gi] * arr)
        return jnp.sum(tree[key] * d)

    def shift(s):
        cp = dict(c)
        if key == "law":
            gi, arr = direction
            law = list(c["law"])
            law[gi] = law[gi] + s * arr
            cp["law"] = tuple(law)
        else:
            cp[key] = c[key] + s * direction
        return cp

    ad = float(along(g, direction))
    errs = []
    for h in hs:
        fd = float(loss(shift(h)) - loss(shift(-h))) / (2 * h)
        errs.append(abs(ad - fd) / max(abs(ad), abs(fd), 1e-300))
    return ad, min(errs)


@functools.lru_cache(maxsize=None)
def setup_2d(transfer):
    """(stepper, controls, loss) of the 2D FD checks on ``transfer``: the six-law scene on
    ALL_LAWS_TRANSFER, the OTHER_TRANSFER_LAWS scene on the others; built once per transfer, so (with
    ``grad_of``) the gradient is compiled once per transfer, whichever test asks first."""
    scene = grad_scene(2, LAWS if transfer == ALL_LAWS_TRANSFER else OTHER_TRANSFER_LAWS)
    st = build_stepper(scene, "jax", transfer, "fp64")
    return st, smooth_controls(st), fd_loss(st, segment=FD_SEGMENT.get(transfer, 4))


#: the 2D FD losses' segment per transfer: MLS's in 3-step segments and a 1-step remainder per 4-step
#: interval (the segmented recomputation, compared against 1-step segments in
#: test_segmenting_does_not_change_the_gradient), the others in one 4-step segment per interval (two copies
#: of the step and its adjoint in the compiled gradient instead of four: the compile is most of each
#: transfer's first test; the segmenting does not depend on the transfer, mpmlab.backends.jax.differentiable.advance)
FD_SEGMENT = {"mls": 3}


def fd_loss(st, segment=3):
    """The 2D FD checks' loss: the velocities at STEPS against fixed random weights, recomputed in
    segments of ``segment`` steps."""
    obs = Lagrangian(quantity="v")
    w = jnp.asarray(np.random.default_rng(0).standard_normal((len(STEPS), st.particles.count, 2)))
    return jax.jit(lambda c: jnp.sum(w * st.observe(c, obs, STEPS, segment=segment)))


@pytest.mark.parametrize("transfer,law", FD_CASES)
def test_fd_initial_velocity_and_position(transfer, law):
    """d loss / d v and d loss / d x along a random direction on one law's particles."""
    st, c, loss = setup_2d(transfer)
    g = next(g for g in st.groups if g.law.name == law)
    rng = np.random.default_rng(1)
    for key in ("v", "x"):
        d = np.zeros(np.shape(c[key]))
        d[g.start:g.stop] = rng.standard_normal((g.count, st.dim))
        ad, err = fd_check(loss, c, key, jnp.asarray(d))
        assert ad != 0.0
        assert err <= 1e-6, f"{law} {st.transfer.name}: d loss / d {key} AD {ad:.6e}, relative error {err:.2e}"


@pytest.mark.parametrize("transfer,law", FD_CASES)
def test_fd_law_parameters(transfer, law):
    """d loss / d each parameter of one law (relative perturbation; parameters inactive in the regime skipped)."""
    st, c, loss = setup_2d(transfer)
    gi = next(i for i, g in enumerate(st.groups) if g.law.name == law)
    prm = np.asarray(c["law"][gi])
    g = grad_of(loss, c)["law"][gi]
    scale = float(jnp.max(jnp.abs(g * prm)))
    assert scale > 0
    inactive = []
    for j, name in enumerate(st.groups[gi].law.param_names()):
        d = np.zeros_like(prm)
        d[:, j] = prm[:, j] if prm[0, j] != 0 else 1.0   # relative perturbation of the parameter
        ad, err = fd_check(loss, c, "law", (gi, jnp.asarray(d)), hs=(1e-3, 1e-4, 1e-5, 1e-6))
        if abs(ad) < 1e-9 * scale:                       # parameter inactive in this regime (e.g. cohesion)
            inactive.append(name)
            continue
        assert err <= 1e-6, f"{law} {st.transfer.name}: d loss / d {name} AD {ad:.6e}, relative error {err:.2e}"
    if transfer != ALL_LAWS_TRANSFER:                    # the other transfers' law yields: every parameter acts
        assert not inactive, f"{law} {transfer}: inactive {inactive}"


def test_fd_3d_fixed_corotated_and_sand():
    """d loss / d v by FD on 3D fixed_corotated and hencky_drucker_prager blocks (APIC), observed at
    STEPS. One segment per observation interval (segment=4 = the spacing of STEPS): the program holds
    two copies of the 3D step and its adjoint instead of four (segment=3: a 3-step segment and a
    1-step remainder per interval), which halves the compile that dominates this test; splitting an
    interval into segments is checked in 2D (test_segmenting_does_not_change_the_gradient)."""
    scene = grad_scene(3, laws=("fixed_corotated", "hencky_drucker_prager"))
    st = build_stepper(scene, "jax", "apic", "fp64")
    c = smooth_controls(st)
    obs = Lagrangian(quantity="x")
    w = jnp.asarray(np.random.default_rng(0).standard_normal((len(STEPS), st.particles.count, 3)))
    loss = jax.jit(lambda c: jnp.sum(w * st.observe(c, obs, STEPS, segment=4)))
    d = jnp.asarray(np.random.default_rng(2).standard_normal(np.shape(c["v"])))
    ad, err = fd_check(loss, c, "v", d)
    assert err <= 1e-6, err


def test_segmenting_does_not_change_the_gradient():
    """The MLS FD checks' loss (steps 4, 8 with segment=3: per interval one unscanned 3-step segment and
    a 1-step remainder) has the same gradient recomputed in 1-step segments (a scan over four). A
    segment longer than the interval is clamped to it: the default segment of the friction and
    JAX = Warp tests, checked there by FD and against Warp."""
    st, c, loss = setup_2d("mls")
    grads = [grad_of(loss, c), jax.jit(jax.grad(fd_loss(st, segment=1)))(c)]
    for a, b in zip(jax.tree_util.tree_leaves(grads[0]), jax.tree_util.tree_leaves(grads[1])):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-12, atol=1e-15)


def test_observe_matches_rollout_and_irregular_schedule():
    st = build_stepper(grad_scene(2, laws=("weakly_compressible",)), "jax", "apic", "fp64")
    c = st.controls()
    tr = st.rollout(steps=9, every=1)
    y = np.asarray(st.observe(c, Lagrangian(quantity="v"), [0, 2, 3, 9], segment=4))
    np.testing.assert_allclose(y, tr.v[[0, 2, 3, 9]], rtol=0, atol=1e-14)
    with pytest.raises(ConfigError):
        st.observe(c, Lagrangian(quantity="v"), [3, 3])


def slide_scene(*boundaries, name="slide"):
    """A fixed_corotated block sliding along the floor at 1.5 m/s while falling onto it."""
    body = mpmlab.Body(shape={"kind": "box", "lo": [0.1, 0.05], "hi": [0.5, 0.15]}, material="fixed_corotated",
                       params={"E": 5e4, "nu": 0.3}, density=1000.0, particles_per_cell=4, velocity=[1.5, -0.3])
    return mpmlab.Scene(dim=2, dx=0.05, domain=([0.0, 0.0], [1.0, 1.0]), bodies=[body], gravity=[0.0, -9.8],
                        boundaries=list(boundaries), dt=5e-4, name=name)


FLOORLESS = Walls(default="slip", faces={"y-": "none"}, thickness=2)


@functools.lru_cache(maxsize=None)
def sliding_setup():
    """The sliding block over a floor with friction per segment, its left strip driven by a particle
    constraint listed before the grid boundaries: (scene, observation, JAX stepper, controls, loss
    sum |x|^2 at steps 10 and 20, its gradient), one compile shared by the JAX = Warp test and the
    per-segment friction FD check."""
    from mpmlab.boundaries import ParticleVelocity

    bcs = [ParticleVelocity(region={"kind": "box", "lo": [0.1, 0.0], "hi": [0.16, 1.0]}, velocity=[0.5, 0.0], t_end=0.005),
           FLOORLESS, FrictionWalls(face="y-", mu=[0.3, 0.2], along="x", thickness=2)]
    scene = slide_scene(*bcs, name="order")
    obs = Lagrangian(quantity="x")
    st = build_stepper(scene, "jax", "apic", "fp64")
    c = st.controls()
    loss = lambda c: jnp.sum(st.observe(c, obs, [10, 20]) ** 2)   # noqa: E731
    return scene, obs, st, c, loss, jax.grad(loss)(c)


def check_friction_fd(loss, c, k, g):
    """The AD gradient ``g`` of ``loss`` w.r.t. boundary ``k``'s mu against a central difference, along
    all-ones and a random direction."""
    assert float(jnp.max(jnp.abs(g))) > 0
    mu = c["boundary"][k]["mu"]
    for d in (jnp.ones_like(mu), jnp.asarray(np.random.default_rng(3).standard_normal(mu.shape))):
        ad = float(jnp.sum(g * d))

        def shifted(s):
            cp = dict(c)
            b = list(c["boundary"])
            b[k] = {**b[k], "mu": mu + s * d}
            cp["boundary"] = tuple(b)
            return cp
        h = 1e-6
        fd = float(loss(shifted(h)) - loss(shifted(-h))) / (2 * h)
        assert abs(ad - fd) <= 1e-6 * abs(ad), (k, ad, fd)


def test_friction_gradient_per_segment():
    """Block sliding over a floor with Coulomb friction (JAX-MPM Eqs. 35-36), mu per segment (two along
    x), a particle constraint on its left strip for the first 10 of 20 steps: d loss / d mu by FD."""
    _, _, st, c, loss, g = sliding_setup()
    check_friction_fd(loss, c, 2, g["boundary"][2]["mu"])


def test_friction_gradient_per_node():
    """The same block over a floor with Coulomb friction per grid node along x: d loss / d mu by FD."""
    fw = FrictionWalls(face="y-", mu=list(np.linspace(0.1, 0.4, 21)), along="x", thickness=2, per_node=True)
    st = build_stepper(slide_scene(FLOORLESS, fw), "jax", "apic", "fp64")
    c = st.controls()
    obs = Lagrangian(quantity="x")
    loss = jax.jit(lambda c: jnp.sum(st.observe(c, obs, [10, 20])[..., 0]))
    check_friction_fd(loss, c, 1, jax.grad(loss)(c)["boundary"][1]["mu"])


def test_observations_against_hand_values():
    st = build_stepper(grad_scene(2, laws=("fixed_corotated",)), "jax", "pic", "fp64")
    x = np.array([[0.1, 0.1], [0.12, 0.09], [0.5, 0.5], [0.3, 0.3]])
    v = np.array([[1.0, 2.0], [3.0, 4.0], [5.0, 6.0], [7.0, 8.0]])
    state = {"x": jnp.asarray(x), "v": jnp.asarray(v)}
    # monitor 0 holds particles 0 and 1 -> mean (2, 3); monitor 1 holds none -> 0; monitor 2 holds particle 2
    eul = Eulerian(centers=[[0.11, 0.1], [0.8, 0.8], [0.5, 0.49]], half_size=0.02)
    impl = eul.implementation("jax", "observation")(eul, st)
    expect = np.array([[2.0, 3.0], [0.0, 0.0], [5.0, 6.0]])
    np.testing.assert_allclose(np.asarray(impl.fn(state)), expect)
    np.testing.assert_allclose(apply_numpy(eul, state), expect)
    assert eul.empty(x).tolist() == [False, True, False]
    lag = Lagrangian(quantity="x", particles=[3, 1])
    impl = lag.implementation("jax", "observation")(lag, st)
    np.testing.assert_allclose(np.asarray(impl.fn(state)), x[[3, 1]])
    # gradient of an Eulerian observation flows to the velocities of the particles inside only
    e_impl = eul.implementation("jax", "observation")(eul, st)
    g = jax.grad(lambda v_: jnp.sum(e_impl.fn({"x": jnp.asarray(x), "v": v_})))(jnp.asarray(v))
    np.testing.assert_allclose(np.asarray(g), [[0.5, 0.5], [0.5, 0.5], [1.0, 1.0], [0.0, 0.0]])


def test_nan_gradient_is_located():
    """A NaN entering the backward pass at a known step and particle is reported there."""
    st = build_stepper(grad_scene(2, laws=("fixed_corotated",)), "jax", "apic", "fp64")
    c = smooth_controls(st)
    obs = Lagrangian(quantity="x")
    steps = [3, 6]
    ct = np.zeros((2, st.particles.count, 2))
    ct[0, 7, 1] = np.nan                           # dL/d x_7 at step 3 is NaN
    with pytest.raises(GradientError) as e:
        D.locate_nan_gradient(st, c, obs, steps, jnp.asarray(ct), segment=2)
    assert e.value.step == 3 and e.value.particle == 7
    assert "step 3" in str(e.value) and "particle 7" in str(e.value)
    assert not D.check_gradient({"a": jnp.asarray([1.0, np.nan])})
    assert D.check_gradient({"a": jnp.asarray([1.0, 2.0])})


#: the contact scene's blocks, one per wall kind: (face of that kind, lo, hi, initial velocity), each
#: pressed onto its face and sliding along it
CONTACT = {"separate": ("y-", [0.2, 0.05], [0.5, 0.2], [1.0, -1.5]),    # the floor, gravity pressing too
           "sticky": ("x-", [0.05, 0.45], [0.2, 0.75], [-1.5, -1.0]),
           "slip": ("x+", [0.8, 0.45], [0.95, 0.75], [1.5, 1.0])}


@functools.lru_cache(maxsize=None)
def contact_setup():
    """Three fixed_corotated blocks, each pressed onto a wall of one kind (far from each other and
    from the other faces), one stepper and loss: one compile serves the three kinds."""
    bodies = [mpmlab.Body(shape={"kind": "box", "lo": lo, "hi": hi}, material="fixed_corotated",
                          params={"E": 3e4, "nu": 0.3}, density=1000.0, particles_per_cell=4, velocity=v, name=kind)
              for kind, (face, lo, hi, v) in CONTACT.items()]
    walls = Walls(default="slip", faces={face: kind for kind, (face, *_) in CONTACT.items()}, thickness=2)
    scene = mpmlab.Scene(dim=2, dx=0.05, domain=([0.0, 0.0], [1.0, 1.0]), bodies=bodies, gravity=[0.0, -9.8],
                         boundaries=[walls], dt=5e-4, name="press")
    st = build_stepper(scene, "jax", "apic", "fp64")
    c = st.controls()
    obs = Lagrangian(quantity="v")
    w = jnp.asarray(np.random.default_rng(5).standard_normal((2, st.particles.count, 2)))
    loss = jax.jit(lambda c: jnp.sum(w * st.observe(c, obs, [6, 12], segment=4)))
    return st, c, loss


@pytest.mark.parametrize("kind", list(CONTACT))
def test_fd_with_walls_in_contact(kind):
    """A block pressed onto a wall of ``kind`` and sliding along it (the separate floor's nodes in contact
    keep v.n < 0, away from its switch): d loss / d v of that block and d loss / d E of its particles by
    FD, so each kind's clamp is differentiated correctly."""
    st, c, loss = contact_setup()
    mine = st.particles.body_id == list(CONTACT).index(kind)
    assert mine.sum() > 0 and len(st.groups) == 1
    d = np.zeros(np.shape(c["v"]))
    d[mine] = np.random.default_rng(6).standard_normal((int(mine.sum()), 2))
    ad, err = fd_check(loss, c, "v", jnp.asarray(d))
    assert ad != 0.0 and err <= 1e-6, (kind, ad, err)
    gi = 0
    dl = np.zeros(np.shape(c["law"][0]))
    dl[mine, 0] = np.asarray(c["law"][0])[mine, 0]
    ad, err = fd_check(loss, c, "law", (gi, jnp.asarray(dl)), hs=(1e-3, 1e-4, 1e-5, 1e-6))
    assert ad != 0.0 and err <= 1e-6, (kind, "E", ad, err)


def test_jax_and_warp_gradients_agree_in_scene_order():
    """Both backends' controls() list boundaries in scene order (a particle constraint before the grid
    boundaries here) and give the same gradient of every control (fp64)."""
    import torch  # noqa: F401 - required (the Warp side of the comparison)

    scene, obs, sj, cj, _, gj = sliding_setup()
    assert [sorted(d) for d in cj["boundary"]] == [["velocity"], [], ["mu"]]
    sw = build_stepper(scene, "warp", "apic", "fp64")
    cw = sw.controls()
    leaves = [cw["x"], cw["v"], cw["law"][0], cw["boundary"][0]["velocity"], cw["boundary"][2]["mu"], cw["gravity"],
              cw["mass"], cw["volume"]]
    for t in leaves:
        t.requires_grad_(True)
    (sw.observe(cw, obs, [10, 20]) ** 2).sum().backward()
    ref = [gj["x"], gj["v"], gj["law"][0], gj["boundary"][0]["velocity"], gj["boundary"][2]["mu"], gj["gravity"],
           gj["mass"], gj["volume"]]
    for a, t in zip(ref, leaves):
        a = np.asarray(a)
        np.testing.assert_allclose(t.grad.numpy().reshape(a.shape), a, rtol=1e-9, atol=1e-12 * np.abs(a).max())


@pytest.mark.parametrize("kind", ("particle_rigid_motion", "grid_velocity"))
@pytest.mark.parametrize("dim", (2,))
def test_rigid_motion_gradients_agree_with_warp_and_differences(dim, kind):
    """particle_velocity with an angular velocity (the torsion end), and the grid grip grid_velocity
    (boundary 1; its particle_velocity partner is boundary 2): d loss / d (v0, omega, v) on JAX
    equals Warp's (fp64) and a central difference in omega. (3D: Warp's central differences in
    tests/test_grad_warp.py::test_boundary_gradients use the same rigid-motion scene in 2D; the 3D
    rotation is checked against its closed form in tests/test_boundaries.py; 3D here costs ~50 s.)"""
    import torch  # noqa: F401 - required (the Warp side of the comparison)

    from tests.test_boundaries import scene_for

    scene = scene_for(kind, dim)
    obs = Lagrangian(quantity="x")
    steps = [10, 20]
    sj = build_stepper(scene, "jax", "apic", "fp64")
    cj = sj.controls()
    loss = lambda c: jnp.sum(jnp.sin(7.0 * sj.observe(c, obs, steps)))   # noqa: E731
    gj = jax.grad(loss)(cj)
    sw = build_stepper(scene, "warp", "apic", "fp64")
    cw = sw.controls()
    leaves = [cw["v"], cw["boundary"][1]["velocity"], cw["boundary"][1]["angular_velocity"]]
    for t in leaves:
        t.requires_grad_(True)
    torch.sin(7.0 * sw.observe(cw, obs, steps)).sum().backward()
    ref = [gj["v"], gj["boundary"][1]["velocity"], gj["boundary"][1]["angular_velocity"]]
    for a, t in zip(ref, leaves):
        a = np.asarray(a)
        assert np.abs(a).max() > 1e-6
        np.testing.assert_allclose(t.grad.numpy().reshape(a.shape), a, rtol=1e-8, atol=1e-10 * np.abs(a).max())
    w = np.asarray(cj["boundary"][1]["angular_velocity"], float)
    d = np.zeros_like(w) + (1.0 if w.ndim == 0 else np.array([0.3, -0.5, 0.8]))
    h = 1e-5

    def at(s):
        b = list(cj["boundary"])
        b[1] = {**b[1], "angular_velocity": jnp.asarray(w + s * d)}
        return float(loss({**cj, "boundary": tuple(b)}))
    fd = (at(h) - at(-h)) / (2 * h)
    ad = float(np.sum(np.asarray(gj["boundary"][1]["angular_velocity"]) * d))
    assert abs(fd - ad) <= 1e-6 * max(1.0, abs(ad)), (fd, ad)
