"""Warp per-particle linear algebra, built per (dim, precision)."""

from functools import lru_cache
from types import SimpleNamespace

import numpy as np
import warp as wp

from .types import warp_types

HENCKY_MIN_STRETCH = 1e-4  # same guard as mpmlab.laws._linalg_np


@lru_cache(maxsize=None)
def warp_linalg(dim: int, precision: str) -> SimpleNamespace:
    T = warp_types(dim, precision)
    scalar, vec, mat = T.scalar, T.vec, T.mat

    @wp.func
    def svd_rotations(F: mat):
        """F = U diag(s) V^T with U, V proper rotations; the last singular value carries det(F)'s sign."""
        U = mat()
        s = vec()
        V = mat()
        if wp.static(dim == 3):
            wp.svd3(F, U, s, V)
        else:
            # wp.svd2 loses U and V when the singular values are equal (F a scaled rotation, the rest state
            # of every rigid motion), so 2D uses the closed form: polar angle, then the symmetric eigenproblem.
            th = wp.atan2(F[1, 0] - F[0, 1], F[0, 0] + F[1, 1])
            R = mat(wp.cos(th), -wp.sin(th), wp.sin(th), wp.cos(th))
            Sm = wp.transpose(R) @ F
            phi = scalar(0.5) * wp.atan2(Sm[0, 1] + Sm[1, 0], Sm[0, 0] - Sm[1, 1])
            V = mat(wp.cos(phi), -wp.sin(phi), wp.sin(phi), wp.cos(phi))
            Dg = wp.transpose(V) @ Sm @ V
            s = vec(Dg[0, 0], Dg[1, 1])
            if wp.abs(s[0]) < wp.abs(s[1]):   # order by magnitude, as LAPACK does
                V = mat(-V[0, 1], V[0, 0], -V[1, 1], V[1, 0])
                s = vec(s[1], s[0])
            U = R @ V
            if s[0] < scalar(0.0):            # keep the sign on the last singular value
                s = -s
                U = -U
        if wp.determinant(U) < scalar(0.0):
            for i in range(dim):
                U[i, dim - 1] = -U[i, dim - 1]
            s[dim - 1] = -s[dim - 1]
        if wp.determinant(V) < scalar(0.0):
            for i in range(dim):
                V[i, dim - 1] = -V[i, dim - 1]
            s[dim - 1] = -s[dim - 1]
        return U, s, V

    @wp.func
    def diag(s: vec):
        D = mat()
        for i in range(dim):
            D[i, i] = s[i]
        return D

    @wp.func
    def lame(E: scalar, nu: scalar):
        return E / (scalar(2.0) * (scalar(1.0) + nu)), E * nu / ((scalar(1.0) + nu) * (scalar(1.0) - scalar(2.0) * nu))

    @wp.func
    def hencky_strain(F: mat):
        U, s, V = svd_rotations(F)
        eps = vec()
        for i in range(dim):
            eps[i] = wp.log(wp.max(s[i], scalar(HENCKY_MIN_STRETCH)))
        return U, eps, V

    @wp.func
    def svd_const(F: mat):
        """``svd_rotations`` without a derivative: spectral maps get theirs from ``spectral_func``."""
        U, s, V = svd_rotations(F)
        return U, s, V

    @wp.func_grad(svd_const)
    def adj_svd_const(F: mat, adj_U: mat, adj_s: vec, adj_V: mat):
        # Nothing flows back through U, s, V themselves (their derivatives blow up at repeated singular
        # values); values derived from s only choose branches (yield tests) or feed ``spectral_func``.
        return

    @wp.func
    def singular_values(F: mat):
        """The s of ``svd_rotations`` with its derivative ds_i = (U^T dF V)_ii, finite at repeated
        singular values (for laws whose state depends on principal stretches, e.g. a hardening variable)."""
        U, s, V = svd_rotations(F)
        return s

    @wp.func_grad(singular_values)
    def adj_singular_values(F: mat, adj_ret: vec):
        U, s, V = svd_rotations(F)
        wp.adjoint[F] += U @ diag(adj_ret) @ wp.transpose(V)

    pv1 = wp.types.vector(1, scalar)
    polar_map = spectral_func(dim, precision, None, left=False, nparams=1, ones=True)

    @wp.func
    def polar(F: mat, U: mat, s: vec, V: mat):
        """U V^T, the rotation of F = R S (fixed corotated stress, the Drucker-Prager cone tip), for
        U, s, V = svd_const(F); its derivative is finite at F = I."""
        return polar_map(F, U, s, V, vec(), pv1())

    return SimpleNamespace(svd_rotations=svd_rotations, svd_const=svd_const, singular_values=singular_values,
                           diag=diag, lame=lame, hencky_strain=hencky_strain, polar=polar, identity=lambda: None)


