"""Hand-written adjoints of the gradient path's transfer kernels (issue 17, item 1, Warp half).

Warp's generated adjoint of a kernel replays the whole forward body (every stencil node, every
intermediate kept as an SSA value), zero-initialises one adjoint variable per SSA value of the
unrolled width^D loop, then runs the reverse sweep and adds each array read's adjoint back with an
atomic add. For P2G that is the forward once more plus a reverse sweep about twice its size
(``benchmarks/_adjoint_split_warp.py`` measures it: 3.2x the forward before this module).

P2G's transpose is a *gather*: its inputs are per particle and its outputs are grid arrays, so the
adjoint of a particle's inputs reads the adjoints of the width^D nodes it wrote and accumulates into
that particle's own entries -- no atomics, no replay of the scatter. It is split in two kernels:

* ``stencil`` (hand-written): per particle, the adjoints of the per-particle P2G terms the stencil
  loop consumes -- the transfer's momentum terms (q, A, Tg) and force terms (Fm, Fg) of
  ``kernels.p2g_kernel``, the mass, the external force -- and of the position through the weights
  (their first and second derivatives: the gradient term w_o' enters the forward, so its
  derivative needs the Hessian of w_o);
* ``terms`` (generated adjoint of a per-particle kernel that only evaluates the transfer's
  ``p2g_momentum`` / ``p2g_force``): maps those adjoints to v, C, tau, mass and volume. It replays
  only those few per-particle operations, so any transfer (plug-ins included) keeps its own
  ``@wp.func``s and needs no hand-written derivative.

Equations (JAX-MPM Eqs. 9-12 in the form of ``kernels.p2g_kernel``): node o with weight w_o(fx),
weight gradient g_o = dw_o/dfx (cell units), fx = (x - origin)/dx - base,

    mm_o   += (w_o (q + A (o - fx) dx) + Tg g_o,  w_o m)
    f_o    += Fg g_o + w_o (Fm (o - fx) dx + fext)            (split-force schemes)

so, with the node adjoints (a_q, a_m) = adj mm_o and a_f = adj f_o,

    adj q   = sum_o w_o a_q                 adj A  = sum_o w_o a_q (o - fx)^T dx
    adj Tg  = sum_o a_q g_o^T               adj m += sum_o w_o a_m
    adj fx  = sum_o g_o (a_q . (q + A (o - fx) dx) + a_m m) - w_o dx A^T a_q + H_o Tg^T a_q  (+ force)
    adj x  += adj fx / dx                   (the floor in base has zero derivative)

with H_o the Hessian of w_o (the shape function's ``hessian``: the quadratic B-spline's second derivatives
1, -2, 1; the cubic's and uGIMP's piecewise). The window (width^D nodes from ``floor(x/dx - offset)``)
is the shape function's (``kernels.stencil_funcs``). Where the scheme reads D_p^-1 (``Dinv``) and it
varies with the position (uGIMP), its derivative is Warp's generated adjoint of the kernel body: in P2G
of x_p, in G2P of x_p + dt v_pic (``dinv_moved``), whose v_pic adjoint joins the gather's (``adj_gather``).

Both adjoints evaluate their stencil sums separably (``_separable``): every sum above is sum_o f(o) y_o
with f a product of per-axis factors (w, o w, w', o w', w''), so it is summed one axis at a time, as
G2P's forward gathers, instead of forming w_o, g_o, H_o and their outer products at each node; G2P's
transpose at the nodes factors the same way. Warp's CPU code is scalar, so the flops are the cost:
the 3D P2G adjoint went from 4.2x to 2.3x its forward, and a node's values are read component by
component (a runtime-indexed loop over a vector's components kept it in memory: 1.8x slower). G2P's
adjoint kernel replays G2P's gather with the same sums (``"gather"``), as the forward kernel gathers.
Measured by ``benchmarks/_adjoint_split_warp.py`` (``benchmarks/README.md``, issue 17).
"""

from functools import lru_cache
from types import SimpleNamespace

import warp as wp

from . import kernels as K
from .types import warp_types


def p2g_adjoint_kernels(dim: int, precision: str, tr, has_ext: bool, shape=None):
    """P2G's adjoint with shape function ``shape`` (None: quadratic); see ``_p2g_adjoint_kernels``."""
    return _p2g_adjoint_kernels(dim, precision, tr, bool(has_ext), K.as_shape(shape))


