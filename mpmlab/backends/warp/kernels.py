"""Warp kernel factories. Each factory is keyed by what changes the generated code -- dimension,
precision, the transfer scheme (its ``@wp.func``s and declarations, ``transfers.py``), the law --
and cached, so a kernel compiles once per process (and Warp's disk cache keeps it across processes).
Scene numbers (dx, dt, gravity, wall kinds, the FLIP ratio) are kernel arguments, so scenes that
differ only in numbers share compiled kernels.

Laws and transfer schemes enter only through kernels built from a closure over their ``@wp.func``s
(Warp's kernel-factory pattern; the kernels compile only the terms a scheme declares): the stepper's
G2P kernel is specialised per law and scheme and runs the law update in the same pass
(``g2p_law_kernel``), so P2G/G2P never branch on a law or a scheme. ``law_kernels`` keeps the
stand-alone update/stress kernels (initial stress, law conformance tests).
"""

from functools import lru_cache
from types import SimpleNamespace
from typing import Any

import warp as wp

from .law_structs import law_types
from .types import warp_types

WALL_NONE, WALL_STICKY, WALL_SLIP, WALL_SEPARATE = 0, 1, 2, 3
WALL_CODES = {"none": WALL_NONE, "sticky": WALL_STICKY, "slip": WALL_SLIP, "separate": WALL_SEPARATE}


def as_shape(shape=None):
    """The shape function instance a kernel factory is keyed by (None: the default quadratic B-spline)."""
    from ...shapes import make_shape

    return make_shape("quadratic" if shape is None else shape)


def stencil_funcs(dim: int, precision: str, shape=None):
    """The stencil of shape function ``shape`` (``mpmlab.shapes``; None: quadratic) as ``@wp.func``s:
    ``locate``, ``weights`` / ``hessian`` (the shape's own Warp functions), ``in_grid``, ``dinv``."""
    return _stencil_funcs(dim, precision, as_shape(shape))


@lru_cache(maxsize=None)
def _stencil_funcs(dim: int, precision: str, shape):
    T = warp_types(dim, precision)
    scalar, vec, mat, ivec = T.scalar, T.vec, T.mat, T.ivec
    shape.check()
    width = int(shape.width)
    offset = float(shape.offset)
    inv_D = shape.inv_D_cells
    inv_D_val = float(inv_D) if inv_D is not None else 0.0
    SF = shape.implementation("warp", "shape")(shape, dim, precision)
    wmat = wp.types.matrix((width, dim), scalar)
    # the node offsets 0 .. width-1 as scalars, a closure constant (Warp 1.19: ``scalar(i)`` of an unrolled
    # loop index turns the index itself into a float)
    OFFS = wp.types.vector(width, scalar)(*[float(k) for k in range(width)])

    @wp.func
    def locate(x: vec, origin: vec, inv_dx: scalar):
        """Base node (lower corner of the width^D window) and fx = x/dx - base per axis (in
        [offset, offset + 1))."""
        Xp = (x - origin) * inv_dx
        base = ivec()
        fx = vec()
        for d in range(dim):
            base[d] = int(wp.floor(Xp[d] - scalar(offset)))
            fx[d] = Xp[d] - scalar(base[d])
        return base, fx

    @wp.func
    def in_grid(x: vec, origin: vec, inv_dx: scalar, strides: ivec, G: int):
        """1 when the width^D window of a particle at x lies on the grid of G nodes (row-major ``strides``),
        else 0 -- also for a non-finite x. A particle that left the grid (a diverged run; the guard
        reports it by step, particle and field) must never make a kernel touch memory outside the grid:
        Warp's CPU kernels do not bounds-check (a 200 m/s particle segfaulted P2G), and a write wrapped
        into another grid row is never cleared and poisons later rollouts. Per axis, in float64, so a
        huge x cannot overflow the int index."""
        Xp = (x - origin) * inv_dx
        ok = int(1)
        for d in range(dim):
            n = G // strides[0]
            if d > 0:
                n = strides[d - 1] // strides[d]
            b = wp.float64(wp.floor(Xp[d] - scalar(offset)))
            if not (b >= wp.float64(0.0) and b + wp.float64(width - 1) < wp.float64(n)):
                ok = 0
        return ok

    @wp.func
    def dinv(W: wmat, fx: vec, inv_dx: scalar):
        """D_p^-1 (1/length^2), D_p = sum_i w_ip (x_i - x_p)(x_i - x_p)^T (Jiang et al. 2015): dx^2 /
        inv_D_cells I for B-splines; for the others diagonal from the particle's own weights,
        D_cells[d] = sum_k W[k, d] (k - fx_d)^2 (separable, linearly complete weights)."""
        if wp.static(inv_D is not None):
            return wp.identity(n=dim, dtype=scalar) * (scalar(inv_D_val) * inv_dx * inv_dx)
        else:
            M = mat()
            for d in range(dim):
                sd = scalar(0.0)
                for k in range(width):
                    r = OFFS[k] - fx[d]
                    sd = sd + W[k, d] * r * r
                M[d, d] = inv_dx * inv_dx / sd
            return M

    @wp.func
    def dinv_at(fx: vec, lp: scalar, inv_dx: scalar):
        """``dinv`` where the weights are not at hand (evaluates them only if D varies per particle)."""
        W = wmat()
        if wp.static(inv_D is None):
            W, DW = SF.weights(fx, lp)
        return dinv(W, fx, inv_dx)

    @wp.func
    def dinv_moved(xn: vec, origin: vec, inv_dx: scalar, lp: scalar):
        """G2P's D_p^-1: that of the position xn = x + dt v_pic the particle moves to, where the next P2G
        applies C = B D^-1 as C (x_i - xn) with the weights, and so the D_p, of xn -- the affine momentum it
        spreads is then exactly the B gathered (Jiang et al. 2015 store B and form C at P2G), and APIC /
        MLS conserve angular momentum to round-off with uGIMP too. Where D_p is constant (B-splines) this is
        ``dinv``'s constant, nothing evaluated. Differentiable in xn (the floor of its base has zero
        derivative)."""
        if wp.static(inv_D is None):
            bn, fxn = locate(xn, origin, inv_dx)
            return dinv_at(fxn, lp, inv_dx)
        else:
            return dinv(wmat(), vec(), inv_dx)

    corners = shape.kind == "corners"
    NC = int(SF.NC) if corners else 1

    @wp.func
    def on_grid(x: vec, R: mat, origin: vec, inv_dx: scalar, strides: ivec, G: int):
        """CPDI: 1 when the window of every corner x + R s_c of the particle's domain lies on the grid."""
        ok = int(1)
        if wp.static(corners):
            for c in range(NC):
                if in_grid(x + R @ SF.corner_sign(c), origin, inv_dx, strides, G) == 0:
                    ok = 0
        return ok

    return SimpleNamespace(locate=locate, weights=SF.weights, hessian=SF.hessian, wmat=wmat, in_grid=in_grid,
                           dinv=dinv, dinv_at=dinv_at, dinv_moved=dinv_moved, width=width, offset=offset, OFFS=OFFS,
                           uses_lp=bool(shape.uses_particle_size), shape=shape, corners=corners, NC=NC,
                           CP=SF if corners else None, on_grid=on_grid)


