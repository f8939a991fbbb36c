"""Small per-particle linear algebra for the JAX laws (vmapped by the stepper)."""
from __future__ import annotations

from contextlib import contextmanager
from functools import partial

import jax
import jax.numpy as jnp

HENCKY_MIN_STRETCH = 1e-4  # same guard as mpmlab.laws._linalg_np

#: Which SVD backs ``svd_rotations`` (read when a function is traced): ``"jacobi"``, the branch-free one
#: below, or ``"lapack"``, ``jnp.linalg.svd`` (one LAPACK call per 3x3 matrix on CPU, 88 % of a 3D
#: fixed-corotated step before issue 17); kept so ``benchmarks/gradients.py`` can time both in one run.
SVD_IMPL = "jacobi"


@contextmanager
def svd_impl(name: str):
    """Trace the JAX laws with SVD implementation ``name`` (``"jacobi"`` or ``"lapack"``) inside the block."""
    global SVD_IMPL
    if name not in ("jacobi", "lapack"):
        raise ValueError(f"svd_impl: unknown SVD implementation {name!r} (jacobi, lapack)")
    old, SVD_IMPL = SVD_IMPL, name
    try:
        yield
    finally:
        SVD_IMPL = old


def svd_rotations(F):
    """F = U diag(s) V^T with U, V proper rotations; the last singular value carries det(F)'s sign.

    |s| in descending order, as ``numpy.linalg.svd``. F: [..., d, d], d = 2 or 3 (``"lapack"``: one [d, d])."""
    if SVD_IMPL == "lapack":
        return _svd_rotations_lapack(F)
    U, s, V = _svd_lists(F)
    return _mat(U), jnp.stack(s, -1), _mat(V)


def _svd_rotations_lapack(F):
    """The implementation before issue 17 (one matrix; vmapped by the laws)."""
    U, s, Vt = jnp.linalg.svd(F)
    V = Vt.T
    du = jnp.sign(jnp.linalg.det(U))
    dv = jnp.sign(jnp.linalg.det(V))
    flip_u = jnp.ones_like(s).at[-1].set(du)
    flip_v = jnp.ones_like(s).at[-1].set(dv)
    return U * flip_u[None, :], s * flip_u * flip_v, V * flip_v[None, :]


# ---- branch-free SVD of 2x2 and 3x3 matrices ---------------------------------------------------------------
# Every entry of a matrix is its own array (shape F.shape[:-2]: [N] under the stepper's vmap), so the SVD is
# elementwise jnp that XLA fuses into vectorised loops over particles; no LAPACK call, no branches (jnp.where).
#
# 3D: one-sided (Hestenes) cyclic Jacobi on the columns of B = F V (V = I at first): each rotation of a
# column pair (p, q) makes the two columns orthogonal; after the sweeps B's columns are the singular vectors
# scaled by the singular values. This is McAdams et al. 2011 ("Computing the Singular Value Decomposition of
# 3x3 matrices with minimal branching and elementary floating point operations") with two changes: exact
# rotations instead of their approximate Givens quaternions (accurate to fp32 only), and the rotations act
# on F's columns (Hestenes) instead of diagonalising F^T F and then QR-factorising F V: the orthogonal
# columns give U and s directly. Sweeps: the worst reconstruction error over 1.5e6 random, near-singular,
# repeated and inverted matrices is at round-off (3e-15) after 5 sweeps in fp64 (2e-10 after 4) and
# (1e-6) after 4 in fp32 (1.6e-3 after 3).
#
# Each rotation also sorts its pair (the longer column goes first: of the two rotations that make the pair
# orthogonal, the one that puts the larger eigenvalue of the pair's Gram matrix first). The last sweep's
# pairs (0,1), (0,2), (1,2) are then a sorting network, so |s| comes out descending as numpy's, with no
# separate sort -- a sort compares near-equal norms at repeated singular values (F = I, rotations), and
# under XLA a compare is recomputed in every fusion that uses it, where FMA contraction can round it the
# other way: B and V would be permuted differently (a sort after the sweeps did that to 4 % of a batch of
# rotations; tests/test_svd_jax.py). The rotation is instead carried by one number, tau = tan(theta / 2)
# from one divide, which XLA computes once and keeps in memory (its fusion pass does not duplicate an
# expensive op such as a divide into several users); B and V are continuous functions of tau. tau itself
# is continuous in the pair's Gram matrix except where a swap of two orthogonal columns goes +90 or -90
# degrees, both valid. (The same holds for the angle itself: at repeated singular values it is decided by
# round-off, so it must be computed once for B and V.)
#
# U: u1 = b1 / |b1|, u2 = the part of b2 normal to u1, normalised, u3 = u1 x u2 (proper by construction);
# s_i = u_i . b_i, so s3 = det(F) / (s1 s2) carries det F's sign (V is a product of rotations, det V = 1).
# 2D: the same rotation once diagonalises the 2x2 Gram matrix (a closed form); u2 = u1 rotated by 90 degrees.
_PAIRS = {2: ((0, 1),), 3: ((0, 1), (0, 2), (1, 2))}


