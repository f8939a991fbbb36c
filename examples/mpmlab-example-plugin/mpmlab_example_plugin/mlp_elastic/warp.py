"""Warp MLP hyperelastic law: the weights are ``wp.array`` members of the generated ``Weights`` struct,
one kernel argument read by every particle (their adjoints accumulate over the group)."""
from functools import lru_cache
from types import SimpleNamespace

import warp as wp

from mpmlab.backends.warp import law_types


@lru_cache(maxsize=None)
def make(law, dim: int, precision: str) -> SimpleNamespace:
    T = law_types(law, dim, precision)
    scalar, mat, LawState, Params, Weights = T.scalar, T.mat, T.LawState, T.Params, T.Weights
    fdim = float(dim)
    width = int(law.width)    # a compile-time constant: the loop is unrolled (Warp 1.19's adjoint of a
    #                           dynamic loop that accumulates into a scalar is wrong: measured 0.7 % on dtau/dF)

    @wp.func
    def kirchhoff(s: LawState, prm: Params, w: Weights):
        eye = wp.identity(dim, scalar)
        B = s.F @ wp.transpose(s.F)
        J = wp.determinant(s.F)
        z0 = wp.trace(B) - scalar(fdim)
        z1 = J - scalar(1.0)
        a = scalar(0.0)
        b = scalar(0.0)
        for i in range(wp.static(width)):
            h = wp.tanh(w.W1[i, 0] * z0 + w.W1[i, 1] * z1)
            a = a + w.W2[0, i] * h
            b = b + w.W2[1, i] * h
        return prm.stress_scale * ((w.c[0] + b) * (B - eye) + (w.c[1] * z1 + a) * eye)

    @wp.func
    def update(s: LawState, grad_v: mat, dt: scalar, prm: Params, w: Weights):
        out = s
        out.F = (wp.identity(dim, scalar) + dt * grad_v) @ s.F
        return out

    return SimpleNamespace(kirchhoff=kirchhoff, update=update)