@lru_cache(maxsize=None)
def _p2g_adjoint_kernels(dim: int, precision: str, tr, has_ext: bool, shape):
    """P2G's adjoint for transfer ``tr`` (a ``WarpTransfer``) as one kernel, ``adjoint``, launched in
    Warp's adjoint mode: per particle it evaluates the transfer's per-particle terms (q, A, Tg; Fm, Fg)
    and hands them to ``pairing``, a function whose forward is 0 and whose hand-written gradient
    (``wp.func_grad``) gathers the node adjoints of the width^D stencil and returns the adjoints of those
    terms, of the mass, the external force and the position. Warp's generated code then carries the
    terms' adjoints through the transfer's own ``p2g_momentum`` / ``p2g_force`` (a replay of those few
    per-particle operations only) into v, C, tau, mass, volume. The forward is
    ``kernels.p2g_kernel(dim, precision, tr, has_ext, atomic=True, shape=shape)``; launch ``adjoint`` with
    ``adj_outputs=[ones]``. The particle's ``Dinv`` is computed in the kernel body (differentiable: for
    uGIMP it depends on the position), the window's weights and their derivatives in ``pairing``."""
    T = warp_types(dim, precision)
    S = K._stencil_funcs(dim, precision, shape)
    NW, OFFS = S.width, S.OFFS
    uses_lp = S.uses_lp
    scalar, vec, mat, ivec = T.scalar, T.vec, T.mat, T.ivec
    gvec = K.grid_vec_type(dim, precision)
    F = tr.funcs
    split = tr.split_force
    m_affine = "affine" in tr.momentum_terms
    m_grad = "gradient" in tr.momentum_terms
    f_affine = split and "affine" in tr.force_terms
    f_grad = split and "gradient" in tr.force_terms
    ext_alone = has_ext and split and not (f_affine or f_grad)
    ext_grad = has_ext and f_grad and not f_affine      # f_grad's node term carries w fext
    ext_affine = has_ext and f_affine                   # f_affine's node term carries w fext
    any_grad = m_grad or f_grad
    carries_C = tr.carries_C

    SEP = _separable(dim, precision, shape, "p2g", split, m_affine or f_affine, any_grad)

    @wp.func
    def pairing(x: vec, q: vec, A: mat, Tg: mat, Fm: mat, Fg: mat, m: scalar, fext: vec, lp: scalar, origin: vec,
                dx: scalar, strides: ivec, adj_mm: wp.array(dtype=gvec), adj_f: wp.array(dtype=vec)):
        """sum_o <adj node_o, P2G's contribution to node_o>, as far as the gradient is concerned: only its
        gradient (below) is ever evaluated, so the forward is a constant."""
        return scalar(0.0)

    @wp.func_grad(pairing)
    def adj_pairing(x: vec, q: vec, A: mat, Tg: mat, Fm: mat, Fg: mat, m: scalar, fext: vec, lp: scalar,
                    origin: vec, dx: scalar, strides: ivec, adj_mm: wp.array(dtype=gvec), adj_f: wp.array(dtype=vec),
                    adj_ret: scalar):
        inv_dx = scalar(1.0) / dx
        base, fx = S.locate(x, origin, inv_dx)
        W, DW = S.weights(fx, lp)
        DD = S.hessian(fx, lp)                                  # W'' per node and axis
        fxd = fx * dx
        nb = int(0)
        for d in range(dim):
            nb = nb + base[d] * strides[d]
        Sw, Swo, Sg, Sgo0, Sgo1, Sgo2, SH0, SH1, SH2 = SEP.sums(W, DW, DD, nb, strides, adj_mm, adj_f, adj_f, adj_f,
                                                               vec(), vec(), mat(), mat())
        # the sums of the node-wise code: s_q = sum w a_q, s_qo = sum w a_q o^T, s_T = sum a_q g^T, ...
        s_q = SEP.headv(Sw)
        s_m = Sw[dim]
        s_qo = SEP.head(Swo)
        s_T = SEP.head(Sg)
        s_f = SEP.tailv(Sw)
        s_fo = SEP.tail(Swo)
        s_Fg = SEP.tail(Sg)
        # adj fx_d = sum g_d (a_q . val + a_m m) + sum (H Tg^T a_q)_d (+ the force terms), val = q + A (o dx - fx dx)
        qc = q
        if wp.static(m_affine):
            qc = q - A @ fxd
        afx = wp.transpose(s_T) @ qc + m * SEP.mrow(Sg)
        if wp.static(m_affine):
            afx = afx + dx * SEP.head_ddots(A, Sgo0, Sgo1, Sgo2)
        if wp.static(m_grad):
            afx = afx + SEP.head_ddots(Tg, SH0, SH1, SH2)
        if wp.static(f_grad):
            afx = afx + SEP.tail_ddots(Fg, SH0, SH1, SH2)
        fc = vec()                       # the force's node value without its o-term (f_affine: Fm (o dx - fx dx))
        if wp.static(ext_grad or ext_alone):
            fc = fext
        if wp.static(f_affine):
            fc = -(Fm @ fxd)
            if wp.static(ext_affine):
                fc = fc + fext
            afx = afx + dx * SEP.tail_ddots(Fm, Sgo0, Sgo1, Sgo2)
        if wp.static(ext_grad or ext_alone or f_affine):
            afx = afx + wp.transpose(s_Fg) @ fc
        # the fx inside A (o - fx) dx: -dx A^T sum_o w_o a_q (likewise Fm)
        if wp.static(m_affine):
            afx = afx - dx * (wp.transpose(A) @ s_q)
            wp.adjoint[A] += adj_ret * ((s_qo - wp.outer(s_q, fx)) * dx)
        if wp.static(f_affine):
            afx = afx - dx * (wp.transpose(Fm) @ s_f)
            wp.adjoint[Fm] += adj_ret * ((s_fo - wp.outer(s_f, fx)) * dx)
        if wp.static(m_grad):
            wp.adjoint[Tg] += adj_ret * s_T
        if wp.static(f_grad):
            wp.adjoint[Fg] += adj_ret * s_Fg
        wp.adjoint[q] += adj_ret * s_q
        wp.adjoint[m] += adj_ret * s_m
        wp.adjoint[x] += adj_ret * (inv_dx * afx)                 # fx = (x - origin) / dx - floor(...)
        if wp.static(split):
            wp.adjoint[fext] += adj_ret * s_f

    @wp.kernel(module="unique")
    def adjoint(x: wp.array(dtype=vec), v: wp.array(dtype=vec), C: wp.array(dtype=mat), tau: wp.array(dtype=mat),
                mass: wp.array(dtype=scalar), vol: wp.array(dtype=scalar), ext: wp.array(dtype=vec),
                lp: wp.array(dtype=scalar), origin: vec, dx: scalar, dt: scalar, tp: wp.array(dtype=scalar),
                strides: ivec, adj_mm: wp.array(dtype=gvec), adj_f: wp.array(dtype=vec), out: wp.array(dtype=scalar)):
        """Run in adjoint mode only (adj out = 1): the forward value is 0."""
        p = wp.tid()
        inv_dx = scalar(1.0) / dx
        if S.in_grid(x[p], origin, inv_dx, strides, adj_mm.shape[0]) == 0:
            return                     # contributed nothing
        m = mass[p]
        lpv = scalar(0.0)
        if wp.static(uses_lp):
            lpv = lp[p]
        base, fx = S.locate(x[p], origin, inv_dx)
        Dinv = S.dinv_at(fx, lpv, inv_dx)          # differentiable here: uGIMP's depends on x
        Cp = mat()
        if wp.static(carries_C):
            Cp = C[p]
        q, A, Tg = F.p2g_momentum(m, vol[p], v[p], Cp, tau[p], dt, inv_dx, Dinv, tp)
        Fm = mat()
        Fg = mat()
        if wp.static(split):
            Fm, Fg = F.p2g_force(m, vol[p], v[p], Cp, tau[p], dt, inv_dx, Dinv, tp)
        fext = vec()
        if wp.static(has_ext):
            fext = ext[p]
            if wp.static(not split):
                q = q + dt * fext
        out[p] = pairing(x[p], q, A, Tg, Fm, Fg, m, fext, lpv, origin, dx, strides, adj_mm, adj_f)

    return SimpleNamespace(adjoint=adjoint)


