"""The ``body_force`` boundary (mpmlab.boundaries.body_force): the manufactured-solution force is the
one that makes U(X, t) exact for the law's own stress (finite differences of the law's NumPy
reference), and the JAX and Warp implementations add the same m_p b(X_p, t) as the NumPy oracle."""
import numpy as np
import pytest

from mpmlab.boundaries.body_force import BodyForce, MMSAxisAligned
from mpmlab.core import registry
from mpmlab.core.errors import ConfigError
from mpmlab.scenes.validation import MMS_LAW_NAMES, mms_axis_aligned


@pytest.mark.parametrize("law", ["fixed_corotated", "hencky"])
@pytest.mark.parametrize("dim", [2, 3])
def test_mms_force_balances_law_stress(law, dim):
    """b = U_tt - div P(F) / rho0 by central differences of the law's reference P (verification #2a)."""
    bf = BodyForce(values={"law": law, "phase": (0.1, 0.7, 0.3), "shift": 0.2})
    p = bf.packed(dim)
    L = registry.laws.get(MMS_LAW_NAMES[law])
    prm = np.array([1.0e4, 0.3] + ([1.0e30] if law == "hencky" else []))
    X = np.array([[0.3, 0.6, 0.8][:dim]])
    t, h, k = 0.0037, 1e-5, 1e-6

    def P(Xq):
        return L.reference.first_piola(np.diag(MMSAxisAligned.exact(np, Xq, t, p, dim)[1][0]), prm)

    div = sum((P(X + h * np.eye(dim)[j]) - P(X - h * np.eye(dim)[j]))[:, j] / (2 * h) for j in range(dim))
    U = lambda tt: MMSAxisAligned.exact(np, X, tt, p, dim)[0][0]
    acc = (U(t + k) - 2 * U(t) + U(t - k)) / k**2
    b = bf.evaluate(X, t, dim)[0]
    np.testing.assert_allclose(b, acc - div / p[4], rtol=2e-5, atol=1e-3 * np.abs(b).max())
    assert np.abs(b).max() > 10.0          # not trivially zero


@pytest.mark.parametrize("law", ["fixed_corotated", "hencky"])
def test_backends_add_the_reference_force(law):
    """JAX particle_force and the Warp kernel equal mass * the NumPy b(X, t), fp64, with a time window."""
    import mpmlab.backends.jax.stepper  # noqa: F401  (enables float64 in JAX, as every JAX stepper does)
    from mpmlab.backends.jax.body_force import body_force as jax_bf
    from mpmlab.backends.warp.body_force import body_force as warp_bf
    import jax.numpy as jnp
    import warp as wp
    from types import SimpleNamespace
    from mpmlab.backends.warp.types import warp_types

    scene = mms_axis_aligned(cells=4, dim=2, law=law)
    bf = next(b for b in scene.boundaries if isinstance(b, BodyForce))
    P = scene.particles()
    t = 0.0041
    ref = P.mass[:, None] * bf.evaluate(P.x, t, 2)
    assert np.abs(ref).max() > 0
    j = jax_bf(bf, scene, jnp.float64)
    out_j = np.asarray(j.particle_force(jnp.asarray(P.x), jnp.asarray(P.mass), jnp.asarray(t), j.params))
    np.testing.assert_allclose(out_j, ref, rtol=1e-12, atol=1e-12)
    wp.init()
    st = SimpleNamespace(T=warp_types(2, "fp64"), device="cpu", precision="fp64")
    w = warp_bf(bf, scene, st)
    ext = wp.zeros(P.count, dtype=st.T.vec, device="cpu")
    assert w.add_force(ext, t)
    np.testing.assert_allclose(ext.numpy(), ref, rtol=1e-12, atol=1e-12)
    # outside [t_start, t_end) nothing is added, on both backends
    late = BodyForce(field=bf.field, values=bf.values, t_end=0.001)
    ext.zero_()
    assert not warp_bf(late, scene, st).add_force(ext, t) and not ext.numpy().any()
    jl = jax_bf(late, scene, jnp.float64)
    assert not np.asarray(jl.particle_force(None, jnp.asarray(P.mass), jnp.asarray(t), jl.params)).any()


