"""A Warp law factory whose update writes a state field its law does not declare (tests/test_law_v2.py)."""
from types import SimpleNamespace

import warp as wp

from mpmlab.backends.warp import law_types


def make(law, dim, precision):
    T = law_types(law, dim, precision)
    LawState, Params, Weights, mat, scalar = T.LawState, T.Params, T.Weights, T.mat, T.scalar

    @wp.func
    def kirchhoff(s: LawState, prm: Params, w: Weights):
        return mat()

    @wp.func
    def update(s: LawState, grad_v: mat, dt: scalar, prm: Params, w: Weights):
        out = s
        out.q = scalar(1.0)
        return out

    return SimpleNamespace(kirchhoff=kirchhoff, update=update)
