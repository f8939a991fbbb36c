"""Grid velocity q / m at nodes with a tiny mass (a stencil's far tail at a free surface, m ~ 1e-25 in fp32):
the reverse pass must stay finite on both backends. The textbook adjoint -q / m^2 underflows m^2 to 0 and
gave -inf there (a NaN gradient once each in two 200-epoch JAX fits of JAX-MPM Sec. 5.2)."""
import numpy as np

Q = np.array([[2e-25, 1e-25], [4.0, 2.0]], np.float32)   # momentum per node
M = np.array([1e-25, 2.0], np.float32)                     # node mass
CT = np.array([[1e-3, 2e-3], [1.0, 1.0]], np.float32)     # incoming cotangent of the velocity
# exact: d/dq = ct / m, d/dm = -(q . ct) / m^2 = -(v . ct) / m
EXPECT_DM = np.array([-(2.0 * 1e-3 + 1.0 * 2e-3) / 1e-25, -(2.0 + 1.0) / 2.0])


def test_jax_per_mass_adjoint_is_finite_and_exact():
    import jax
    import jax.numpy as jnp

    from mpmlab.backends.jax.stepper import per_mass

    f = lambda q, m: jnp.sum(jnp.asarray(CT) * per_mass(q, m[:, None]))
    gq, gm = jax.grad(f, argnums=(0, 1))(jnp.asarray(Q), jnp.asarray(M))
    naive = jax.grad(lambda m: jnp.sum(jnp.asarray(CT) * (jnp.asarray(Q) / m[:, None])))(jnp.asarray(M))
    assert not np.isfinite(np.asarray(naive)[0])              # what the textbook adjoint gives
    np.testing.assert_allclose(np.asarray(gm), EXPECT_DM, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(gq), CT / M[:, None], rtol=1e-6)


def test_warp_grid_update_adjoint_is_finite_and_exact():
    import warp as wp

    from mpmlab.backends.warp import kernels as K
    from mpmlab.backends.warp.types import warp_types

    T, gvec = warp_types(2, "fp32"), K.grid_vec_type(2, "fp32")
    mm = wp.array(np.concatenate([Q, M[:, None]], axis=1), dtype=gvec, requires_grad=True)
    f = wp.zeros(1, dtype=T.vec, requires_grad=True)
    g = wp.zeros(1, dtype=T.vec, requires_grad=True)
    gv, gvo = wp.zeros(2, dtype=T.vec, requires_grad=True), wp.zeros(1, dtype=T.vec, requires_grad=True)
    none = np.full(4, K.WALL_CODES["none"], np.int32)
    tape = wp.Tape()
    with tape:
        # the tape-safe form of the grid update (the differentiable path's)
        wp.launch(K.grid_update_kernel(2, "fp32", False, tape=True), dim=2,
                  inputs=[mm, f, 1, 2, 0, T.ivec(), T.ivec(), T.scalar(1e-3), T.vec(), g, T.ivec(2, 1), T.ivec(1, 2),
                          wp.array(none, dtype=int), 0, gv, gvo])
    gv.grad.assign(CT)
    tape.backward()
    adj = mm.grad.numpy()
    np.testing.assert_allclose(gv.numpy(), Q / M[:, None], rtol=1e-6)
    np.testing.assert_allclose(adj[:, 2], EXPECT_DM, rtol=1e-6)
    np.testing.assert_allclose(adj[:, :2], CT / M[:, None], rtol=1e-6)