def test_uniform_field_and_body_selection():
    b = BodyForce(field="uniform", values={"g": (1.0, -2.0)}, bodies=[0])
    X = np.random.default_rng(0).random((5, 2))
    np.testing.assert_allclose(b.evaluate(X, 0.3, 2), np.tile([1.0, -2.0], (5, 1)))


def test_bad_configs_fail_clearly():
    scene = mms_axis_aligned(cells=4)
    with pytest.raises(ConfigError, match="unknown field"):
        BodyForce(field="nope").validate(scene)
    with pytest.raises(ConfigError, match="law"):
        BodyForce(values={"law": "neo_hookean"}).validate(scene)
    with pytest.raises(ConfigError, match="unknown option"):
        BodyForce(values={"amplitude": 1.0}).validate(scene)
    assert registry.boundaries.get("body_force") is BodyForce


def test_only_scenes_with_a_body_force_compile_it():
    """A scene without body force builds no force term (Warp: no ext array, P2G without the ext
    branch; JAX: no force boundary), so fixed-dt scenes without one are unchanged."""
    from mpmlab.simulator import build_stepper
    from mpmlab.transfers import make_transfer
    from mpmlab.scenes.validation import vibrating_bar

    s = build_stepper(vibrating_bar(cells=10), backend="jax", transfer=make_transfer("apic"), precision="fp64")
    assert s._force_bcs == []
    s = build_stepper(mms_axis_aligned(cells=4), backend="jax", transfer=make_transfer("apic"), precision="fp64")
    assert len(s._force_bcs) == 1


def test_body_force_gradients_on_both_backends():
    """``body_force`` is differentiable on Warp too (its tape-safe implementation): gradients of a loss of
    the positions with respect to the field's values, the mass and v agree with JAX (fp64)."""
    import jax
    import jax.numpy as jnp
    import torch

    import mpmlab
    from mpmlab.boundaries import Walls
    from mpmlab.observations import Lagrangian

    bodies = [mpmlab.Body(shape={"kind": "box", "lo": [0.3, 0.4], "hi": [0.45, 0.5]}, material="fixed_corotated",
                          params={"E": 2e4}, particles_per_cell=4, velocity=[0.2, 0.0]),
              mpmlab.Body(shape={"kind": "box", "lo": [0.55, 0.4], "hi": [0.7, 0.5]}, material="fixed_corotated",
                          params={"E": 2e4}, particles_per_cell=4)]
    scene = mpmlab.Scene(dim=2, dx=0.05, domain=([0, 0], [1, 1]), gravity=[0, 0], dt=1e-3, bodies=bodies,
                         boundaries=[Walls(default="slip", thickness=2),
                                     BodyForce(field="uniform", values={"g": (3.0, -2.0)}, bodies=[1], t_end=0.012)])
    obs, steps = Lagrangian(quantity="x"), (10, 20)
    sj = mpmlab.build_stepper(scene, "jax", "apic", "fp64")
    c = sj.controls()
    n = sj.particles.count
    w = np.sin(np.arange(2 * n * 2)).reshape(2, n, 2)

    def loss(field, mass, v):
        bc = list(c["boundary"])
        bc[1] = {"field": field}
        return jnp.sum(sj.observe({**c, "boundary": tuple(bc), "mass": mass, "v": v}, obs, steps) * w)

    gj = jax.grad(loss, argnums=(0, 1, 2))(c["boundary"][1]["field"], c["mass"], c["v"])
    sw = mpmlab.build_stepper(scene, "warp", "apic", "fp64")
    cw = sw.controls()
    leaves = [cw["boundary"][1]["field"], cw["mass"], cw["v"]]
    for t in leaves:
        t.requires_grad_(True)
    (sw.observe(cw, obs, steps) * torch.tensor(w)).sum().backward()
    for name, a, t in zip(("field", "mass", "v"), gj, leaves):
        a = np.asarray(a)
        assert np.abs(a).max() > 0, name
        assert np.max(np.abs(a - t.grad.numpy())) <= 1e-9 * np.abs(a).max(), name