def spectral_func(dim: int, precision: str, jac, left: bool, nparams: int, ones: bool = False):
    """A spectral map of F, U diag(g) W^T (W = U if ``left`` else V, F = U diag(s) V^T from
    ``svd_const``), with a hand-written adjoint that stays finite at repeated singular values.

    Called as ``spectral(F, U, s, V, g, pv)``: the caller computes g = g(s, pv) itself (so the forward
    arithmetic is exactly the inline U diag(g) W^T), and ``jac(s, g, pv) -> dg/ds [D, D]`` gives the
    Jacobian of its isotropic g. The adjoint is the transpose of the JAX custom JVP
    (``backends.jax.linalg.spectral``), so both backends take the same derivative: divided differences
    (g_i - g_j)/(s_i - s_j) off the diagonal, their symmetrised limit 0.5 (Jg_ii - Jg_ij + Jg_jj - Jg_ji)
    when s_i, s_j are closer than eps^(1/3) (relative), rotation terms (g_i +- g_j)/(s_i + s_j), and
    dg/ds on the diagonal; the parameters' part flows through g (the adjoint of g is diag(U^T G_bar W)).
    ``ones``: g = 1 (U W^T, no g or jac needed).
    """
    T = warp_types(dim, precision)
    scalar, vec, mat = T.scalar, T.vec, T.mat
    pvec = wp.types.vector(nparams, scalar)
    close_tol = float(np.finfo(np.float64 if precision == "fp64" else np.float32).eps ** (1.0 / 3.0))

    @wp.func
    def diag_(s: vec):
        D = mat()
        for i in range(dim):
            D[i, i] = s[i]
        return D

    @wp.func
    def spectral(F: mat, U: mat, s: vec, V: mat, g: vec, pv: pvec):
        if wp.static(ones):
            if wp.static(left):
                return U @ wp.transpose(U)
            else:
                return U @ wp.transpose(V)
        else:
            if wp.static(left):
                return U @ diag_(g) @ wp.transpose(U)
            else:
                return U @ diag_(g) @ wp.transpose(V)

    @wp.func_grad(spectral)
    def adj_spectral(F: mat, U: mat, s: vec, V: mat, g: vec, pv: pvec, adj_ret: mat):
        gs = g
        Jg = mat()
        if wp.static(ones):
            for i in range(dim):
                gs[i] = scalar(1.0)
        else:
            Jg = jac(s, g, pv)
        Gb = mat()
        if wp.static(left):
            Gb = wp.transpose(U) @ adj_ret @ U
        else:
            Gb = wp.transpose(U) @ adj_ret @ V
        A = mat()                       # adjoint of dFp = U^T dF V
        for i in range(dim):
            for j in range(dim):
                if i != j:
                    diff = s[i] - s[j]
                    dd = scalar(0.0)
                    if wp.abs(diff) <= scalar(close_tol) * wp.max(wp.abs(s[i]), wp.abs(s[j])):
                        dd = scalar(0.5) * (Jg[i, i] - Jg[i, j] + Jg[j, j] - Jg[j, i])
                    else:
                        dd = (gs[i] - gs[j]) / diff
                    ssum = s[i] + s[j]
                    rot = scalar(0.0)
                    if wp.abs(ssum) > scalar(0.0):
                        if wp.static(left):
                            rot = (gs[j] - gs[i]) / ssum
                        else:
                            rot = (gs[i] + gs[j]) / ssum
                    # dGp_ij = 0.5 (dFp_ij + dFp_ji) dd + 0.5 (dFp_ij - dFp_ji) rot
                    A[i, j] = A[i, j] + scalar(0.5) * Gb[i, j] * (dd + rot)
                    A[j, i] = A[j, i] + scalar(0.5) * Gb[i, j] * (dd - rot)
        ag = vec()
        for i in range(dim):
            for j in range(dim):
                A[j, j] = A[j, j] + Gb[i, i] * Jg[i, j]       # dGp_ii = sum_j Jg_ij dFp_jj + dg_i
            ag[i] = Gb[i, i]
        wp.adjoint[F] += U @ A @ wp.transpose(V)
        if wp.static(not ones):
            wp.adjoint[g] += ag

    return spectral