# ---- separable stencil sums, shared by both adjoints ---------------------------------------------------
@lru_cache(maxsize=None)
def _separable(dim: int, precision: str, shape, kind: str, second: bool, need_o: bool, need_h: bool):
    """The stencil sums of both adjoints (and of the gather G2P's adjoint replays), sum_o f(o) y_o, with y_o
    a node's values and f a product of one per-axis factor of the kinds W (w), O (o w), D (w'), X (o w'), H (w'') --
    separable (tensor-product weights), so summed over the last axis first, then the next, as G2P's
    forward gathers, instead of forming w_o, g_o = grad w_o, H_o and their outer products at each node.

    ``kind`` "p2g": y_o = (a_q, a_m[, a_f]) from the node adjoints (src0 = adj mm, src1 = adj f, ``second``:
    split force); "g2p": y_o = (v_o[, v_old_o]) from the grid velocities (``second``: FLIP), and every
    node also gets G2P's transpose, w_o (a_vp + aB o) + aG g_o added to dst0 (and w_o a_vo to dst1);
    "gather": the same y_o, no transpose (G2P's own gather, replayed by its adjoint kernel).

    ``sums`` returns the families (NY = len(y); NY x D matrices, column e): Sw = sum w y (a vector; "p2g",
    "gather"), Swo[e] = sum w o_e y ("p2g", "gather"; ``need_o``), Sg[e] = sum g_e y, Sgo_d[e] = sum g_d o_e y
    (``need_o``), SH_d[e] = sum H_de y (``need_h``); unused ones are zero. ``head`` / ``tail`` / ``mrow`` cut a family's
    rows of y's first part (D x D), its second part (D x D) and, for "p2g", the mass row; ``headv`` /
    ``tailv`` the same of a vector."""
    T = warp_types(dim, precision)
    S = K._stencil_funcs(dim, precision, shape)
    NW, OFFS = S.width, S.OFFS
    scalar, vec, mat, ivec = T.scalar, T.vec, T.mat, T.ivec
    p2g = kind == "p2g"                                # y from the node adjoints (else from the grid velocities)
    need_w = kind in ("p2g", "gather")
    transpose = kind == "g2p"                          # G2P's transpose at the nodes
    src_t = K.grid_vec_type(dim, precision) if p2g else vec
    n0 = dim + 1 if p2g else dim                       # where y's second part starts
    NY = n0 + (dim if second else 0)
    yvec = wp.types.vector(NY, scalar)
    kmat = wp.types.matrix((NY, dim), scalar)
    wmat = S.wmat

    @wp.func
    def load(src0: wp.array(dtype=src_t), src1: wp.array(dtype=vec), n: int):
        """y_n, component by component (a runtime index would keep the vectors in memory: 1.8x slower)."""
        a = src0[n]
        if wp.static(second):
            f = src1[n]
            if wp.static(dim == 3 and p2g):
                return yvec(a[0], a[1], a[2], a[3], f[0], f[1], f[2])
            elif wp.static(dim == 3):
                return yvec(a[0], a[1], a[2], f[0], f[1], f[2])
            elif wp.static(p2g):
                return yvec(a[0], a[1], a[2], f[0], f[1])
            else:
                return yvec(a[0], a[1], f[0], f[1])
        else:
            if wp.static(dim == 3 and p2g):
                return yvec(a[0], a[1], a[2], a[3])
            elif wp.static(dim == 3):
                return yvec(a[0], a[1], a[2])
            elif wp.static(p2g):
                return yvec(a[0], a[1], a[2])
            else:
                return yvec(a[0], a[1])

    @wp.func
    def column(M: mat, e: int):
        if wp.static(dim == 3):
            return vec(M[0, e], M[1, e], M[2, e])
        else:
            return vec(M[0, e], M[1, e])

    # G2P's transpose at a node, ag_o = w_o (a_vp + aB o) + aG g_o, is separable too: with per-axis
    # e_d(k) = o_k W_k aB[:, d] + W'_k aG[:, d] and A(i) = W_i a_vp + e_0(i), in 3D
    # ag_ijk = W_k (W_j A(i) + W_i e_1(j)) + W_i W_j e_2(k): two vector FMAs per node instead of ~40 flops.
    emat = wp.types.matrix((NW, dim), scalar)

    @wp.func
    def axis_terms(W: wmat, DW: wmat, d: int, aB: mat, aG: mat):
        """e_d(k) for k = 0 .. width-1 (rows)."""
        E = emat()
        b = column(aB, d)
        g = column(aG, d)
        for k in range(NW):
            e = vec()
            if wp.static(need_o):
                e = e + (OFFS[k] * W[k, d]) * b
            if wp.static(need_h):
                e = e + DW[k, d] * g
            for c in range(dim):
                E[k, c] = e[c]
        return E

    @wp.func
    def row(E: emat, k: int):
        if wp.static(dim == 3):
            return vec(E[k, 0], E[k, 1], E[k, 2])
        else:
            return vec(E[k, 0], E[k, 1])

    @wp.func
    def scatter(dst0: wp.array(dtype=vec), dst1: wp.array(dtype=vec), n: int, ag: vec, w: scalar, a_vo: vec):
        """Adds at node n (atomic on CUDA; the CPU gradient path is single-threaded)."""
        wp.atomic_add(dst0, n, ag)
        if wp.static(second):
            wp.atomic_add(dst1, n, w * a_vo)

    @wp.func
    def kcols(a: yvec, b: yvec, c: yvec):
        """The NY x D matrix of columns a, b (, c)."""
        M = kmat()
        for r in range(NY):
            M[r, 0] = a[r]
            M[r, 1] = b[r]
            if wp.static(dim == 3):
                M[r, 2] = c[r]
        return M

    @wp.func
    def sums(W: wmat, DW: wmat, DD: wmat, nb: int, strides: ivec, src0: wp.array(dtype=src_t),
             src1: wp.array(dtype=vec), dst0: wp.array(dtype=vec), dst1: wp.array(dtype=vec), a_vp: vec, a_vo: vec,
             aB: mat, aG: mat):
        z = yvec()
        Sw = yvec()
        Swo = kmat()
        Sg = kmat()
        Sgo0 = kmat()
        Sgo1 = kmat()
        Sgo2 = kmat()
        SH0 = kmat()
        SH1 = kmat()
        SH2 = kmat()
        E0 = emat()
        E1 = emat()
        E2 = emat()
        if wp.static(transpose):
            E0 = axis_terms(W, DW, 0, aB, aG)
            E1 = axis_terms(W, DW, 1, aB, aG)
            if wp.static(dim == 3):
                E2 = axis_terms(W, DW, 2, aB, aG)
        if wp.static(dim == 3):
            for i in range(NW):
                tWW = yvec()
                tOW = yvec()
                tWO = yvec()
                tDW = yvec()
                tWD = yvec()
                tXW = yvec()
                tWX = yvec()
                tDO = yvec()
                tOD = yvec()
                tHW = yvec()
                tWH = yvec()
                tDD = yvec()
                for j in range(NW):
                    nij = nb + i * strides[0] + j * strides[1]
                    pW = yvec()
                    pO = yvec()
                    pD = yvec()
                    pX = yvec()
                    pH = yvec()
                    for k in range(NW):                               # axis 2
                        y = load(src0, src1, nij + k)
                        pW = pW + W[k, 2] * y
                        pD = pD + DW[k, 2] * y
                        if wp.static(need_o):
                            pO = pO + (OFFS[k] * W[k, 2]) * y
                            pX = pX + (OFFS[k] * DW[k, 2]) * y
                        if wp.static(need_h):
                            pH = pH + DD[k, 2] * y
                    w1 = W[j, 1]                                      # axis 1
                    d1 = DW[j, 1]
                    tWW = tWW + w1 * pW
                    tDW = tDW + d1 * pW
                    tWD = tWD + w1 * pD
                    if wp.static(need_o):
                        o1 = OFFS[j] * w1
                        tOW = tOW + o1 * pW
                        tWO = tWO + w1 * pO
                        tXW = tXW + (OFFS[j] * d1) * pW
                        tWX = tWX + w1 * pX
                        tDO = tDO + d1 * pO
                        tOD = tOD + o1 * pD
                    if wp.static(need_h):
                        tHW = tHW + DD[j, 1] * pW
                        tWH = tWH + w1 * pH
                        tDD = tDD + d1 * pD
                w0 = W[i, 0]                                          # axis 0
                d0 = DW[i, 0]
                if wp.static(need_w):
                    Sw = Sw + w0 * tWW
                Sg = Sg + kcols(d0 * tWW, w0 * tDW, w0 * tWD)
                if wp.static(need_o):
                    o0 = OFFS[i] * w0
                    if wp.static(need_w):
                        Swo = Swo + kcols(o0 * tWW, w0 * tOW, w0 * tWO)
                    Sgo0 = Sgo0 + kcols((OFFS[i] * d0) * tWW, d0 * tOW, d0 * tWO)
                    Sgo1 = Sgo1 + kcols(o0 * tDW, w0 * tXW, w0 * tDO)
                    Sgo2 = Sgo2 + kcols(o0 * tWD, w0 * tOD, w0 * tWX)
                if wp.static(need_h):
                    SH0 = SH0 + kcols(DD[i, 0] * tWW, d0 * tDW, d0 * tWD)
                    SH1 = SH1 + kcols(d0 * tDW, w0 * tHW, w0 * tDD)
                    SH2 = SH2 + kcols(d0 * tWD, w0 * tDD, w0 * tWH)
        else:
            for i in range(NW):
                ni = nb + i * strides[0]
                pW = yvec()
                pO = yvec()
                pD = yvec()
                pX = yvec()
                pH = yvec()
                for j in range(NW):                                   # axis 1
                    y = load(src0, src1, ni + j)
                    pW = pW + W[j, 1] * y
                    pD = pD + DW[j, 1] * y
                    if wp.static(need_o):
                        pO = pO + (OFFS[j] * W[j, 1]) * y
                        pX = pX + (OFFS[j] * DW[j, 1]) * y
                    if wp.static(need_h):
                        pH = pH + DD[j, 1] * y
                w0 = W[i, 0]                                          # axis 0
                d0 = DW[i, 0]
                if wp.static(need_w):
                    Sw = Sw + w0 * pW
                Sg = Sg + kcols(d0 * pW, w0 * pD, z)
                if wp.static(need_o):
                    o0 = OFFS[i] * w0
                    if wp.static(need_w):
                        Swo = Swo + kcols(o0 * pW, w0 * pO, z)
                    Sgo0 = Sgo0 + kcols((OFFS[i] * d0) * pW, d0 * pO, z)
                    Sgo1 = Sgo1 + kcols(o0 * pD, w0 * pX, z)
                if wp.static(need_h):
                    SH0 = SH0 + kcols(DD[i, 0] * pW, d0 * pD, z)
                    SH1 = SH1 + kcols(d0 * pD, w0 * pH, z)
        if wp.static(transpose):          # G2P's transpose, after the reductions: no store between their loads
            if wp.static(dim == 3):
                for i in range(NW):
                    Ai = W[i, 0] * a_vp + row(E0, i)
                    for j in range(NW):
                        nij = nb + i * strides[0] + j * strides[1]
                        Bij = W[j, 1] * Ai + W[i, 0] * row(E1, j)
                        wij = W[i, 0] * W[j, 1]
                        for k in range(NW):
                            scatter(dst0, dst1, nij + k, W[k, 2] * Bij + wij * row(E2, k), wij * W[k, 2], a_vo)
            else:
                for i in range(NW):
                    ni = nb + i * strides[0]
                    Ai = W[i, 0] * a_vp + row(E0, i)
                    for j in range(NW):
                        scatter(dst0, dst1, ni + j, W[j, 1] * Ai + W[i, 0] * row(E1, j), W[i, 0] * W[j, 1], a_vo)
        return Sw, Swo, Sg, Sgo0, Sgo1, Sgo2, SH0, SH1, SH2

    @wp.func
    def headv(y: yvec):
        r = vec()
        for c in range(dim):
            r[c] = y[c]
        return r

    @wp.func
    def tailv(y: yvec):
        r = vec()
        if wp.static(second):
            for c in range(dim):
                r[c] = y[n0 + c]
        return r

    @wp.func
    def head(M: kmat):
        r = mat()
        for a in range(dim):
            for b in range(dim):
                r[a, b] = M[a, b]
        return r

    @wp.func
    def tail(M: kmat):
        r = mat()
        if wp.static(second):
            for a in range(dim):
                for b in range(dim):
                    r[a, b] = M[n0 + a, b]
        return r

    @wp.func
    def mrow(M: kmat):
        r = vec()
        if wp.static(p2g):
            for b in range(dim):
                r[b] = M[dim, b]
        return r

    @wp.func
    def head_ddots(M: mat, S0: kmat, S1: kmat, S2: kmat):
        """(M : head(S_d)) for d = 0 .. D-1: a family of D matrices contracted with M (S2 unused in 2D)."""
        if wp.static(dim == 3):
            return vec(wp.ddot(M, head(S0)), wp.ddot(M, head(S1)), wp.ddot(M, head(S2)))
        else:
            return vec(wp.ddot(M, head(S0)), wp.ddot(M, head(S1)))

    @wp.func
    def tail_ddots(M: mat, S0: kmat, S1: kmat, S2: kmat):
        """(M : tail(S_d)) for d = 0 .. D-1 (S2 unused in 2D)."""
        if wp.static(dim == 3):
            return vec(wp.ddot(M, tail(S0)), wp.ddot(M, tail(S1)), wp.ddot(M, tail(S2)))
        else:
            return vec(wp.ddot(M, tail(S0)), wp.ddot(M, tail(S1)))

    return SimpleNamespace(sums=sums, head=head, tail=tail, headv=headv, tailv=tailv, mrow=mrow, head_ddots=head_ddots,
                           tail_ddots=tail_ddots)