# ---- user fields (issue 19 item 2): a registry, written once per backend, refused where missing ----------
from mpmlab.boundaries.body_force import BodyForceField, register_field  # noqa: E402

A_RAMP, C_RAMP, DT, STEPS = 3.0, 2.0, 1e-3, 10


class Ramp(BodyForceField):
    """b = (a t, c X_0): a user field with a NumPy/JAX formula and a Warp function (no mpmlab edit)."""

    name = "test_ramp"
    defaults = {"a": 1.0, "c": 1.0}

    @staticmethod
    def evaluate(xp, X, t, p, dim, options):
        return xp.stack([p[0] * t + 0.0 * X[:, 0], p[1] * X[:, 0]], axis=-1)

    @staticmethod
    def warp_func(dim, precision, options):
        import warp as wp
        from mpmlab.backends.warp.types import warp_types

        T = warp_types(dim, precision)
        vec, scalar = T.vec, T.scalar

        @wp.func
        def ramp(X: vec, t: scalar, p: wp.array(dtype=scalar)):
            return vec(p[0] * t, p[1] * X[0])

        return ramp


class JaxOnly(Ramp):
    name = "test_jax_only"
    warp_func = None


register_field(Ramp, provenance="tests")
register_field(JaxOnly, provenance="tests")


def ramp_scene(bf):
    import mpmlab
    from mpmlab.boundaries import Walls

    body = mpmlab.Body(shape={"kind": "box", "lo": [0.35, 0.45], "hi": [0.65, 0.55]}, material="fixed_corotated",
                       params={"E": 1e4}, particles_per_cell=4, velocity=[0.1, 0.0])
    return mpmlab.Scene(dim=2, dx=0.1, domain=([0, 0], [1, 1]), gravity=[0, 0], dt=DT, bodies=[body],
                        boundaries=[Walls(default="slip", thickness=2), bf], name="ramp")


def momentum_change(scene, backend):
    """(trajectory, total momentum change over STEPS steps); APIC conserves momentum, so it is exactly
    sum_k sum_p m_p b_p(t_k) dt (the walls are never reached)."""
    import mpmlab

    traj = mpmlab.simulate(scene, steps=STEPS, every=1, backend=backend, transfer="apic", precision="fp64")
    return traj, traj.mass @ traj.v[-1] - traj.mass @ traj.v[0]


@pytest.mark.parametrize("backend", ["jax", "warp"])
def test_user_field_momentum_change(backend):
    """The registered user field and the same b as an ``expression`` both give the analytic momentum change
    sum_k sum_p m_p (a t_k, c X_p0) dt = (a M dt^2 sum k, c dt STEPS sum_p m_p X_p0)."""
    expr = {"b": ["a * t", "c * X[0]"], "constants": {"a": A_RAMP, "c": C_RAMP}}
    for bf in (BodyForce(field="test_ramp", values={"a": A_RAMP, "c": C_RAMP}), BodyForce(field="expression", values=expr)):
        scene = ramp_scene(bf)
        traj, dP = momentum_change(scene, backend)
        m, X0 = traj.mass, traj.x[0]
        exact = np.array([A_RAMP * m.sum() * DT**2 * sum(range(STEPS)), C_RAMP * DT * STEPS * (m @ X0[:, 0])])
        assert bf.position == "reference"
        assert np.all(np.abs(exact) > 1e-3)
        np.testing.assert_allclose(dP, exact, rtol=1e-11, atol=0, err_msg=f"{backend} {bf.field}")