def _sweeps(dim, dtype):
    if dim == 2:
        return 1
    return 5 if jnp.finfo(dtype).bits > 32 else 4


def _dot(a, b):
    return sum(x * y for x, y in zip(a, b))


def _sorting_rotation(bp, bq):
    """tan(theta / 2) of the rotation [[c, s], [-s, c]] of columns (bp, bq) that makes them orthogonal with
    |bp| >= |bq|: (c, -s) is the top eigenvector (v0, v1) of the Gram matrix [[a, g], [g, b]], v0 >= 0, and
    tan(theta / 2) = -v1 / (|v| + v0)."""
    a, b, g = _dot(bp, bp), _dot(bq, bq), _dot(bp, bq)
    d = b - a
    r = jnp.sqrt(d * d + 4.0 * g * g)            # eigenvalue gap
    rho = r + jnp.abs(d)
    nv = jnp.sqrt(2.0 * r * rho)                 # |v|: v = (rho, 2g) if a >= b else (2|g|, sign(g) rho)
    keep = d <= 0.0
    v1 = jnp.where(keep, 2.0 * g, jnp.where(g >= 0.0, rho, -rho))
    den = nv + jnp.where(keep, rho, 2.0 * jnp.abs(g))
    return -v1 / jnp.where(den > 0.0, den, 1.0)  # den = 0 only for two zero columns: no rotation


def _rotate(bp, bq, tau):
    k = 1.0 / (1.0 + tau * tau)
    c, s = (1.0 - tau * tau) * k, 2.0 * tau * k
    return [c * x - s * y for x, y in zip(bp, bq)], [s * x + c * y for x, y in zip(bp, bq)]


def _svd_lists(F):
    """(U, s, V) of ``svd_rotations`` as nested lists of arrays: U[i][j], s[i], V[i][j]."""
    d = F.shape[-1]
    one, zero = jnp.ones_like(F[..., 0, 0]), jnp.zeros_like(F[..., 0, 0])
    B = [[F[..., i, j] for i in range(d)] for j in range(d)]          # columns of F V
    V = [[one if i == j else zero for i in range(d)] for j in range(d)]   # columns of V
    for _ in range(_sweeps(d, F.dtype)):
        for p, q in _PAIRS[d]:
            tau = _sorting_rotation(B[p], B[q])
            B[p], B[q] = _rotate(B[p], B[q], tau)
            V[p], V[q] = _rotate(V[p], V[q], tau)
    n1 = jnp.sqrt(_dot(B[0], B[0]))
    ok1 = n1 > 0.0
    u1 = [jnp.where(ok1, x / jnp.where(ok1, n1, 1.0), e) for x, e in zip(B[0], [one] + [zero] * (d - 1))]
    if d == 2:
        u = [u1, [-u1[1], u1[0]]]
    else:
        w = [x - _dot(u1, B[1]) * y for x, y in zip(B[1], u1)]
        n2 = jnp.sqrt(_dot(w, w))
        # rank <= 1: any unit vector normal to u1 (u1 x e_x or u1 x e_y, the longer)
        alt = jnp.where(u1[0] * u1[0] <= u1[1] * u1[1], jnp.stack([zero, u1[2], -u1[1]]),
                        jnp.stack([-u1[2], zero, u1[0]]))
        alt = alt / jnp.sqrt(jnp.sum(alt * alt, axis=0))
        ok2 = n2 > 0.0
        u2 = [jnp.where(ok2, x / jnp.where(ok2, n2, 1.0), y) for x, y in zip(w, alt)]
        u3 = [u1[1] * u2[2] - u1[2] * u2[1], u1[2] * u2[0] - u1[0] * u2[2], u1[0] * u2[1] - u1[1] * u2[0]]
        u = [u1, u2, u3]
    s = [_dot(u[j], B[j]) for j in range(d)]
    return [[u[j][i] for j in range(d)] for i in range(d)], s, [[V[j][i] for j in range(d)] for i in range(d)]


def _mat(rows):
    return jnp.stack([jnp.stack(r, -1) for r in rows], -2)


def polar_rotation(F):
    """R of F = R S, with finite derivatives at repeated singular values (F = I included)."""
    return spectral(_ones, False, F, jnp.zeros((), F.dtype))


@jax.custom_jvp
def singular_values(F):
    """The s of ``svd_rotations`` (the last one carries det(F)'s sign) with the derivative
    ds_i = (U^T dF V)_ii, finite at repeated singular values (where the SVD's own JVP divides by
    s_i^2 - s_j^2); the same derivative as Warp's ``singular_values``."""
    return svd_rotations(F)[1]


@singular_values.defjvp
def _singular_values_jvp(primals, tangents):
    (F,), (dF,) = primals, tangents
    U, s, V = svd_rotations(F)
    return s, jnp.einsum("ji,jk,ki->i", U, dF, V)


def _ones(s, p):
    return jnp.ones_like(s) + 0.0 * p


def lame(E, nu):
    return E / (2.0 * (1.0 + nu)), E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))