class RecordedP2G:
    """A P2G launch recorded on a ``wp.Tape`` with its hand-written adjoint (``Tape.record_func``):
    calling it runs the adjoint; :meth:`forward` reruns the forward launch (the benchmark times both)."""

    name = "p2g"

    def __init__(self, path, fwd_inputs, s, ctl, ext, grid_mm, grid_f):
        self.path, self.fwd_inputs = path, fwd_inputs
        self.s, self.ctl, self.ext, self.grid_mm, self.grid_f = s, ctl, ext, grid_mm, grid_f

    def forward(self):
        p = self.path
        wp.launch(p.k_p2g, dim=p.N, inputs=self.fwd_inputs, device=p.dev, record_tape=False)

    def __call__(self):
        p, s, ctl = self.path, self.s, self.ctl
        sc = p.p2g_adj_scratch()
        st = p.st
        g = lambda a: a.grad if (isinstance(a, wp.array) and a.requires_grad) else None
        C = s.C if p.affine else p.empty_C
        adj_f = self.grid_f.grad if p.split else sc.f
        inputs = [s.x, s.v, C, s.tau, ctl.mass, ctl.volume, self.ext, st.lp, st.origin, st.dx_s, st.dt_s,
                  st.transfer_scalars, st.strides, self.grid_mm.grad, adj_f]
        wp.launch(p.k_p2g_adj.adjoint, dim=p.N, inputs=inputs, outputs=[sc.out],
                  adj_inputs=[g(s.x), g(s.v), g(C) if p.affine else None, g(s.tau), g(ctl.mass), g(ctl.volume),
                              g(self.ext) if p.has_ext else None] + [None] * 8,
                  adj_outputs=[sc.ones], adjoint=True, device=p.dev, record_tape=False)