@pytest.mark.parametrize("backend", ["jax", "warp"])
def test_expression_of_the_current_position(backend):
    """An expression in x (current position) is evaluated at each step's start positions on both backends:
    dP = sum_k sum_p m_p c x_p0(t_k) dt, from the positions of every frame."""
    bf = BodyForce(field="expression", values={"b": ["0", "c * x[0]"], "constants": {"c": C_RAMP}})
    assert bf.position == "current"
    traj, dP = momentum_change(ramp_scene(bf), backend)
    exact = C_RAMP * DT * sum(traj.mass @ traj.x[k][:, 0] for k in range(STEPS))
    assert abs(dP[0]) < 1e-14
    np.testing.assert_allclose(dP[1], exact, rtol=1e-11, atol=0)
    # the body moves (v_x = 0.1): the reference-position answer differs by ~1e-3 relative, 1e8 x the tolerance
    assert abs(exact - C_RAMP * DT * STEPS * (traj.mass @ traj.x[0][:, 0])) > 1e-4 * abs(exact)


def test_unknown_or_missing_fields_are_refused():
    """An unknown field is refused on both backends with the registered names (never mapped to another
    formula); a field without a Warp function is refused by the Warp stepper, and runs on JAX."""
    import mpmlab
    from mpmlab.core.errors import MissingImplementationError

    for backend in ("jax", "warp"):
        with pytest.raises(ConfigError, match=r"unknown field 'nope'; registered fields: .*expression.*test_ramp"):
            mpmlab.build_stepper(ramp_scene(BodyForce(field="nope")), backend, "apic", "fp64")
    scene = ramp_scene(BodyForce(field="test_jax_only", values={"a": A_RAMP, "c": C_RAMP}))
    with pytest.raises(MissingImplementationError, match="body_force field 'test_jax_only' has no implementation "
                                                         "for backend 'warp'"):
        mpmlab.build_stepper(scene, "warp", "apic", "fp64")
    assert momentum_change(scene, "jax")[1][1] > 0
    with pytest.raises(ConfigError, match="both X .* and x"):
        BodyForce(field="expression", values={"b": ["X[0]", "x[1]"]}).validate(scene)
    with pytest.raises(ConfigError, match="unknown name 'y'"):
        BodyForce(field="expression", values={"b": ["y", "0"]}).validate(scene)
    with pytest.raises(ConfigError, match="not an allowed function"):
        BodyForce(field="expression", values={"b": ["__import__('os')", "0"]}).validate(scene)
    with pytest.raises(ConfigError, match="3 components; the scene is 2D"):
        BodyForce(field="expression", values={"b": ["0", "0", "0"]}).validate(scene)
    with pytest.raises(ConfigError, match="is built in"):
        register_field(Ramp, name="uniform")


def test_expression_constants_get_gradients_on_both_backends():
    """An expression's constants are the field's differentiable parameters; with b(x, t) the force also
    depends on the positions along the rollout. JAX and Warp gradients agree (fp64)."""
    import jax
    import jax.numpy as jnp
    import torch

    import mpmlab
    from mpmlab.observations import Lagrangian

    bf = BodyForce(field="expression", values={"b": ["a * t", "c * x[0] * x[1]"], "constants": {"a": 2.0, "c": 3.0}})
    scene = ramp_scene(bf)
    obs, steps = Lagrangian(quantity="x"), (5, 10)
    sj = mpmlab.build_stepper(scene, "jax", "apic", "fp64")
    c = sj.controls()
    w = np.sin(np.arange(2 * sj.particles.count * 2)).reshape(2, -1, 2)

    def loss(field, v):
        return jnp.sum(sj.observe({**c, "boundary": (c["boundary"][0], {"field": field}), "v": v}, obs, steps) * w)

    gj = jax.grad(loss, argnums=(0, 1))(c["boundary"][1]["field"], c["v"])
    sw = mpmlab.build_stepper(scene, "warp", "apic", "fp64")
    cw = sw.controls()
    leaves = [cw["boundary"][1]["field"], cw["v"]]
    for t in leaves:
        t.requires_grad_(True)
    (sw.observe(cw, obs, steps) * torch.tensor(w)).sum().backward()
    for name, a, t in zip(("field", "v"), gj, leaves):
        a = np.asarray(a)
        assert np.all(np.abs(a) > 0) if name == "field" else np.abs(a).max() > 0, name
        assert np.max(np.abs(a - t.grad.numpy())) <= 1e-9 * np.abs(a).max(), name