def hencky_strain(F):
    U, s, V = svd_rotations(F)
    return U, jnp.log(jnp.maximum(s, HENCKY_MIN_STRETCH)), V


# Spectral functions of F with a custom JVP (moved here from the Hencky law so every law shares it):
# the JVP of jnp.linalg.svd divides by s_i^2 - s_j^2 and is NaN at repeated singular values -- at
# F = I, the rest state of every particle -- while the spectral map's derivative is well defined there.
@partial(jax.custom_jvp, nondiff_argnums=(0, 1))
def spectral(g, left, F, p):
    """U diag(g(s, p)) U^T if ``left`` else U diag(g(s, p)) V^T, for F = U diag(s) V^T (``svd_rotations``).

    ``g(s, p) -> [d]`` must be permutation-equivariant in s (isotropic), ``p`` holds its parameters
    (differentiable). Derivatives are finite at repeated singular values.
    """
    U, s, V = svd_rotations(F)
    return _scaled_product(U, g(s, p), U if left else V)


def _scaled_product(U, gs, W):
    """U diag(gs) W^T of one matrix. With the Jacobi SVD as a sum of outer products (elementwise): XLA CPU
    runs a batched 3x3 dot through transposed copies of its operands, slower than the SVD's own fusions."""
    if SVD_IMPL == "lapack":
        return (U * gs[None, :]) @ W.T                  # as before issue 17
    return sum((U[..., :, k] * gs[..., k, None])[..., :, None] * W[..., None, :, k] for k in range(U.shape[-1]))


@spectral.defjvp
def _spectral_jvp(g, left, primals, tangents):
    F, p = primals
    dF, dp = tangents
    U, s, V = svd_rotations(F)
    W = U if left else V
    gs, dg_p = jax.jvp(lambda q: g(s, q), (p,), (dp,))
    Jg = jax.jacfwd(g)(s, p)                              # [d, d], d g_i / d s_j
    dFp = U.T @ dF @ V                                    # dF in the singular bases
    sym, skw = 0.5 * (dFp + dFp.T), 0.5 * (dFp - dFp.T)
    si, sj = s[:, None], s[None, :]
    gi, gj = gs[:, None], gs[None, :]
    diff = si - sj
    # closer than eps^(1/3) (relative): the symmetrised limit below (error O(diff^2)) beats the quotient
    # (round-off error eps / diff); 6e-6 in fp64, 5e-3 in fp32
    close = jnp.abs(diff) <= jnp.finfo(F.dtype).eps ** (1.0 / 3.0) * jnp.maximum(jnp.abs(si), jnp.abs(sj))
    Jd = jnp.diag(Jg)
    limit = 0.5 * (Jd[:, None] - Jg + Jd[None, :] - Jg.T)  # lim (g_i - g_j)/(s_i - s_j) for isotropic g
    dd = jnp.where(close, limit, (gi - gj) / jnp.where(close, 1.0, diff))
    ssum = si + sj
    ok = jnp.abs(ssum) > 0.0
    num = (gj - gi) if left else (gi + gj)
    rot = jnp.where(ok, num / jnp.where(ok, ssum, 1.0), 0.0)
    eye = jnp.eye(s.shape[0], dtype=F.dtype)
    dGp = (1.0 - eye) * (sym * dd + skw * rot) + jnp.diag(Jg @ jnp.diag(dFp) + dg_p)
    return _scaled_product(U, gs, W), U @ dGp @ W.T


def safe_norm(x):
    """|x| with a zero (not NaN) gradient at x = 0."""
    sq = jnp.sum(x * x)
    pos = sq > 0.0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, sq, 1.0)), 0.0)


def inv_small(M):
    """M^-1 for batches of 2 x 2 or 3 x 3 matrices [..., D, D] by the adjugate over the determinant, in
    elementwise ``jnp``: no LAPACK custom call (with batched ``jnp.linalg.inv`` / ``solve`` the CPDI step of an
    80k-particle MLS run hung in XLA CPU's thread pool, twice in a row at the same point, and ran with this),
    and cheaper for tiny matrices; differentiable."""
    D = M.shape[-1]
    m = lambda i, j: M[..., i, j]                                    # noqa: E731
    if D == 2:
        det = m(0, 0) * m(1, 1) - m(0, 1) * m(1, 0)
        adj = _mat([[m(1, 1), -m(0, 1)], [-m(1, 0), m(0, 0)]])
    elif D == 3:
        c = lambda i, j: (m((i + 1) % 3, (j + 1) % 3) * m((i + 2) % 3, (j + 2) % 3)          # noqa: E731
                          - m((i + 1) % 3, (j + 2) % 3) * m((i + 2) % 3, (j + 1) % 3))        # cofactor C_ij
        adj = _mat([[c(j, i) for j in range(3)] for i in range(3)])                          # adj = C^T
        det = m(0, 0) * c(0, 0) + m(0, 1) * c(0, 1) + m(0, 2) * c(0, 2)
    else:
        raise ValueError(f"inv_small: {D} x {D} matrices; 2 x 2 or 3 x 3 only")
    return adj / det[..., None, None]
