"""Hand-written adjoints of the gradient path's transfer kernels (issue 17, item 1, Warp half).

Warp's generated adjoint of a kernel replays the whole forward body (every stencil node, every
intermediate kept as an SSA value), zero-initialises one adjoint variable per SSA value of the
unrolled 3^D loop, then runs the reverse sweep and adds each array read's adjoint back with an
atomic add. For P2G that is the forward once more plus a reverse sweep about twice its size
(``benchmarks/_adjoint_split_warp.py`` measures it: 3.2x the forward before this module).

P2G's transpose is a *gather*: its inputs are per particle and its outputs are grid arrays, so the
adjoint of a particle's inputs reads the adjoints of the 3^D nodes it wrote and accumulates into
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

with H_o the Hessian of w_o (the B-spline's second derivatives 1, -2, 1).
"""

from functools import lru_cache
from types import SimpleNamespace

import warp as wp

from . import kernels as K
from .types import warp_types


@lru_cache(maxsize=None)
def p2g_adjoint_kernels(dim: int, precision: str, tr, has_ext: bool):
    """(stencil, terms) kernels of P2G's adjoint for transfer ``tr`` (a ``WarpTransfer``); the
    forward is ``kernels.p2g_kernel(dim, precision, tr, has_ext, atomic=True)``."""
    T = warp_types(dim, precision)
    S = K.stencil_funcs(dim, precision)
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
    carries_C = tr.carries_C

    @wp.func
    def head(a: gvec):
        out = vec()
        for d in range(dim):
            out[d] = a[d]
        return out

    @wp.func
    def second(i: int):
        """d^2 W_i / d f^2 of the quadratic B-spline: 1, -2, 1."""
        r = scalar(1.0)
        if i == 1:
            r = scalar(-2.0)
        return r

    @wp.kernel(module="unique", enable_backward=False)
    def stencil(x: wp.array(dtype=vec), v: wp.array(dtype=vec), C: wp.array(dtype=mat), tau: wp.array(dtype=mat),
                mass: wp.array(dtype=scalar), vol: wp.array(dtype=scalar), ext: wp.array(dtype=vec),
                origin: vec, dx: scalar, dt: scalar, tp: wp.array(dtype=scalar), strides: ivec,
                adj_mm: wp.array(dtype=gvec), adj_f: wp.array(dtype=vec),
                adj_x: wp.array(dtype=vec), adj_mass: wp.array(dtype=scalar), adj_ext: wp.array(dtype=vec),
                adj_q: wp.array(dtype=vec), adj_A: wp.array(dtype=mat), adj_T: wp.array(dtype=mat),
                adj_Fm: wp.array(dtype=mat), adj_Fg: wp.array(dtype=mat)):
        p = wp.tid()
        inv_dx = scalar(1.0) / dx
        G = adj_mm.shape[0]
        if S.in_grid(x[p], origin, inv_dx, strides, G) == 0:
            adj_q[p] = vec()                       # contributed nothing: its terms' adjoints are 0
            if wp.static(m_affine):
                adj_A[p] = mat()
            if wp.static(m_grad):
                adj_T[p] = mat()
            if wp.static(f_affine):
                adj_Fm[p] = mat()
            if wp.static(f_grad):
                adj_Fg[p] = mat()
            return
        base, fx = S.locate(x[p], origin, inv_dx)
        W, DW = S.bspline(fx)
        m = mass[p]
        Cp = mat()
        if wp.static(carries_C):
            Cp = C[p]
        q, A, Tg = F.p2g_momentum(m, vol[p], v[p], Cp, tau[p], dt, inv_dx, tp)
        Fm = mat()
        Fg = mat()
        if wp.static(split):
            Fm, Fg = F.p2g_force(m, vol[p], v[p], Cp, tau[p], dt, inv_dx, tp)
        fext = vec()
        if wp.static(has_ext):
            fext = ext[p]
            if wp.static(not split):
                q = q + dt * fext
        fxd = fx * dx
        nb = int(0)
        for d in range(dim):
            nb = nb + base[d] * strides[d]
        s_q = vec()          # sum w a_q
        s_qo = mat()         # sum w a_q o^T
        s_T = mat()          # sum a_q g^T
        s_m = scalar(0.0)    # sum w a_m
        s_fo = mat()         # sum w a_f o^T
        s_f = vec()          # sum w a_f
        s_Fg = mat()         # sum a_f g^T
        afx = vec()          # adjoint of fx (cell units) through the weights
        for n in range(wp.static(3**dim)):
            oi = ivec()
            o = vec()
            node = nb
            r = n
            for d in range(dim):
                od = r % 3
                r = r // 3
                oi[d] = od
                o[d] = scalar(od)
                node = node + od * strides[d]
            w = scalar(1.0)
            for e in range(dim):
                w = w * W[oi[e], e]
            gw = vec()       # grad w (cell units)
            for d in range(dim):
                wd = scalar(1.0)
                for e in range(dim):
                    if e == d:
                        wd = wd * DW[oi[e], e]
                    else:
                        wd = wd * W[oi[e], e]
                gw[d] = wd
            H = mat()        # Hessian of w (only the gradient terms need it)
            if wp.static(m_grad or f_grad):
                for d in range(dim):
                    for c in range(dim):
                        h = scalar(1.0)
                        for e in range(dim):
                            if e == d and e == c:
                                h = h * second(oi[e])
                            elif e == d or e == c:
                                h = h * DW[oi[e], e]
                            else:
                                h = h * W[oi[e], e]
                        H[d, c] = h
            a4 = adj_mm[node]
            aq = head(a4)
            am = a4[dim]
            val = q
            if wp.static(m_affine):
                val = q + A @ (o * dx - fxd)
                s_qo = s_qo + wp.outer(w * aq, o)
            s_q = s_q + w * aq
            s_m = s_m + w * am
            afx = afx + (wp.dot(aq, val) + am * m) * gw
            if wp.static(m_grad):
                s_T = s_T + wp.outer(aq, gw)
                afx = afx + H @ (wp.transpose(Tg) @ aq)
            if wp.static(split):
                af = adj_f[node]
                if wp.static(f_grad):
                    s_Fg = s_Fg + wp.outer(af, gw)
                    afx = afx + H @ (wp.transpose(Fg) @ af)
                    if wp.static(ext_grad):
                        s_f = s_f + w * af
                        afx = afx + wp.dot(af, fext) * gw
                if wp.static(f_affine):
                    fv = Fm @ (o * dx - fxd)
                    if wp.static(ext_affine):
                        fv = fv + fext
                    s_fo = s_fo + wp.outer(w * af, o)
                    s_f = s_f + w * af
                    afx = afx + wp.dot(af, fv) * gw
                if wp.static(ext_alone):
                    s_f = s_f + w * af
                    afx = afx + wp.dot(af, fext) * gw
        # -w dx A^T a_q summed over nodes (the fx inside A (o - fx) dx), likewise for Fm
        if wp.static(m_affine):
            afx = afx - dx * (wp.transpose(A) @ s_q)
            adj_A[p] = (s_qo - wp.outer(s_q, fx)) * dx
        if wp.static(f_affine):
            afx = afx - dx * (wp.transpose(Fm) @ s_f)
            adj_Fm[p] = (s_fo - wp.outer(s_f, fx)) * dx
        if wp.static(m_grad):
            adj_T[p] = s_T
        if wp.static(f_grad):
            adj_Fg[p] = s_Fg
        adj_q[p] = s_q
        adj_x[p] = adj_x[p] + inv_dx * afx
        adj_mass[p] = adj_mass[p] + s_m
        if wp.static(has_ext):
            ae = s_f
            if wp.static(not split):
                ae = dt * s_q
            adj_ext[p] = adj_ext[p] + ae

    @wp.kernel(module="unique")
    def terms(v: wp.array(dtype=vec), C: wp.array(dtype=mat), tau: wp.array(dtype=mat),
              mass: wp.array(dtype=scalar), vol: wp.array(dtype=scalar), dt: scalar, dx: scalar,
              tp: wp.array(dtype=scalar),
              q_out: wp.array(dtype=vec), A_out: wp.array(dtype=mat), T_out: wp.array(dtype=mat),
              Fm_out: wp.array(dtype=mat), Fg_out: wp.array(dtype=mat)):
        """The per-particle P2G terms alone; only its generated adjoint is launched."""
        p = wp.tid()
        inv_dx = scalar(1.0) / dx
        Cp = mat()
        if wp.static(carries_C):
            Cp = C[p]
        q, A, Tg = F.p2g_momentum(mass[p], vol[p], v[p], Cp, tau[p], dt, inv_dx, tp)
        q_out[p] = q
        if wp.static(m_affine):
            A_out[p] = A
        if wp.static(m_grad):
            T_out[p] = Tg
        if wp.static(split):
            Fm, Fg = F.p2g_force(mass[p], vol[p], v[p], Cp, tau[p], dt, inv_dx, tp)
            if wp.static(f_affine):
                Fm_out[p] = Fm
            if wp.static(f_grad):
                Fg_out[p] = Fg

    return SimpleNamespace(stencil=stencil, terms=terms, m_affine=m_affine, m_grad=m_grad, f_affine=f_affine,
                           f_grad=f_grad)


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
        k, tmp = p.k_p2g_adj, p.p2g_adj_scratch()
        st, dev, N = p.st, p.dev, p.N
        g = lambda a: a.grad if a.requires_grad else None
        adj_x, adj_mass = g(s.x), g(ctl.mass)
        adj_ext = g(self.ext) if p.has_ext else None
        if adj_x is None:                  # positions not differentiable here: accumulate into scratch
            adj_x = tmp.x
            adj_x.zero_()
        if adj_mass is None:
            adj_mass = tmp.m
            adj_mass.zero_()
        if adj_ext is None:
            adj_ext = tmp.e
        adj_f = self.grid_f.grad if p.split else tmp.f
        wp.launch(k.stencil, dim=N, inputs=[s.x, s.v, s.C, s.tau, ctl.mass, ctl.volume, self.ext, st.origin, st.dx_s,
                                            st.dt_s, st.transfer_scalars, st.strides, self.grid_mm.grad, adj_f,
                                            adj_x, adj_mass, adj_ext, tmp.q, tmp.A, tmp.T, tmp.Fm, tmp.Fg],
                  device=dev, record_tape=False)
        C = s.C if p.affine else p.empty_C
        wp.launch(k.terms, dim=N, inputs=[s.v, C, s.tau, ctl.mass, ctl.volume, st.dt_s, st.dx_s,
                                          st.transfer_scalars],
                  outputs=[tmp.q_out, tmp.A_out, tmp.T_out, tmp.Fm_out, tmp.Fg_out],
                  adj_inputs=[g(s.v), g(C) if p.affine else None, g(s.tau), g(ctl.mass), g(ctl.volume), None, None,
                              None],
                  adj_outputs=[tmp.q, tmp.A, tmp.T, tmp.Fm, tmp.Fg], adjoint=True, device=dev, record_tape=False)
