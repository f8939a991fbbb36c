"""Warp per-particle linear algebra, built per (dim, precision)."""

from functools import lru_cache
from types import SimpleNamespace

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

    return SimpleNamespace(svd_rotations=svd_rotations, diag=diag, lame=lame, hencky_strain=hencky_strain,
                           identity=lambda: None)
