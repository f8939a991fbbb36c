"""CPDI on Warp: the corner pseudo-particles' linear hat and the domain's corner signs, inertia and Cayley
update as ``@wp.func``s, the formulas of ``reference.py`` (the kernels' corner loops:
``backends/warp/kernels.py``, ``_p2g_kernel`` / ``_g2p_law_kernel`` with ``kind == "corners"``).

Why the corners are pseudo-particles: S_ip = 2^-D sum_c N_i(x_c) and grad S_ip = 2^-D sum_c N_i(x_c) R^-T s_c
are sums over the 2^D corners x_c = x_p + R s_c of one linear-hat window each, so P2G and G2P run the
ordinary window loop once per corner (weight 2^-D, its own base node and fx), and the weight gradient --
constant per corner -- folds into each corner's linear term: no weight-gradient lanes, no Hessian."""
from functools import lru_cache
from types import SimpleNamespace

import warp as wp

from ...backends.warp.types import warp_types


@lru_cache(maxsize=None)
def make(shape, dim: int, precision: str):
    """``weights(fx, lp) -> (W, DW)`` (the linear hat of one corner's window, 2 x dim; fx in [0, 1) per
    axis, lp unused), ``hessian`` (zeros), and the CPDI functions ``corner_sign(c) -> s_c`` (corner order of
    ``reference.signs``), ``inertia(x, R, origin, inv_dx, dx) -> D_p``, ``dinv(...)`` = D_p^-1,
    ``update_domain(R, L, dt)`` (Cayley), ``on_grid(x, R, ...)`` (every corner's window on the grid)."""
    T = warp_types(dim, precision)
    scalar, vec, mat = T.scalar, T.vec, T.mat
    wmat = wp.types.matrix((2, dim), scalar)
    NC = 2 ** dim
    INV_NC = 1.0 / NC           # a float constant (Warp 1.19: scalar(NC) would retype the int NC)

    @wp.func
    def weights(fx: vec, lp: scalar):
        """W[0, d] = 1 - fx_d, W[1, d] = fx_d; DW = -1, +1 (cells)."""
        W = wmat()
        DW = wmat()
        for d in range(dim):
            W[0, d] = scalar(1.0) - fx[d]
            W[1, d] = fx[d]
            DW[0, d] = scalar(-1.0)
            DW[1, d] = scalar(1.0)
        return W, DW

    @wp.func
    def hessian(fx: vec, lp: scalar):
        return wmat()

    @wp.func
    def corner_sign(c: int):
        """s_c in {-1, +1}^D, itertools.product((-1, 1), repeat=D) order: axis 0 varies slowest."""
        s = vec()
        for d in range(dim):
            b = (c >> (dim - 1 - d)) & 1
            s[d] = scalar(2 * b - 1)
        return s

    @wp.func
    def inertia(x: vec, R: mat, origin: vec, inv_dx: scalar, dx: scalar):
        """D_p = 2^-D sum_c dx^2 diag(f_c (1 - f_c)) + R R^T, f_c = x_c/dx - floor(x_c/dx) (``reference.inertia``;
        the floor's derivative is zero)."""
        acc = vec()
        for c in range(NC):
            Xc = (x + R @ corner_sign(c) - origin) * inv_dx
            f = vec()
            for d in range(dim):
                f[d] = Xc[d] - wp.floor(Xc[d])
            acc = acc + wp.cw_mul(f, vec(scalar(1.0)) - f)
        acc = acc * (dx * dx * scalar(INV_NC))
        return wp.diag(acc) + R @ wp.transpose(R)

    @wp.func
    def dinv(x: vec, R: mat, origin: vec, inv_dx: scalar, dx: scalar):
        """D_p^-1 (per particle, full matrix; the schemes' ``Dinv``)."""
        return wp.inverse(inertia(x, R, origin, inv_dx, dx))

    @wp.func
    def update_domain(R: mat, L: mat, dt: scalar):
        """R <- (I - dt/2 L)^-1 (I + dt/2 L) R (``reference.update_domain``)."""
        I = wp.identity(n=dim, dtype=scalar)
        h = scalar(0.5) * dt
        return wp.inverse(I - h * L) @ ((I + h * L) @ R)

    return SimpleNamespace(weights=weights, hessian=hessian, wmat=wmat, corner_sign=corner_sign, inertia=inertia,
                           dinv=dinv, update_domain=update_domain, NC=NC)
