"""The branch-free JAX SVD behind every F-based law (``mpmlab.backends.jax.linalg``, issue 17): accuracy
against ``numpy.linalg.svd`` in fp64 on the laws' hard deformation gradients and on repeated, inverted and
rank-deficient ones, fp32 sanity, the sign and order conventions of ``svd_rotations``, agreement with the
LAPACK implementation it replaced, and finite derivatives at repeated singular values. Everything runs
jitted and vmapped, as the stepper runs the laws (XLA fuses and recomputes differently from eager jnp)."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mpmlab.backends.jax import linalg as L
from mpmlab.laws import _linalg_np
from mpmlab.testing.states import deformation_gradients, rotation

jax.config.update("jax_enable_x64", True)

svd = jax.jit(jax.vmap(L.svd_rotations))


def hard_cases(dim, rng):
    """The laws' hard F (random, rotated, near-singular 1e-3, stretch 3) and: identity, exact rotations,
    repeated singular values, near-repeated ones, inverted (det < 0), a singular value of 1e-8, rank 1, zero."""
    R = lambda: rotation(dim, rng)
    diag = lambda *s: np.diag(np.array(s[:dim - 1] + s[-1:], float))
    Fs = list(deformation_gradients(dim, rng))
    Fs += [np.eye(dim), -np.eye(dim), diag(1.0, -1.0), diag(3.0, 0.6), diag(0.6, 3.0), diag(1.0, 0.0),
           np.zeros((dim, dim))]
    for _ in range(8):
        Fs += [R(), 2.5 * R(), R() @ diag(2.0, 2.0, 0.5) @ R().T, R() @ diag(0.5, 2.0, 2.0) @ R().T,
               R() @ diag(1.0, 1.0 + 1e-9, 1.0 - 1e-9) @ R().T, R() @ diag(3.0, 1.0, 0.6) @ R().T @ diag(1.0, 1.0, -1.0),
               R() @ diag(1.0, 1.0, 1e-3) @ R().T @ diag(1.0, 1.0, -1.0), R() @ diag(2.0, 1.0, 1e-8) @ R().T,
               R() @ np.diag(rng.uniform(0.1, 3.0, dim)) @ R().T]
    return np.array(Fs)


def check(F, U, s, V, tol):
    """Reconstruction, orthogonality, proper rotations, |s| against numpy, order and det sign: the largest
    error of each (relative to max |F| or s_1)."""
    F, U, s, V = (np.asarray(a, float) for a in (F, U, s, V))
    dim = F.shape[-1]
    scale = np.maximum(np.abs(F).max(axis=(1, 2)), 1e-300)
    sn = np.linalg.svd(F, compute_uv=False)
    err = {
        "reconstruction": (np.abs(np.einsum("nij,nj,nkj->nik", U, s, V) - F).max(axis=(1, 2)) / scale).max(),
        "orthogonality": max(np.abs(np.einsum("nji,njk->nik", W, W) - np.eye(dim)).max() for W in (U, V)),
        "det": max(np.abs(np.linalg.det(W) - 1.0).max() for W in (U, V)),
        "singular values": (np.abs(np.abs(s) - sn).max(axis=1) / np.maximum(sn[:, 0], 1e-300)).max(),
    }
    for k, e in err.items():
        assert e <= tol, f"{k}: {e:.3e} > {tol:.0e}"
    assert np.all(s[:, :-1] >= 0.0)
    assert np.all(np.abs(s[:, :-1]) >= np.abs(s[:, 1:]) - tol * sn[:, :1]), "|s| not descending"
    detF = np.linalg.det(F)
    clear = np.abs(detF) > 1e3 * tol * scale ** dim
    assert np.all(np.sign(s[clear, -1]) == np.sign(detF[clear])), "the last singular value lacks det F's sign"
    return err


@pytest.mark.parametrize("dim", (2, 3))
def test_fp64_hard_cases_against_numpy(dim):
    F = hard_cases(dim, np.random.default_rng(0))
    U, s, V = svd(jnp.asarray(F))
    check(F, U, s, V, 1e-12)
    # the same U, s, V conventions as the NumPy reference where the SVD is unique (distinct singular values)
    for k in range(16):
        Ur, sr, Vr = _linalg_np.svd_rotations(F[k])
        if np.min(np.abs(np.diff(np.abs(sr)))) > 1e-6:
            assert np.abs(np.asarray(s[k]) - sr).max() <= 1e-12 * sr[0]
            # singular vectors up to the sign of each pair (u_i, v_i): compare U_i v_i^T
            for i in range(dim):
                assert np.abs(np.outer(U[k][:, i], V[k][:, i]) - np.outer(Ur[:, i], Vr[:, i])).max() <= 1e-11


@pytest.mark.parametrize("dim", (2, 3))
def test_random_batches_with_inversions(dim):
    rng = np.random.default_rng(1)
    F = np.concatenate([rng.standard_normal((3000, dim, dim)), np.eye(dim) + 1e-6 * rng.standard_normal((500, dim, dim))])
    assert (np.linalg.det(F) < 0).sum() > 1000
    U, s, V = svd(jnp.asarray(F))
    check(F, U, s, V, 1e-12)


@pytest.mark.parametrize("dim", (2, 3))
def test_repeated_singular_values_in_one_compiled_batch(dim):
    # rotations and scaled rotations (F = I after a rigid motion): the Jacobi rotations' angles are decided
    # by round-off here, and XLA recomputes a value in each fusion that uses it, possibly rounded otherwise
    # (FMA contraction); a decision taken twice (a sort, say) then permutes U and V differently
    rng = np.random.default_rng(5)
    Q = np.array([rotation(dim, rng) for _ in range(1500)])
    D = np.diag([2.0] * (dim - 1) + [0.5])
    F = np.concatenate([Q, 0.7 * Q, Q @ D @ np.swapaxes(Q, 1, 2), Q @ np.diag([1.0] * (dim - 1) + [-1.0])])
    U, s, V = svd(jnp.asarray(F))
    check(F, U, s, V, 1e-12)


@pytest.mark.parametrize("dim", (2, 3))
def test_fp32(dim):
    rng = np.random.default_rng(2)
    F = np.concatenate([hard_cases(dim, rng), rng.standard_normal((2000, dim, dim))])
    F32 = F.astype(np.float32)
    U, s, V = svd(jnp.asarray(F32))
    assert U.dtype == s.dtype == V.dtype == jnp.float32
    check(F32, U, s, V, 5e-6)


@pytest.mark.parametrize("dim", (2, 3))
def test_polar_and_spectral_match_numpy_and_lapack(dim):
    rng = np.random.default_rng(3)
    F = hard_cases(dim, rng)
    # R is unique where no two signed singular values sum to zero (rank >= d - 1 and not, e.g., -I in 3D)
    sv = np.array([_linalg_np.svd_rotations(f)[1] for f in F])
    F = F[np.min(np.abs(sv[:, :, None] + sv[:, None, :]) + 9.0 * np.eye(dim), axis=(1, 2)) > 1e-6]
    R = jax.jit(jax.vmap(L.polar_rotation))(jnp.asarray(F))
    Rn = np.array([_linalg_np.polar_rotation(f) for f in F])
    assert np.abs(np.asarray(R) - Rn).max() <= 1e-12
    with L.svd_impl("lapack"):
        R_lapack = jax.jit(jax.vmap(L.polar_rotation))(jnp.asarray(F))
        logV_lapack = jax.jit(jax.vmap(lambda f: L.spectral(_log, True, f, 0.0)))(jnp.asarray(F[:16]))
    assert np.abs(np.asarray(R) - np.asarray(R_lapack)).max() <= 1e-12
    logV = jax.jit(jax.vmap(lambda f: L.spectral(_log, True, f, 0.0)))(jnp.asarray(F[:16]))
    assert np.abs(np.asarray(logV) - np.asarray(logV_lapack)).max() <= 1e-11


def _log(s, p):
    return jnp.log(jnp.abs(s)) + p


@pytest.mark.parametrize("dim", (2, 3))
def test_derivatives_finite_at_repeated_singular_values_and_as_before(dim):
    rng = np.random.default_rng(4)
    Q = rotation(dim, rng)
    Fs = [np.eye(dim), Q, 2.0 * Q, Q @ np.diag([2.0] * (dim - 1) + [0.5]) @ Q.T, np.eye(dim) + 0.2 * rng.standard_normal((dim, dim))]
    W = jnp.asarray(rng.standard_normal((dim, dim)))

    def loss(F):
        return (jnp.sum(W * L.polar_rotation(F)) + jnp.sum(W * L.spectral(_log, True, F, 0.0))
                + jnp.sum(L.singular_values(F) ** 3))      # symmetric in s: defined at repeated values

    grad = jax.jit(jax.vmap(jax.grad(loss)))
    G = np.asarray(grad(jnp.asarray(np.array(Fs))))
    assert np.all(np.isfinite(G))
    with L.svd_impl("lapack"):
        G_lapack = np.asarray(jax.jit(jax.vmap(jax.grad(loss)))(jnp.asarray(np.array(Fs))))
    # the custom JVP rules do not depend on which orthonormal bases the SVD picks at repeated values
    assert np.abs(G - G_lapack).max() <= 1e-10 * max(1.0, np.abs(G).max())


def test_unknown_implementation_is_refused():
    with pytest.raises(ValueError, match="unknown SVD implementation"):
        with L.svd_impl("qr"):
            pass
    assert L.SVD_IMPL == "jacobi"
