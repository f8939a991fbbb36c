"""Warp per-particle linear algebra, built per (dim, precision)."""
from __future__ import annotations

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
            wp.svd2(F, U, s, V)
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
