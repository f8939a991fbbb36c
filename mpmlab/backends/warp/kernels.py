"""Warp kernel factories. Each factory is keyed by what changes the generated code -- dimension,
precision, the transfer's four choices, the law -- and cached, so a kernel compiles once per process
(and Warp's disk cache keeps it across processes). Scene numbers (dx, dt, gravity, wall kinds) are
kernel arguments, so scenes that differ only in numbers share compiled kernels.

Laws enter only through the per-law kernel built from a closure over the law's ``@wp.func``s
(Warp's kernel-factory pattern): P2G/G2P never branch on a law id.
"""

from functools import lru_cache
from types import SimpleNamespace

import warp as wp

from .types import warp_types

WALL_NONE, WALL_STICKY, WALL_SLIP, WALL_SEPARATE = 0, 1, 2, 3
WALL_CODES = {"none": WALL_NONE, "sticky": WALL_STICKY, "slip": WALL_SLIP, "separate": WALL_SEPARATE}


@lru_cache(maxsize=None)
def stencil_funcs(dim: int, precision: str):
    T = warp_types(dim, precision)
    scalar, vec, mat, ivec = T.scalar, T.vec, T.mat, T.ivec

    @wp.func
    def bspline(fx: vec):
        """Quadratic B-spline weights w[k][d] and derivatives (cell units), fx in [0.5, 1.5)."""
        w0 = vec(); w1 = vec(); w2 = vec(); d0 = vec(); d1 = vec(); d2 = vec()
        for d in range(dim):
            f = fx[d]
            w0[d] = scalar(0.5) * (scalar(1.5) - f) * (scalar(1.5) - f)
            w1[d] = scalar(0.75) - (f - scalar(1.0)) * (f - scalar(1.0))
            w2[d] = scalar(0.5) * (f - scalar(0.5)) * (f - scalar(0.5))
            d0[d] = f - scalar(1.5)
            d1[d] = scalar(-2.0) * (f - scalar(1.0))
            d2[d] = f - scalar(0.5)
        return w0, w1, w2, d0, d1, d2

    @wp.func
    def pick(a: vec, b: vec, c: vec, k: int, d: int):
        r = a[d]
        if k == 1:
            r = b[d]
        elif k == 2:
            r = c[d]
        return r

    return SimpleNamespace(bspline=bspline, pick=pick)


def _offsets(dim):
    return [(i, j) for i in range(3) for j in range(3)] if dim == 2 else \
           [(i, j, k) for i in range(3) for j in range(3) for k in range(3)]


@lru_cache(maxsize=None)
def p2g_kernel(dim: int, precision: str, affine: bool, mls_force: bool, split_force: bool, has_ext: bool):
    """P2G: mass, momentum (+ affine), force (gradient or MLS form). ``split_force``: keep momentum and
    force apart (FLIP needs the old grid velocity); otherwise momentum += dt f as in MLS-MPM."""
    T = warp_types(dim, precision)
    S = stencil_funcs(dim, precision)
    scalar, vec, mat, ivec = T.scalar, T.vec, T.mat, T.ivec
    stencil = 3**dim

    @wp.kernel(module="unique")
    def p2g(x: wp.array(dtype=vec), v: wp.array(dtype=vec), C: wp.array(dtype=mat), tau: wp.array(dtype=mat),
            mass: wp.array(dtype=scalar), vol: wp.array(dtype=scalar), ext: wp.array(dtype=vec),
            origin: vec, dx: scalar, dt: scalar, strides: ivec,
            grid_m: wp.array(dtype=scalar), grid_mv: wp.array(dtype=vec), grid_f: wp.array(dtype=vec)):
        p = wp.tid()
        inv_dx = scalar(1.0) / dx
        Xp = (x[p] - origin) * inv_dx
        base = ivec()
        fx = vec()
        for d in range(dim):
            base[d] = int(wp.floor(Xp[d] - scalar(0.5)))
            fx[d] = Xp[d] - scalar(base[d])
        w0, w1, w2, d0, d1, d2 = S.bspline(fx)
        m = mass[p]
        V = vol[p]
        stress = tau[p]
        mv = m * v[p]
        Cp = mat()
        if wp.static(affine):
            Cp = C[p]
        fext = vec()
        if wp.static(has_ext):
            fext = ext[p]
        for s in range(stencil):
            weight = scalar(1.0)
            gw = vec()
            for d in range(dim):
                gw[d] = scalar(1.0)
            node = int(0)
            dpos = vec()
            rem = s
            for d in range(dim):
                k = rem % 3
                rem = rem // 3
                wd = S.pick(w0, w1, w2, k, d)
                weight = weight * wd
                for e in range(dim):
                    if e == d:
                        gw[e] = gw[e] * S.pick(d0, d1, d2, k, d) * inv_dx
                    else:
                        gw[e] = gw[e] * wd
                dpos[d] = (scalar(k) - fx[d]) * dx
                node = node + (base[d] + k) * strides[d]
            mom = weight * mv
            if wp.static(affine):
                mom = mom + weight * m * (Cp @ dpos)
            f = vec()
            if wp.static(mls_force):
                f = -(scalar(4.0) * inv_dx * inv_dx) * V * weight * (stress @ dpos)   # Hu et al. 2018
            else:
                f = -V * (stress @ gw)                                                # JAX-MPM Eq. 12
            if wp.static(has_ext):
                f = f + weight * fext
            wp.atomic_add(grid_m, node, weight * m)
            if wp.static(split_force):
                wp.atomic_add(grid_mv, node, mom)
                wp.atomic_add(grid_f, node, f)
            else:
                wp.atomic_add(grid_mv, node, mom + dt * f)

    return p2g