def grid_vec_type(dim: int, precision: str):
    """P2G accumulator per node: (momentum..., mass) in one vector, so a node's update touches one place."""
    return wp.types.vector(dim + 1, warp_types(dim, precision).scalar)


def p2g_kernel(dim: int, precision: str, tr, has_ext: bool, atomic: bool = False, shape=None):
    """P2G with shape function ``shape`` (None: quadratic); see ``_p2g_kernel``."""
    return _p2g_kernel(dim, precision, tr, bool(has_ext), bool(atomic), as_shape(shape))


@lru_cache(maxsize=None)
def _p2g_kernel(dim: int, precision: str, tr, has_ext: bool, atomic: bool, shape):
    """P2G of transfer scheme ``tr`` (a ``WarpTransfer``): mass, and per node o with weight w_o the
    scheme's momentum terms w_o (q + A (o - fx) dx) + G (dx grad w_o) and, for ``split_force`` schemes
    (FLIP needs the old grid velocity), its force terms w_o F (o - fx) dx + H (dx grad w_o) on a grid of
    their own. Only the terms the scheme declares are compiled; the per-particle terms come from the
    scheme's ``p2g_momentum`` / ``p2g_force`` before the stencil loop, which get the particle's D_p^-1 as
    ``Dinv`` (MLS: ``A = m C - dt V tau Dinv``, the mpm3d form for quadratic B-splines). External
    particle forces add dt f to q, or f to the force grid. The window is the shape function's
    (``stencil_funcs``: width^D nodes from ``floor(x/dx - offset)``); ``lp`` [N] is the particles' half
    width in cells, read only by shape functions that use it (``uses_particle_size``; else a dummy).

    CPDI (``kind == "corners"``, compiled in with ``wp.static``): the particle's domain R = ``domain[p]``
    gives 2^D corner pseudo-particles x_c = x_p + R s_c, each of weight 2^-D with the linear hat's window;
    the same window loop (``window``) runs once per corner (separable shapes: once, as before, the results
    bit-identical), the weight gradient folded into each corner's linear term (no gradient lanes):
    w_o (q + A (r_c - fx_c dx) + G dx R^-T s_c + sum_d o_d A[:, d] dx) / 2^D, mass m / 2^D, the force
    lanes likewise with (F, H) and the load. D_p^-1 is the inverse of ``cpdi.reference.inertia``. A
    particle with any corner off the grid contributes nothing; the bounding box covers every corner's base.

    Launched on a chunk of particles (``start``) into one private grid copy (``goff``), so chunks can run
    on different CPU threads (Warp's CPU atomics are plain adds); the copies are summed by the grid
    update. The loops over the width^D nodes are unrolled. Also records the chunk's bounding box of base
    nodes (``bbox[2 slot]``, ``bbox[2 slot + 1]``), so the grid update visits only nodes particles reach.

    ``atomic`` (CUDA, and the tape path): all particles run concurrently into one grid, so the node sums
    are atomic adds and no bounding box is kept (the grid update visits the whole grid). The plain
    read-add-write of the CPU form would be a data race there.
    """
    T = warp_types(dim, precision)
    S = _stencil_funcs(dim, precision, shape)
    scalar, vec, mat, ivec = T.scalar, T.vec, T.mat, T.ivec
    gvec = grid_vec_type(dim, precision)
    NW, OFFS = S.width, S.OFFS
    uses_lp = S.uses_lp
    F = tr.funcs
    split = tr.split_force
    m_affine = "affine" in tr.momentum_terms
    m_grad = "gradient" in tr.momentum_terms
    f_affine = split and "affine" in tr.force_terms
    f_grad = split and "gradient" in tr.force_terms
    any_grad = m_grad or f_grad                         # weight gradients needed at all
    ext_alone = has_ext and split and not (f_affine or f_grad)
    corners, NC, CP = S.corners, S.NC, S.CP             # CPDI: 2^D corner pseudo-particles (else one "corner")
    INV_NC = 1.0 / NC                                   # (a float constant: Warp 1.19's scalar(NC) retypes NC)

    @wp.func
    def ext4(a: vec, last: scalar):
        """(a, last) as a (dim+1)-vector: node updates then run as whole-vector (SIMD) operations."""
        if wp.static(dim == 3):
            return gvec(a[0], a[1], a[2], last)
        else:
            return gvec(a[0], a[1], last)

    @wp.func
    def add(a: wp.array(dtype=Any), i: int, val: Any):
        """a[i] += val: atomic on CUDA, a plain add into this thread's private copy on the CPU."""
        if wp.static(atomic):
            wp.atomic_add(a, i, val)
        else:
            a[i] = a[i] + val

    # the window loop's flags: a separable shape as before; CPDI's corners fold the weight-gradient terms
    # (and the external force) into their linear term, so no gradient lanes and the force always in the
    # f0 (+ offsets) form
    w_m_grad = m_grad and not corners
    w_f_grad = f_grad and not corners
    w_any_grad = w_m_grad or w_f_grad
    w_f_lin = split if corners else f_affine
    w_ext_alone = ext_alone and not corners

    @wp.func
    def window(grid_mm: wp.array(dtype=gvec), grid_f: wp.array(dtype=vec), nb: int, strides: ivec, W: S.wmat,
               DW: S.wmat, q4: gvec, a40: gvec, a41: gvec, a42: gvec, t40: gvec, t41: gvec, t42: gvec, f0: vec,
               Fd: mat, Fg: mat, fext: vec):
        """The width^D window from node ``nb``: per node o, w_o (q4 + sum_d o_d a4[d]) [+ sum_e (dx grad w_o)_e
        t4[e]] into ``grid_mm`` and the force terms into ``grid_f`` (one particle, or one CPDI corner)."""
        if wp.static(dim == 3):
            for i in range(NW):
                qi = q4
                if wp.static(m_affine):
                    qi = q4 + OFFS[i] * a40
                for j in range(NW):
                    wxy = W[i, 0] * W[j, 1]
                    qij = qi
                    if wp.static(m_affine):
                        qij = qi + OFFS[j] * a41
                    fij = f0 + OFFS[i] * Fd[0] + OFFS[j] * Fd[1]
                    nij = nb + i * strides[0] + j * strides[1]
                    for k in range(NW):
                        wgt = wxy * W[k, 2]
                        val = wgt * qij
                        if wp.static(m_affine):
                            val = wgt * (qij + OFFS[k] * a42)
                        if wp.static(w_any_grad):
                            g0 = DW[i, 0] * W[j, 1] * W[k, 2]
                            g1 = W[i, 0] * DW[j, 1] * W[k, 2]
                            g2 = wxy * DW[k, 2]
                            if wp.static(w_f_grad):
                                f = Fg @ vec(g0, g1, g2)
                                if wp.static(has_ext and not f_affine):
                                    f = f + wgt * fext
                                add(grid_f, nij + k, f)
                            if wp.static(w_m_grad):
                                val = val + g0 * t40 + g1 * t41 + g2 * t42
                        if wp.static(w_f_lin):
                            add(grid_f, nij + k, wgt * (fij + OFFS[k] * Fd[2]))
                        if wp.static(w_ext_alone):
                            add(grid_f, nij + k, wgt * fext)
                        add(grid_mm, nij + k, val)
        else:
            for i in range(NW):
                qi = q4
                if wp.static(m_affine):
                    qi = q4 + OFFS[i] * a40
                fi = f0 + OFFS[i] * Fd[0]
                ni = nb + i * strides[0]
                for j in range(NW):
                    wgt = W[i, 0] * W[j, 1]
                    val = wgt * qi
                    if wp.static(m_affine):
                        val = wgt * (qi + OFFS[j] * a41)
                    if wp.static(w_any_grad):
                        g0 = DW[i, 0] * W[j, 1]
                        g1 = W[i, 0] * DW[j, 1]
                        if wp.static(w_f_grad):
                            f = Fg @ vec(g0, g1)
                            if wp.static(has_ext and not f_affine):
                                f = f + wgt * fext
                            add(grid_f, ni + j, f)
                        if wp.static(w_m_grad):
                            val = val + g0 * t40 + g1 * t41
                    if wp.static(w_f_lin):
                        add(grid_f, ni + j, wgt * (fi + OFFS[j] * Fd[1]))
                    if wp.static(w_ext_alone):
                        add(grid_f, ni + j, wgt * fext)
                    add(grid_mm, ni + j, val)

    @wp.kernel(module="unique")
    def p2g(x: wp.array(dtype=vec), v: wp.array(dtype=vec), C: wp.array(dtype=mat), tau: wp.array(dtype=mat),
            mass: wp.array(dtype=scalar), vol: wp.array(dtype=scalar), ext: wp.array(dtype=vec),
            lp: wp.array(dtype=scalar), origin: vec, dx: scalar, dt: scalar, tp: wp.array(dtype=scalar), strides: ivec,
            start: int, goff: int, grid_mm: wp.array(dtype=gvec), grid_f: wp.array(dtype=vec),
            bbox: wp.array(dtype=ivec), slot: int, domain: wp.array(dtype=mat)):
        p = wp.tid() + start
        inv_dx = scalar(1.0) / dx
        base = ivec()
        fx = vec()
        W = S.wmat()
        DW = S.wmat()
        Dinv = mat()
        Rp = mat()
        lpv = scalar(0.0)
        if wp.static(corners):
            # CPDI: the particle's domain; off the grid if any corner's window is
            Rp = domain[p]
            if S.on_grid(x[p], Rp, origin, inv_dx, strides, grid_mm.shape[0] // (bbox.shape[0] // 2)) == 0:
                return
            Dinv = CP.dinv(x[p], Rp, origin, inv_dx, dx)
            if wp.static(not atomic):
                for c in range(NC):
                    bc, fc = S.locate(x[p] + Rp @ CP.corner_sign(c), origin, inv_dx)
                    bbox[2 * slot] = wp.min(bbox[2 * slot], bc)
                    bbox[2 * slot + 1] = wp.max(bbox[2 * slot + 1], bc)
        else:
            if S.in_grid(x[p], origin, inv_dx, strides, grid_mm.shape[0] // (bbox.shape[0] // 2)) == 0:
                return                 # off the grid: contributes nothing (G2P keeps it off; the guard names it)
            base, fx = S.locate(x[p], origin, inv_dx)
            if wp.static(uses_lp):
                lpv = lp[p]
            W, DW = S.weights(fx, lpv)
            Dinv = S.dinv(W, fx, inv_dx)
            if wp.static(not atomic):
                bbox[2 * slot] = wp.min(bbox[2 * slot], base)
                bbox[2 * slot + 1] = wp.max(bbox[2 * slot + 1], base)
        m = mass[p]
        V = vol[p]
        Cp = mat()
        if wp.static(tr.carries_C):
            Cp = C[p]
        q, A, Tg = F.p2g_momentum(m, V, v[p], Cp, tau[p], dt, inv_dx, Dinv, tp)
        Fm = mat()
        Fg = mat()
        if wp.static(split):
            Fm, Fg = F.p2g_force(m, V, v[p], Cp, tau[p], dt, inv_dx, Dinv, tp)
        fext = vec()
        if wp.static(has_ext):
            fext = ext[p]
            if wp.static(not split):
                q = q + dt * fext
        if wp.static(corners):
            # CPDI: each corner c is a pseudo-particle of weight 1/NC at x_c = x_p + r_c, r_c = R s_c, with
            # the linear hat's window: x_i - x_p = (x_i - x_c) + r_c adds A (r_c - fx_c dx) to its linear
            # term, and the gradient terms G (dx grad S_ip) = sum_c N_i(x_c) G (dx R^-T s_c) / NC fold in as
            # G g_c (cell units, g_c = dx R^-T s_c); the force lanes likewise with (F, H) and the load
            Rit = wp.transpose(wp.inverse(Rp))
            inv_nc = scalar(INV_NC)
            Ad = wp.transpose(A * dx) * inv_nc
            a40 = ext4(Ad[0], scalar(0.0))
            a41 = ext4(Ad[1], scalar(0.0))
            a42 = ext4(Ad[dim - 1], scalar(0.0))
            Fd = wp.transpose(Fm * dx) * inv_nc
            zero4 = ext4(vec(), scalar(0.0))
            for c in range(NC):
                sc = CP.corner_sign(c)
                rc = Rp @ sc
                bc, fc = S.locate(x[p] + rc, origin, inv_dx)
                Wc, DWc = S.weights(fc, scalar(0.0))
                gc = dx * (Rit @ sc)
                lin = q
                if wp.static(m_affine):
                    lin = lin + A @ (rc - fc * dx)
                if wp.static(m_grad):
                    lin = lin + Tg @ gc
                f0 = vec()
                if wp.static(split):
                    f0 = fext
                    if wp.static(f_affine):
                        f0 = f0 + Fm @ (rc - fc * dx)
                    if wp.static(f_grad):
                        f0 = f0 + Fg @ gc
                nbc = goff
                for d in range(dim):
                    nbc = nbc + bc[d] * strides[d]
                window(grid_mm, grid_f, nbc, strides, Wc, DWc, ext4(lin, m) * inv_nc, a40, a41, a42, zero4, zero4,
                       zero4, f0 * inv_nc, Fd, Fg, fext)
        else:
            # per node o, as (dim+1)-vectors: w_o (q4 + sum_d o_d a4[d]) [+ sum_e (dx grad w_o)_e t4[e]], where
            # q4 = (q - A fx dx, m), a4[d] = (A[:, d] dx, 0), t4[e] = (G[:, e], 0)
            q4 = ext4(q, m)
            if wp.static(m_affine):
                q4 = ext4(q - A @ (fx * dx), m)
            Ad = wp.transpose(A * dx)      # rows = columns of A dx
            Tt = wp.transpose(Tg)
            a40 = ext4(Ad[0], scalar(0.0))
            a41 = ext4(Ad[1], scalar(0.0))
            a42 = ext4(Ad[dim - 1], scalar(0.0))
            t40 = ext4(Tt[0], scalar(0.0))
            t41 = ext4(Tt[1], scalar(0.0))
            t42 = ext4(Tt[dim - 1], scalar(0.0))
            Fd = wp.transpose(Fm * dx)
            f0 = -(Fm @ (fx * dx))
            if wp.static(f_affine and has_ext):
                f0 = f0 + fext
            nb = goff
            for d in range(dim):
                nb = nb + base[d] * strides[d]
            window(grid_mm, grid_f, nb, strides, W, DW, q4, a40, a41, a42, t40, t41, t42, f0, Fd, Fg, fext)

    return p2g


@lru_cache(maxsize=None)
def wall_func(dim: int, precision: str):
    """Domain walls on one node's velocity: nodes within ``thickness`` of a face get that face's kind
    (``WALL_CODES``: 1 sticky, 2 slip, 3 separate = only into the wall). Shared by the fast grid update and
    its tape-safe form (``grid_node_func``); the normal component is removed by subtracting it
    (``vn - vn[d] e_d``), not by overwriting it, because Warp 1.19's adjoint of a vector-component
    overwrite still passes the old value's gradient through."""
    T = warp_types(dim, precision)
    scalar, vec, ivec = T.scalar, T.vec, T.ivec

    @wp.func
    def axis(d: int):
        e = vec()
        e[d] = scalar(1.0)
        return e

    @wp.func
    def walls(vn: vec, I: ivec, shape: ivec, wall_kind: wp.array(dtype=int), thickness: int):
        out = vn
        for d in range(dim):
            cells = shape[d] - 1
            for side in range(2):
                kind = wall_kind[2 * d + side]
                near = False
                if side == 0:
                    near = I[d] < thickness
                else:
                    near = I[d] > cells - thickness
                if near and kind != 0:
                    if kind == 1:
                        out = vec()
                    else:
                        into = False
                        if side == 0:
                            into = out[d] < scalar(0.0)
                        else:
                            into = out[d] > scalar(0.0)
                        if kind == 2 or into:
                            out = out - out[d] * axis(d)
        return out

    return walls


@lru_cache(maxsize=None)
def grid_node_func(dim: int, precision: str, split_force: bool):
    """One node's velocity update (JAX-MPM Eqs. 13-14) and domain walls, shared by the fast grid update
    and the tape-safe one: ``(acc = (momentum, mass), force, dt, gravity, node index I, ...) -> (v_new,
    v_old)``. ``per_mass`` is q / m with the adjoint written with the quotient itself,
    d(q/m) = (dq - (q/m) dm) / m: Warp's -q dm / m^2 underflows at free-surface nodes reached only by a
    stencil's far tail (m ~ 1e-20 in fp32) and gives inf/NaN (as JAX's ``per_mass``)."""
    T = warp_types(dim, precision)
    scalar, vec, ivec = T.scalar, T.vec, T.ivec
    gvec = grid_vec_type(dim, precision)
    walls = wall_func(dim, precision)

    @wp.func
    def per_mass(q: vec, m: scalar):
        return q / m

    @wp.func_grad(per_mass)
    def adj_per_mass(q: vec, m: scalar, adj_ret: vec):
        v = q / m
        wp.adjoint[q] += adj_ret / m
        wp.adjoint[m] -= wp.dot(v, adj_ret) / m

    @wp.func
    def node(acc: gvec, fs: vec, dt: scalar, gravity: vec, I: ivec, shape: ivec, wall_kind: wp.array(dtype=int),
             thickness: int):
        m = acc[dim]
        vn = vec()
        vo = vec()
        if m > scalar(0.0):
            mv = vec()
            for d in range(dim):
                mv[d] = acc[d]
            vo = per_mass(mv, m)
            if wp.static(split_force):
                vn = vo + dt * (per_mass(fs, m) + gravity)
            else:
                vn = vo + dt * gravity
            vn = walls(vn, I, shape, wall_kind, thickness)
        return vn, vo

    return node


@lru_cache(maxsize=None)
def _grid_fast_node_func(dim: int, precision: str, split_force: bool):
    """The fast grid update of one node ``i`` (grid index ``I``): sums the ``copies`` private P2G grids,
    clears them for the next step (so no separate zeroing pass), updates the velocity (``grid_node_func``)
    and writes it. Shared by the box form and the listed form of the fast update."""
    T = warp_types(dim, precision)
    vec, ivec = T.vec, T.ivec
    scalar = T.scalar
    gvec = grid_vec_type(dim, precision)
    node = grid_node_func(dim, precision, split_force)

    @wp.func
    def fast_node(i: int, I: ivec, grid_mm: wp.array(dtype=gvec), grid_f: wp.array(dtype=vec), copies: int, G: int,
                  dt: scalar, gravity_v: vec, shape: ivec, wall_kind: wp.array(dtype=int), thickness: int,
                  grid_v: wp.array(dtype=vec), grid_v_old: wp.array(dtype=vec)):
        acc = grid_mm[i]
        grid_mm[i] = gvec()
        fs = vec()
        if wp.static(split_force):
            fs = grid_f[i]
            grid_f[i] = vec()
        for c in range(1, copies):
            acc = acc + grid_mm[c * G + i]
            grid_mm[c * G + i] = gvec()
            if wp.static(split_force):
                fs = fs + grid_f[c * G + i]
                grid_f[c * G + i] = vec()
        vn, vo = node(acc, fs, dt, gravity_v, I, shape, wall_kind, thickness)
        if wp.static(split_force):
            grid_v_old[i] = vo
        grid_v[i] = vn

    return fast_node


@lru_cache(maxsize=None)
def grid_update_kernel(dim: int, precision: str, split_force: bool, tape: bool = False):
    """Grid velocity update (JAX-MPM Eqs. 13-14) fused with the domain walls (kinds are arguments), from
    one node function (``grid_node_func``) in two forms:

    * fast (``tape=False``): over the box ``lo + [0, ext)`` of nodes (the nodes particles reached this
      step), ``_grid_fast_node_func``: sums the ``copies`` private P2G grids and clears them; gravity is
      ``gravity_v``;
    * tape-safe (``tape=True``): over every node, reads one grid and writes fresh outputs (clearing
      what it reads is what a tape cannot replay); gravity is the differentiable ``gravity[0]``.

    ``grid_update_listed_kernel`` is the fast form over a list of nodes (a compact node set).

    Warp pitfall: in a differentiated kernel never overwrite a vector component that depends on the
    inputs (``v[d] = 0``): Warp 1.19 still routes the old value's adjoint through. Build new vectors.
    """
    T = warp_types(dim, precision)
    scalar, vec, ivec = T.scalar, T.vec, T.ivec
    gvec = grid_vec_type(dim, precision)
    node = grid_node_func(dim, precision, split_force)
    fast_node = _grid_fast_node_func(dim, precision, split_force)

    @wp.kernel(module="unique")
    def grid_update(grid_mm: wp.array(dtype=gvec), grid_f: wp.array(dtype=vec), copies: int, G: int, start: int,
                    lo: ivec, ext: ivec, dt: scalar, gravity_v: vec, gravity: wp.array(dtype=vec), shape: ivec,
                    strides: ivec, wall_kind: wp.array(dtype=int), thickness: int,
                    grid_v: wp.array(dtype=vec), grid_v_old: wp.array(dtype=vec)):
        t = wp.tid() + start
        I = ivec()
        i = int(0)
        if wp.static(tape):
            i = t
            for d in range(dim):
                I[d] = (i // strides[d]) % shape[d]
            acc = grid_mm[i]
            fs = vec()
            if wp.static(split_force):
                fs = grid_f[i]
            vn, vo = node(acc, fs, dt, gravity[0], I, shape, wall_kind, thickness)
            if wp.static(split_force):
                if acc[dim] > scalar(0.0):
                    grid_v_old[i] = vo
            grid_v[i] = vn
        else:
            rem = t
            for e in range(dim):
                d = dim - 1 - e
                c = rem % ext[d]
                rem = rem // ext[d]
                I[d] = lo[d] + c
                i = i + I[d] * strides[d]
            fast_node(i, I, grid_mm, grid_f, copies, G, dt, gravity_v, shape, wall_kind, thickness, grid_v, grid_v_old)

    return grid_update


@lru_cache(maxsize=None)
def grid_update_listed_kernel(dim: int, precision: str, split_force: bool):
    """The fast grid update over the first ``count[0]`` entries of ``nodes`` (flat grid indices, each node
    once): a compact node set (``node_list.NodeList``), so the update costs what the list holds, not the
    reached nodes' bounding box. Launched over the list's capacity; the threads past the count return."""
    T = warp_types(dim, precision)
    scalar, vec, ivec = T.scalar, T.vec, T.ivec
    gvec = grid_vec_type(dim, precision)
    fast_node = _grid_fast_node_func(dim, precision, split_force)

    @wp.kernel(module="unique")
    def grid_update_listed(grid_mm: wp.array(dtype=gvec), grid_f: wp.array(dtype=vec), copies: int, G: int,
                           nodes: wp.array(dtype=int), count: wp.array(dtype=int), dt: scalar, gravity_v: vec,
                           shape: ivec, strides: ivec, wall_kind: wp.array(dtype=int), thickness: int,
                           grid_v: wp.array(dtype=vec), grid_v_old: wp.array(dtype=vec)):
        t = wp.tid()
        if t >= count[0]:
            return
        i = nodes[t]
        I = ivec()
        for d in range(dim):
            I[d] = (i // strides[d]) % shape[d]
        fast_node(i, I, grid_mm, grid_f, copies, G, dt, gravity_v, shape, wall_kind, thickness, grid_v, grid_v_old)

    return grid_update_listed


def law_module_options(impl) -> dict:
    """Warp module options a law's Warp implementation asks for its kernels (``impl.module_options``,
    e.g. CPU compiler flags for a compute-bound law); none by default."""
    return dict(getattr(impl, "module_options", None) or {})


def g2p_law_kernel(law, dim: int, precision: str, tr, shape=None):
    """G2P + law with shape function ``shape`` (None: quadratic); see ``_g2p_law_kernel``."""
    return _g2p_law_kernel(law, dim, precision, tr, as_shape(shape))


@lru_cache(maxsize=None)
def _g2p_law_kernel(law, dim: int, precision: str, tr, shape):
    """G2P of transfer scheme ``tr`` (a ``WarpTransfer``) fused with the law update of one material
    group (a closure over the scheme's and the law's ``@wp.func``s).

    Gathers the shape function's width^D window with separable partial sums (z lines first) -- v_pic = sum w v_i and the
    moments the scheme declares (``first``: B = sum w v_i o^T; ``gradient``: sum v_i (grad w)^T; the
    old grid velocity for ``split_force``) -- lets the scheme's ``g2p`` turn them into (v, C, grad_v) (with the particle's D_p^-1 as ``Dinv``),
    writes x (moved with v_pic, JAX-MPM Eq. 17), v, C, then feeds the velocity gradient straight into
    the law's ``update`` and stores the new law state and its Kirchhoff stress, so the velocity gradient
    never goes through memory. Launched on a chunk ``start`` of the group that begins at particle ``goff``.

    CPDI (``kind == "corners"``): the same gather (``gather``) per corner of the domain ``domain[p]``; v_pic
    = mean_c v_c, B = mean_c [(B_c - v_c fx_c^T) + v_c (r_c / dx)^T] (the first moment about x_p, so the
    scheme reads it with fx = 0), grad v = mean_c v_c (R^-T s_c)^T (always: it is the scheme's ``Gv`` and
    the domain's Cayley update ``domain_out = (I - dt/2 L)^-1 (I + dt/2 L) R``), D_p^-1 of the moved
    position and domain. Off the grid (any corner): ballistic, the domain kept. Other shapes get one-entry
    dummies for ``domain`` / ``domain_out``.
    """
    T = warp_types(dim, precision)
    S = _stencil_funcs(dim, precision, shape)
    NW, OFFS = S.width, S.OFFS
    uses_lp = S.uses_lp
    L = law_types(law, dim, precision)
    scalar, vec, mat, ivec = T.scalar, T.vec, T.mat, T.ivec
    need_grad = "gradient" in tr.moments
    apic = "first" in tr.moments          # the first moment (APIC's B)
    flip = tr.split_force
    F = tr.funcs
    impl = law.implementation("warp", "law")(law, dim, precision)

    @wp.func
    def cols(a: vec, b: vec, c: vec):
        if wp.static(dim == 3):
            return wp.matrix_from_cols(a, b, c)
        else:
            return wp.matrix_from_cols(a, b)

    corners, NC, CP = S.corners, S.NC, S.CP             # CPDI: 2^D corner pseudo-particles (else one "corner")
    INV_NC = 1.0 / NC                                   # (a float constant: Warp 1.19's scalar(NC) retypes NC)
    g_need_grad = need_grad and not corners             # CPDI: grad v from the corners' sums, not the weights'

    @wp.func
    def gather(grid_v: wp.array(dtype=vec), grid_v_old: wp.array(dtype=vec), nb: int, strides: ivec, W: S.wmat,
               DW: S.wmat):
        """The width^D window from node ``nb`` (one particle, or one CPDI corner): (sum w v_i, sum w v_old_i,
        sum v_i (grad w)_d for d = 0, 1, 2 (cells), sum w v_i o_d for d = 0, 1, 2), the declared ones only."""
        vp = vec()
        vo = vec()
        G0 = vec(); G1 = vec(); G2 = vec()     # sum_i v_i (grad w_i)_d, d = 0, 1, 2
        B0 = vec(); B1 = vec(); B2 = vec()     # sum_i w_i v_i o_d
        if wp.static(dim == 3):
            for i in range(NW):
                sy = vec(); sdy = vec(); syd = vec(); jy = vec(); kz = vec(); oy = vec()
                for j in range(NW):
                    s = vec(); sd = vec(); st = vec(); so = vec()
                    nij = nb + i * strides[0] + j * strides[1]
                    for k in range(NW):
                        g = grid_v[nij + k]
                        s = s + W[k, 2] * g
                        if wp.static(g_need_grad):
                            sd = sd + DW[k, 2] * g
                        if wp.static(apic):
                            st = st + (OFFS[k] * W[k, 2]) * g
                        if wp.static(flip):
                            so = so + W[k, 2] * grid_v_old[nij + k]
                    wy = W[j, 1]
                    sy = sy + wy * s
                    if wp.static(g_need_grad):
                        sdy = sdy + DW[j, 1] * s
                        syd = syd + wy * sd
                    if wp.static(apic):
                        jy = jy + (OFFS[j] * wy) * s
                        kz = kz + wy * st
                    if wp.static(flip):
                        oy = oy + wy * so
                wx = W[i, 0]
                vp = vp + wx * sy
                if wp.static(g_need_grad):
                    G0 = G0 + DW[i, 0] * sy
                    G1 = G1 + wx * sdy
                    G2 = G2 + wx * syd
                if wp.static(apic):
                    B0 = B0 + (OFFS[i] * wx) * sy
                    B1 = B1 + wx * jy
                    B2 = B2 + wx * kz
                if wp.static(flip):
                    vo = vo + wx * oy
        else:
            for i in range(NW):
                s = vec(); sd = vec(); st = vec(); so = vec()
                ni = nb + i * strides[0]
                for j in range(NW):
                    g = grid_v[ni + j]
                    s = s + W[j, 1] * g
                    if wp.static(g_need_grad):
                        sd = sd + DW[j, 1] * g
                    if wp.static(apic):
                        st = st + (OFFS[j] * W[j, 1]) * g
                    if wp.static(flip):
                        so = so + W[j, 1] * grid_v_old[ni + j]
                wx = W[i, 0]
                vp = vp + wx * s
                if wp.static(g_need_grad):
                    G0 = G0 + DW[i, 0] * s
                    G1 = G1 + wx * sd
                if wp.static(apic):
                    B0 = B0 + (OFFS[i] * wx) * s
                    B1 = B1 + wx * st
                if wp.static(flip):
                    vo = vo + wx * so
        return vp, vo, G0, G1, G2, B0, B1, B2

    @wp.kernel(module="unique", module_options=law_module_options(impl))
    def g2p(x: wp.array(dtype=vec), v: wp.array(dtype=vec), grid_v: wp.array(dtype=vec),
            grid_v_old: wp.array(dtype=vec), origin: vec, dx: scalar, dt: scalar, strides: ivec,
            tp: wp.array(dtype=scalar), lp: wp.array(dtype=scalar), goff: int, start: int,
            state: L.StateArrays, prm: wp.array2d(dtype=scalar), w: L.Weights,
            x_out: wp.array(dtype=vec), v_out: wp.array(dtype=vec), C_out: wp.array(dtype=mat),
            state_out: L.StateArrays, tau: wp.array(dtype=mat),
            domain: wp.array(dtype=mat), domain_out: wp.array(dtype=mat)):
        q = wp.tid() + start
        p = goff + q
        inv_dx = scalar(1.0) / dx
        xp = x[p]
        Rp = mat()
        ok = int(0)
        if wp.static(corners):
            Rp = domain[p]
            ok = S.on_grid(xp, Rp, origin, inv_dx, strides, grid_v.shape[0])
        else:
            ok = S.in_grid(xp, origin, inv_dx, strides, grid_v.shape[0])
        if ok == 0:
            # off the grid: moves on ballistically, outside the domain, so the guard reports it; its law
            # state is carried over unchanged (the output buffers are uninitialised memory: leaving them
            # unwritten made the guard report garbage F, or a NaN, instead of the particle leaving); a
            # CPDI particle keeps its domain
            x_out[p] = xp + dt * v[p]
            v_out[p] = v[p]
            if wp.static(corners):
                domain_out[p] = Rp
            P0 = L.load_params(prm, q)
            s0 = L.load_state(state, q)
            L.store_state(state_out, q, s0)
            tau[p] = impl.kirchhoff(s0, P0, w)
            return
        fx = vec()
        vp = vec()
        vo = vec()
        Gv = mat()
        B = mat()
        Dinv = mat()
        lpv = scalar(0.0)
        if wp.static(corners):
            # CPDI: each corner's window gathered as a pseudo-particle of weight 1/NC; B about the particle
            # (x_i - x_p = (x_i - x_c) + r_c) read with fx = 0, grad v = sum_c v_c (R^-T s_c)^T / NC (physical
            # units; always: the domain's Cayley update needs it)
            Rit = wp.transpose(wp.inverse(Rp))
            for c in range(NC):
                sc = CP.corner_sign(c)
                rc = Rp @ sc
                bc, fc = S.locate(xp + rc, origin, inv_dx)
                Wc, DWc = S.weights(fc, scalar(0.0))
                nbc = int(0)
                for d in range(dim):
                    nbc = nbc + bc[d] * strides[d]
                vc, voc, H0, H1, H2, C0, C1, C2 = gather(grid_v, grid_v_old, nbc, strides, Wc, DWc)
                vp = vp + vc
                Gv = Gv + wp.outer(vc, Rit @ sc)
                if wp.static(apic):
                    B = B + cols(C0, C1, C2) + wp.outer(vc, rc * inv_dx - fc)
                if wp.static(flip):
                    vo = vo + voc
            inv_nc = scalar(INV_NC)
            vp = vp * inv_nc
            vo = vo * inv_nc
            Gv = Gv * inv_nc
            B = B * inv_nc
        else:
            base, fxp = S.locate(xp, origin, inv_dx)
            fx = fxp
            if wp.static(uses_lp):
                lpv = lp[p]
            W, DW = S.weights(fx, lpv)
            nb = int(0)
            for d in range(dim):
                nb = nb + base[d] * strides[d]
            vp0, vo0, G0, G1, G2, B0, B1, B2 = gather(grid_v, grid_v_old, nb, strides, W, DW)
            vp = vp0
            vo = vo0
            if wp.static(need_grad):
                Gv = inv_dx * cols(G0, G1, G2)                                      # JAX-MPM Eq. 18
            if wp.static(apic):
                B = cols(B0, B1, B2)
        xn = xp + dt * vp                                                            # JAX-MPM Eq. 17
        if wp.static(corners):
            Rn = CP.update_domain(Rp, Gv, dt)                                        # Cayley (reference.py)
            domain_out[p] = Rn
            Dinv = CP.dinv(xn, Rn, origin, inv_dx, dx)                               # D_p^-1 at (xn, Rn)
        else:
            Dinv = S.dinv_moved(xn, origin, inv_dx, lpv)                             # D_p^-1 of xn (the next P2G's)
        vnew, Cn, grad_v = F.g2p(v[p], vp, vo, B, Gv, fx, inv_dx, Dinv, tp)
        v_out[p] = vnew
        x_out[p] = xn
        if wp.static(tr.carries_C):
            C_out[p] = Cn
        # law update of this particle's material (state and parameters by name: law_types.py)
        P = L.load_params(prm, q)
        n = impl.update(L.load_state(state, q), grad_v, dt, P, w)
        L.store_state(state_out, q, n)
        tau[p] = impl.kirchhoff(n, P, w)

    return g2p


@lru_cache(maxsize=None)
def law_kernels(law, dim: int, precision: str):
    """Per-law kernels from a closure over the law's ``@wp.func``s: ``update`` (state + stress) and
    ``stress`` (stress only, used at init and in conformance tests)."""
    T = warp_types(dim, precision)
    L = law_types(law, dim, precision)
    scalar, mat = T.scalar, T.mat
    impl = law.implementation("warp", "law")(law, dim, precision)

    @wp.kernel(module="unique", module_options=law_module_options(impl))
    def update(state: L.StateArrays, grad_v: wp.array(dtype=mat), prm: wp.array2d(dtype=scalar), w: L.Weights,
               dt: scalar, offset: int, state_out: L.StateArrays, tau: wp.array(dtype=mat)):
        q = wp.tid()
        P = L.load_params(prm, q)
        n = impl.update(L.load_state(state, q), grad_v[offset + q], dt, P, w)
        L.store_state(state_out, q, n)
        tau[offset + q] = impl.kirchhoff(n, P, w)

    @wp.kernel(module="unique", module_options=law_module_options(impl))
    def stress(state: L.StateArrays, prm: wp.array2d(dtype=scalar), w: L.Weights, offset: int,
               tau: wp.array(dtype=mat)):
        q = wp.tid()
        tau[offset + q] = impl.kirchhoff(L.load_state(state, q), L.load_params(prm, q), w)

    return SimpleNamespace(update=update, stress=stress, types=L)


@lru_cache(maxsize=None)
def guard_kernel(dim: int, precision: str):
    """Sets flag[0] = 1 if any position/velocity is non-finite or outside [lo, hi)."""
    vec = warp_types(dim, precision).vec

    @wp.kernel(module="unique")
    def guard(x: wp.array(dtype=vec), v: wp.array(dtype=vec), lo: vec, hi: vec, flag: wp.array(dtype=int)):
        p = wp.tid()
        bad = False
        for d in range(dim):
            a = x[p][d]
            b = v[p][d]
            if not (wp.isfinite(a) and wp.isfinite(b)):
                bad = True
            if a < lo[d] or a >= hi[d]:
                bad = True
        if bad:
            flag[0] = 1

    return guard


@lru_cache(maxsize=None)
def corner_guard_kernel(dim: int, precision: str):
    """CPDI: sets flag[0] = 1 if a particle's domain is non-finite or one of its corners x + R s_c lies
    outside [lo, hi) (``shapes.inner_bounds``: the corners' windows stay on the grid)."""
    from ...shapes import make_shape

    T = warp_types(dim, precision)
    vec, mat = T.vec, T.mat
    CP = make_shape("cpdi").implementation("warp", "shape")(make_shape("cpdi"), dim, precision)

    @wp.kernel(module="unique")
    def guard(x: wp.array(dtype=vec), domain: wp.array(dtype=mat), lo: vec, hi: vec, flag: wp.array(dtype=int)):
        p = wp.tid()
        bad = False
        R = domain[p]
        for i in range(dim):
            for j in range(dim):
                if not wp.isfinite(R[i, j]):
                    bad = True
        for c in range(CP.NC):
            xc = x[p] + R @ CP.corner_sign(c)
            for d in range(dim):
                if xc[d] < lo[d] or xc[d] >= hi[d]:
                    bad = True
        if bad:
            flag[0] = 1

    return guard


@lru_cache(maxsize=None)
def law_guard_kernel(dim: int, precision: str, shape: tuple, check: str | None):
    """Sets flag[0] = 1 if a law state entry (of per-particle ``shape``) is non-finite, or fails its
    declared ``check`` (``positive``: a scalar <= 0; ``positive_det``: a matrix with det <= 0)."""
    from .law_structs import field_dtype

    T = warp_types(dim, precision)
    scalar = T.scalar
    dtype = field_dtype(T, tuple(shape))
    is_mat = len(shape) == 2
    is_vec = len(shape) == 1
    rows = shape[0] if shape else 1
    cols_ = shape[1] if is_mat else 1
    check_j = check is not None

    @wp.kernel(module="unique")
    def guard(a: wp.array(dtype=dtype), flag: wp.array(dtype=int)):
        q = wp.tid()
        bad = False
        if wp.static(is_mat):
            for i in range(rows):
                for j in range(cols_):
                    if not wp.isfinite(a[q][i, j]):
                        bad = True
            if wp.static(check_j):
                if not (wp.determinant(a[q]) > scalar(0.0)):
                    bad = True
        elif wp.static(is_vec):
            for i in range(rows):
                if not wp.isfinite(a[q][i]):
                    bad = True
        else:
            if not wp.isfinite(a[q]):
                bad = True
            if wp.static(check_j):
                if not (a[q] > scalar(0.0)):
                    bad = True
        if bad:
            flag[0] = 1

    return guard