# ---- G2P fused with the law update ----------------------------------------------------------------------
def g2p_adjoint_kernel(law, dim: int, precision: str, tr, shape=None):
    """G2P + law adjoint with shape function ``shape`` (None: quadratic); see ``_g2p_adjoint_kernel``."""
    return _g2p_adjoint_kernel(law, dim, precision, tr, K.as_shape(shape))


@lru_cache(maxsize=None)
def _g2p_adjoint_kernel(law, dim: int, precision: str, tr, shape):
    """G2P + law update (``kernels.g2p_law_kernel``) with the stencil's adjoint written by hand, as one
    kernel launched in Warp's adjoint mode with the forward kernel's arguments plus the node adjoint
    arrays ``adj_grid_v``, ``adj_grid_v_old``. The stencil gather is a function (``gather``) returning
    its moments packed in one matrix -- columns v_pic, v_old, B (``first``), sum v_i (grad w_i)^T
    (``gradient``) -- whose hand-written gradient (``wp.func_grad``) scatters the moments' adjoints
    back onto the nodes (adds: atomic on CUDA; the CPU gradient path is single-threaded) and into the
    position through the weights (gradient and Hessian). Everything after the gather -- the scheme's
    ``g2p``, the law update and its stress, the stores -- is the forward kernel's code and keeps Warp's
    generated adjoint (the law's replay is needed anyway: nothing of it is saved)."""
    T = warp_types(dim, precision)
    S = K._stencil_funcs(dim, precision, shape)
    NW, OFFS = S.width, S.OFFS
    uses_lp = S.uses_lp
    L = K.law_types(law, dim, precision)
    scalar, vec, mat, ivec = T.scalar, T.vec, T.mat, T.ivec
    need_grad = "gradient" in tr.moments
    apic = "first" in tr.moments
    flip = tr.split_force
    F = tr.funcs
    NC = 2 + 2 * dim
    pmat = wp.types.matrix((dim, NC), scalar)         # packed moments
    impl = law.implementation("warp", "law")(law, dim, precision)
    SEP = _separable(dim, precision, shape, "g2p", flip, apic, need_grad)

    @wp.func
    def cols(a: vec, b: vec, c: vec):
        if wp.static(dim == 3):
            return wp.matrix_from_cols(a, b, c)
        else:
            return wp.matrix_from_cols(a, b)

    @wp.func
    def col(M: pmat, j: int):
        if wp.static(dim == 3):
            return vec(M[0, j], M[1, j], M[2, j])
        else:
            return vec(M[0, j], M[1, j])

    GATHER = _separable(dim, precision, shape, "gather", flip, apic, False)

    @wp.func
    def pack(vp: vec, vo: vec, B: mat, Gs: mat):
        """The moments as one matrix: columns v_pic, v_old, B, sum v (grad w)^T."""
        if wp.static(dim == 3):
            return pmat(vp[0], vo[0], B[0, 0], B[0, 1], B[0, 2], Gs[0, 0], Gs[0, 1], Gs[0, 2],
                        vp[1], vo[1], B[1, 0], B[1, 1], B[1, 2], Gs[1, 0], Gs[1, 1], Gs[1, 2],
                        vp[2], vo[2], B[2, 0], B[2, 1], B[2, 2], Gs[2, 0], Gs[2, 1], Gs[2, 2])
        else:
            return pmat(vp[0], vo[0], B[0, 0], B[0, 1], Gs[0, 0], Gs[0, 1],
                        vp[1], vo[1], B[1, 0], B[1, 1], Gs[1, 0], Gs[1, 1])

    @wp.func
    def gather(x: vec, lp: scalar, origin: vec, dx: scalar, strides: ivec, grid_v: wp.array(dtype=vec),
               grid_v_old: wp.array(dtype=vec), adj_gv: wp.array(dtype=vec), adj_gvo: wp.array(dtype=vec)):
        """G2P's moments (separable sums, as the forward kernel's gather); the adjoint kernel replays it."""
        inv_dx = scalar(1.0) / dx
        base, fx = S.locate(x, origin, inv_dx)
        W, DW = S.weights(fx, lp)
        nb = int(0)
        for d in range(dim):
            nb = nb + base[d] * strides[d]
        Sw, Swo, Sg, g0, g1, g2, h0, h1, h2 = GATHER.sums(W, DW, W, nb, strides, grid_v, grid_v_old, adj_gv, adj_gvo,
                                                          vec(), vec(), mat(), mat())
        Gs = mat()
        if wp.static(need_grad):
            Gs = GATHER.head(Sg)
        return pack(GATHER.headv(Sw), GATHER.tailv(Sw), GATHER.head(Swo), Gs)

    @wp.func_grad(gather)
    def adj_gather(x: vec, lp: scalar, origin: vec, dx: scalar, strides: ivec, grid_v: wp.array(dtype=vec),
                   grid_v_old: wp.array(dtype=vec), adj_gv: wp.array(dtype=vec), adj_gvo: wp.array(dtype=vec),
                   adj_ret: pmat):
        inv_dx = scalar(1.0) / dx
        base, fx = S.locate(x, origin, inv_dx)
        W, DW = S.weights(fx, lp)
        DD = S.hessian(fx, lp)                                  # W'' per node and axis
        nb = int(0)
        for d in range(dim):
            nb = nb + base[d] * strides[d]
        a_vp = col(adj_ret, 0)
        a_vo = col(adj_ret, 1)
        aB = mat()
        aG = mat()
        if wp.static(apic):
            aB = cols(col(adj_ret, 2), col(adj_ret, 3), col(adj_ret, 1 + dim))
        if wp.static(need_grad):
            aG = cols(col(adj_ret, 2 + dim), col(adj_ret, 3 + dim), col(adj_ret, 1 + 2 * dim))
        # G2P's transpose: each node gets w (a_vp + aB o) + aG g (+ w a_vo), and x gets, through the weights,
        # adj fx_d = sum_o g_d a_vp . v_o + g_d v_o . (aB o) + (H aG^T v_o)_d (+ g_d a_vo . v_old_o): separable sums
        Sw_, Swo_, Sg, Sgo0, Sgo1, Sgo2, SH0, SH1, SH2 = SEP.sums(W, DW, DD, nb, strides, grid_v, grid_v_old, adj_gv,
                                                                   adj_gvo, a_vp, a_vo, aB, aG)   # Sw, Swo: P2G's
        afx = wp.transpose(SEP.head(Sg)) @ a_vp
        if wp.static(apic):
            afx = afx + SEP.head_ddots(aB, Sgo0, Sgo1, Sgo2)
        if wp.static(need_grad):
            afx = afx + SEP.head_ddots(aG, SH0, SH1, SH2)
        if wp.static(flip):
            afx = afx + wp.transpose(SEP.tail(Sg)) @ a_vo
        wp.adjoint[x] += inv_dx * afx

    @wp.kernel(module="unique", module_options=K.law_module_options(impl))
    def g2p(x: wp.array(dtype=vec), v: wp.array(dtype=vec), grid_v: wp.array(dtype=vec),
            grid_v_old: wp.array(dtype=vec), origin: vec, dx: scalar, dt: scalar, strides: ivec,
            tp: wp.array(dtype=scalar), lp: wp.array(dtype=scalar), goff: int, start: int,
            state: L.StateArrays, prm: wp.array2d(dtype=scalar), w: L.Weights,
            x_out: wp.array(dtype=vec), v_out: wp.array(dtype=vec), C_out: wp.array(dtype=mat),
            state_out: L.StateArrays, tau: wp.array(dtype=mat),
            domain: wp.array(dtype=mat), domain_out: wp.array(dtype=mat),     # CPDI's (no hand adjoint: unused)
            adj_gv: wp.array(dtype=vec), adj_gvo: wp.array(dtype=vec)):
        q = wp.tid() + start
        p = goff + q
        inv_dx = scalar(1.0) / dx
        xp = x[p]
        if S.in_grid(xp, origin, inv_dx, strides, grid_v.shape[0]) == 0:
            x_out[p] = xp + dt * v[p]
            v_out[p] = v[p]
            P0 = L.load_params(prm, q)
            s0 = L.load_state(state, q)
            L.store_state(state_out, q, s0)
            tau[p] = impl.kirchhoff(s0, P0, w)
            return
        base, fx = S.locate(xp, origin, inv_dx)
        lpv = scalar(0.0)
        if wp.static(uses_lp):
            lpv = lp[p]
        M = gather(xp, lpv, origin, dx, strides, grid_v, grid_v_old, adj_gv, adj_gvo)
        vp = col(M, 0)
        vo = col(M, 1)
        Gv = mat()
        if wp.static(need_grad):
            Gv = inv_dx * cols(col(M, 2 + dim), col(M, 3 + dim), col(M, 1 + 2 * dim))     # JAX-MPM Eq. 18
        B = mat()
        if wp.static(apic):
            B = cols(col(M, 2), col(M, 3), col(M, 1 + dim))
        xn = xp + dt * vp                                                            # JAX-MPM Eq. 17
        # D_p^-1 of xn, the next P2G's position (kernels.g2p_law_kernel); differentiable here: uGIMP's
        # depends on x and on v_pic, whose adjoint reaches the gather's (adj_gather: the nodes and x)
        Dinv = S.dinv_moved(xn, origin, inv_dx, lpv)
        vnew, Cn, grad_v = F.g2p(v[p], vp, vo, B, Gv, fx, inv_dx, Dinv, tp)
        v_out[p] = vnew
        x_out[p] = xn
        if wp.static(tr.carries_C):
            C_out[p] = Cn
        P = L.load_params(prm, q)
        n = impl.update(L.load_state(state, q), grad_v, dt, P, w)
        L.store_state(state_out, q, n)
        tau[p] = impl.kirchhoff(n, P, w)

    return g2p


class RecordedG2P:
    """A G2P + law launch recorded on a ``wp.Tape`` with the hand-written stencil adjoint
    (:func:`g2p_adjoint_kernel`): calling it runs the adjoint; :meth:`forward` reruns the forward."""

    name = "g2p+law"

    def __init__(self, path, kernel, adj_kernel, dim, inputs, grid_v, grid_v_old):
        self.path, self.kernel, self.adj_kernel, self.dim, self.inputs = path, kernel, adj_kernel, dim, inputs
        self.grid_v, self.grid_v_old = grid_v, grid_v_old

    def forward(self):
        wp.launch(self.kernel, dim=self.dim, inputs=self.inputs, device=self.path.dev, record_tape=False)

    def __call__(self):
        get = wp.Tape().get_adjoint
        adj = [get(a) for a in self.inputs]
        adj[2] = adj[3] = None                      # the node adjoints go through adj_gv / adj_gvo instead
        gvo = self.grid_v_old.grad if self.grid_v_old.requires_grad else self.path.empty_vec
        wp.launch(self.adj_kernel, dim=self.dim, inputs=self.inputs + [self.grid_v.grad, gvo],
                  adj_inputs=adj + [None, None], adjoint=True, device=self.path.dev, record_tape=False)