@lru_cache(maxsize=None)
def grid_update_kernel(dim: int, precision: str, split_force: bool):
    """Grid velocity update (JAX-MPM Eqs. 13-14) fused with the domain walls (kinds are arguments)."""
    T = warp_types(dim, precision)
    scalar, vec, ivec = T.scalar, T.vec, T.ivec

    @wp.kernel(module="unique")
    def grid_update(grid_m: wp.array(dtype=scalar), grid_mv: wp.array(dtype=vec), grid_f: wp.array(dtype=vec),
                    dt: scalar, gravity: vec, shape: ivec, strides: ivec, wall_kind: wp.array(dtype=int),
                    thickness: int, grid_v: wp.array(dtype=vec), grid_v_old: wp.array(dtype=vec)):
        i = wp.tid()
        m = grid_m[i]
        vn = vec()
        if m > scalar(0.0):
            vo = grid_mv[i] / m
            if wp.static(split_force):
                grid_v_old[i] = vo
                vn = vo + dt * (grid_f[i] / m + gravity)
            else:
                vn = vo + dt * gravity
            rem = i
            for d in range(dim):
                I = rem // strides[d]
                rem = rem - I * strides[d]
                cells = shape[d] - 1
                for side in range(2):
                    kind = wall_kind[2 * d + side]
                    near = False
                    if side == 0:
                        near = I < thickness
                    else:
                        near = I > cells - thickness
                    if near and kind != 0:
                        if kind == 1:
                            vn = vec()
                        else:
                            into = False
                            if side == 0:
                                into = vn[d] < scalar(0.0)
                            else:
                                into = vn[d] > scalar(0.0)
                            if kind == 2 or into:
                                vn[d] = scalar(0.0)
        elif wp.static(split_force):
            grid_v_old[i] = vec()
        grid_v[i] = vn

    return grid_update


@lru_cache(maxsize=None)
def g2p_kernel(dim: int, precision: str, affine: str | None, grad_v_from_affine: bool, flip: bool):
    T = warp_types(dim, precision)
    S = stencil_funcs(dim, precision)
    scalar, vec, mat, ivec = T.scalar, T.vec, T.mat, T.ivec
    stencil = 3**dim
    need_gradw = (not grad_v_from_affine) or affine == "velocity_gradient"
    apic = affine == "apic"
    tpic = affine == "velocity_gradient"

    @wp.kernel(module="unique")
    def g2p(x: wp.array(dtype=vec), v: wp.array(dtype=vec), grid_v: wp.array(dtype=vec),
            grid_v_old: wp.array(dtype=vec), origin: vec, dx: scalar, dt: scalar, strides: ivec,
            flip_ratio: scalar, x_out: wp.array(dtype=vec), v_out: wp.array(dtype=vec),
            C_out: wp.array(dtype=mat), grad_v_out: wp.array(dtype=mat)):
        p = wp.tid()
        inv_dx = scalar(1.0) / dx
        Xp = (x[p] - origin) * inv_dx
        base = ivec()
        fx = vec()
        for d in range(dim):
            base[d] = int(wp.floor(Xp[d] - scalar(0.5)))
            fx[d] = Xp[d] - scalar(base[d])
        w0, w1, w2, d0, d1, d2 = S.bspline(fx)
        v_pic = vec()
        dv = vec()
        B = mat()
        G = mat()
        for s in range(stencil):
            weight = scalar(1.0)
            gw = vec()
            for d in range(dim):
                gw[d] = scalar(1.0)
            node = int(0)
            dpos = vec()
            rem = s
            for d in range(dim):
                k = rem % 3
                rem = rem // 3
                wd = S.pick(w0, w1, w2, k, d)
                weight = weight * wd
                if wp.static(need_gradw):
                    for e in range(dim):
                        if e == d:
                            gw[e] = gw[e] * S.pick(d0, d1, d2, k, d) * inv_dx
                        else:
                            gw[e] = gw[e] * wd
                dpos[d] = (scalar(k) - fx[d]) * dx
                node = node + (base[d] + k) * strides[d]
            gv = grid_v[node]
            v_pic = v_pic + weight * gv
            if wp.static(flip):
                dv = dv + weight * (gv - grid_v_old[node])
            if wp.static(apic):
                B = B + weight * wp.outer(gv, dpos)
            if wp.static(need_gradw):
                G = G + wp.outer(gv, gw)                                   # JAX-MPM Eq. 18
        vp = v_pic
        if wp.static(flip):
            vp = flip_ratio * (v[p] + dv) + (scalar(1.0) - flip_ratio) * v_pic   # JAX-MPM Eq. 15
        v_out[p] = vp
        x_out[p] = x[p] + dt * v_pic                                        # JAX-MPM Eq. 17
        if wp.static(apic):
            Cn = scalar(4.0) * inv_dx * inv_dx * B                           # B D^-1, D = dx^2/4 I
            C_out[p] = Cn
            if wp.static(grad_v_from_affine):
                grad_v_out[p] = Cn
            else:
                grad_v_out[p] = G
        else:
            if wp.static(tpic):
                C_out[p] = G
            grad_v_out[p] = G

    return g2p


