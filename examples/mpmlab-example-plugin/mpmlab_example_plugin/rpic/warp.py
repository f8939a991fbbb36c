"""RPIC on Warp: the same math as ``jax.py`` as ``@wp.func``s (mpmlab's kernels close over them)."""
from functools import lru_cache
from types import SimpleNamespace

import warp as wp

from mpmlab.backends.warp.types import warp_types


@lru_cache(maxsize=None)       # one set of functions per (dim, precision): the kernels compile once
def funcs(dim: int, precision: str):
    T = warp_types(dim, precision)
    scalar, vec, mat = T.scalar, T.vec, T.mat

    @wp.func
    def p2g_momentum(m: scalar, V: scalar, v: vec, C: mat, tau: mat, dt: scalar, inv_dx: scalar,
                     Dinv: mat, tp: wp.array(dtype=scalar)):
        # G multiplies the weight gradient in cell units (dx grad w): hence the inv_dx
        return m * v, m * C, dt * (-(V * inv_dx) * tau)

    @wp.func
    def isotropic(Dinv: mat):
        """1 when D^-1 = c I (B-spline shapes), else 0 (uGIMP: per particle, diagonal, anisotropic)."""
        out = int(1)
        for i in range(dim):
            for j in range(dim):
                if i == j:
                    if Dinv[i, j] != Dinv[0, 0]:
                        out = 0
                elif Dinv[i, j] != scalar(0.0):
                    out = 0
        return out

    @wp.func
    def g2p(v: vec, vp: vec, vo: vec, B: mat, Gv: mat, fx: vec, inv_dx: scalar, Dinv: mat,
            tp: wp.array(dtype=scalar)):
        C = mat()
        if isotropic(Dinv) == 1:
            C = ((B - wp.outer(vp, fx)) @ Dinv) * (scalar(1.0) / inv_dx)     # B D^-1 (B in cells: times dx)
            C = scalar(0.5) * (C - wp.transpose(C))
        else:
            # omega = K^-1 axial(B), K = tr(D) I - D the inertia tensor (jax.py: rigid_C)
            Bl = (B - wp.outer(vp, fx)) * (scalar(1.0) / inv_dx)
            D = wp.inverse(Dinv)
            if wp.static(dim == 2):
                c = (Bl[1, 0] - Bl[0, 1]) / (D[0, 0] + D[1, 1])
                C = mat(scalar(0.0), -c, c, scalar(0.0))
            else:
                a = vec(Bl[2, 1] - Bl[1, 2], Bl[0, 2] - Bl[2, 0], Bl[1, 0] - Bl[0, 1])
                K = wp.identity(n=3, dtype=scalar) * wp.trace(D) - D
                w = wp.inverse(K) @ a
                C = mat(scalar(0.0), -w[2], w[1], w[2], scalar(0.0), -w[0], -w[1], w[0], scalar(0.0))
        return vp, C, Gv

    return SimpleNamespace(p2g_momentum=p2g_momentum, g2p=g2p)


def make(transfer, dim: int, precision: str):
    return funcs(dim, precision)
