"""The Warp ``weights`` and ``hessian`` of a separable shape function from its 1-D formulas: every shape
whose weight is a product over axes of one 1-D function N(r), r = fx_d - k (in cells) for the node
offsets k = 0 .. width-1 (cubic B-spline, uGIMP). A new shape of that kind writes N, N' and N'' as
``@wp.func (r, lp) -> scalar`` (lp: the particle's half width in cells, unused by most) and returns
``separable(dim, precision, width, n, dn, ddn)`` from its ``warp.make``."""
from types import SimpleNamespace

import warp as wp

from ...backends.warp.types import warp_types


def separable(dim: int, precision: str, width: int, n, dn, ddn) -> SimpleNamespace:
    """``weights(fx, lp) -> (W, DW)`` and ``hessian(fx, lp) -> DDW``, each a ``width x dim`` matrix with
    [k, d] = N(fx_d - k), N'(fx_d - k), N''(fx_d - k); ``wmat`` is that matrix type."""
    T = warp_types(dim, precision)
    scalar, vec = T.scalar, T.vec
    wmat = wp.types.matrix((width, dim), scalar)
    offs = wp.types.vector(width, scalar)(*[float(k) for k in range(width)])   # (not offs[k] = k: Warp 1.19)

    @wp.func
    def weights(fx: vec, lp: scalar):
        W = wmat()
        DW = wmat()
        for d in range(dim):
            for k in range(width):
                r = fx[d] - offs[k]
                W[k, d] = n(r, lp)
                DW[k, d] = dn(r, lp)
        return W, DW

    @wp.func
    def hessian(fx: vec, lp: scalar):
        H = wmat()
        for d in range(dim):
            for k in range(width):
                H[k, d] = ddn(fx[d] - offs[k], lp)
        return H

    return SimpleNamespace(weights=weights, hessian=hessian, wmat=wmat)