@lru_cache(maxsize=None)
def law_kernels(law_cls, dim: int, precision: str):
    """Per-law kernels from a closure over the law's ``@wp.func``s: ``update`` (state + stress) and
    ``stress`` (stress only, used at init and in conformance tests)."""
    T = warp_types(dim, precision)
    scalar, mat, LawState = T.scalar, T.mat, T.LawState
    impl = law_cls.implementation("warp", "law")(dim, precision)
    fields = set(law_cls.state_fields)
    hasF, hasJ, hasS, hasE = "F" in fields, "J" in fields, "sigma" in fields, "eps_p" in fields

    @wp.func
    def load(F: wp.array(dtype=mat), J: wp.array(dtype=scalar), sig: wp.array(dtype=mat),
             eps: wp.array(dtype=scalar), q: int):
        s = LawState()
        if wp.static(hasF):
            s.F = F[q]
        if wp.static(hasJ):
            s.J = J[q]
        if wp.static(hasS):
            s.sigma = sig[q]
        if wp.static(hasE):
            s.eps_p = eps[q]
        return s

    @wp.kernel(module="unique")
    def update(F: wp.array(dtype=mat), J: wp.array(dtype=scalar), sig: wp.array(dtype=mat),
               eps: wp.array(dtype=scalar), grad_v: wp.array(dtype=mat), prm: wp.array2d(dtype=scalar),
               dt: scalar, offset: int,
               F_out: wp.array(dtype=mat), J_out: wp.array(dtype=scalar), sig_out: wp.array(dtype=mat),
               eps_out: wp.array(dtype=scalar), tau: wp.array(dtype=mat)):
        q = wp.tid()
        s = load(F, J, sig, eps, q)
        n = impl.update(s, grad_v[offset + q], dt, prm, q)
        if wp.static(hasF):
            F_out[q] = n.F
        if wp.static(hasJ):
            J_out[q] = n.J
        if wp.static(hasS):
            sig_out[q] = n.sigma
        if wp.static(hasE):
            eps_out[q] = n.eps_p
        tau[offset + q] = impl.kirchhoff(n, prm, q)

    @wp.kernel(module="unique")
    def stress(F: wp.array(dtype=mat), J: wp.array(dtype=scalar), sig: wp.array(dtype=mat),
               eps: wp.array(dtype=scalar), prm: wp.array2d(dtype=scalar), offset: int, tau: wp.array(dtype=mat)):
        q = wp.tid()
        tau[offset + q] = impl.kirchhoff(load(F, J, sig, eps, q), prm, q)

    return SimpleNamespace(update=update, stress=stress)


@lru_cache(maxsize=None)
def guard_kernel(dim: int, precision: str):
    """Sets flag[0] = 1 if any position/velocity is non-finite or outside [lo, hi)."""
    T = warp_types(dim, precision)
    scalar, vec = T.scalar, T.vec

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
def law_guard_kernel(dim: int, precision: str, field: str):
    """Sets flag[0] = 1 if a law state entry is non-finite or its J (det F) is <= 0."""
    T = warp_types(dim, precision)
    scalar, mat = T.scalar, T.mat
    is_mat = field in ("F", "sigma")
    dtype = mat if is_mat else scalar
    check_j = field in ("F", "J")

    @wp.kernel(module="unique")
    def guard(a: wp.array(dtype=dtype), flag: wp.array(dtype=int)):
        q = wp.tid()
        bad = False
        if wp.static(is_mat):
            for i in range(dim):
                for j in range(dim):
                    if not wp.isfinite(a[q][i, j]):
                        bad = True
            if wp.static(check_j):
                if not (wp.determinant(a[q]) > scalar(0.0)):
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
