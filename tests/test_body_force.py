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
