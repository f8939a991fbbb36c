"""Warp NCLaw (Ma et al. 2023, App. C Alg. 4), built per (law instance, dim, precision).

The two networks are evaluated inside the fused G2P + law kernel, per particle, as one ``@wp.func``
each, on fixed-size Warp vectors of the hidden width (``wp.types.vector(64)``):

* a layer is a sum of weight columns, ``a += W[:, j] * x_j`` over j, reading the law's column copies
  of W (``Law.weight_views``: one 64-vector per input unit, members of the ``Weights`` struct); the
  compiler turns each such 64-wide multiply-add into SIMD code (no reduction, so no reassociation is
  needed: the sums run in the same order as a scalar loop, j ascending);
* GELU is exact in fp64 (``wp.erf``, libm). In fp32 it is evaluated on the whole 64-vector with the
  rational erf of XLA's/Eigen's fp32 ``erf`` (x P(x^2) / Q(x^2) on [-4, 4], clamped outside; max
  error 6.5e-8 in exact arithmetic, 4.4e-7 in fp32 vs 4.5e-8 for libm's ``erff``), which vectorises;
  libm's scalar ``erff`` cost ~12 ns a call, 1.5 ms of a 2 ms network at 1,000 particles;
* the MLP has a hand-written adjoint (``wp.func_grad``): recompute the activations, back-propagate
  with the row copies (``g += W[i, :] * g_i``, again SIMD), the derivative of the GELU actually
  evaluated (fp32: of the rational erf), and accumulate the weight gradients with ``wp.atomic_add``
  into the sources' gradient arrays, a row vector at a time (the ``grad_rows`` views). Warp's own
  adjoint of a dynamic loop that accumulates into a scalar is wrong in Warp 1.19 (0.7 % on
  mlp_elastic's dtau/dF), so the automatic one is not used.
* one SVD per network evaluation: the singular values fed to the network are those of the SVD that
  also gives R = U V^T, with the derivative ds_i = (U^T dF V)_ii (``sv``);
* the kernels that call these functions are compiled at -O3 with -ffp-contract=fast on the CPU
  (``module_options``, read by ``kernels.law_module_options``): Warp emits each multiply and add as
  its own statement, so the default contraction fuses none of the MLP's multiply-adds (paired, 1000
  steps: 0.905x of the time with Warp's default flags).

Measured (2-core shared CPU, 1 Warp thread, NCLaw's 1,000-particle cube, 3D MLS fp32;
``benchmarks/nclaw_warp.py``, ``benchmarks/README.md`` "NCLaw on Warp"): one network for 1,000
particles takes 6.5-8 ms in the former scalar form (2D scalar arrays, libm erff), 1.7-1.9 ms as
64-vectors with libm erff, 0.47 ms as 64-vectors with the vectorised erf, against 0.69 ms batched in
torch (1 thread, not counting the kernel split that it needs). A torch (or tile) evaluation between
kernels splits the fused G2P kernel in three (the plastic network sits between G2P and the elastic
one) and puts torch ops on the Warp tape path, so the in-kernel form is kept. A 1000-step forward:
2.8-3.3 s (nclaw) vs 1.1-1.25 s (fixed_corotated), 2.49-2.67x; it was 16.9 vs 1.8 ms/step
before (``benchmarks/nclaw.md``). The GPU side is argued, not measured, in the README section.

``make`` also returns ``mlp_e`` (the elastic MLP alone), ``features`` and ``vin`` for profiling
kernels (``benchmarks/README.md``).
"""

import math
from functools import lru_cache
from types import SimpleNamespace

import warp as wp

from ...backends.warp.law_structs import law_types
from ...backends.warp.linalg import warp_linalg

_SQRT1_2 = 1.0 / math.sqrt(2.0)
_INV_SQRT_2PI = 1.0 / math.sqrt(2.0 * math.pi)
# fp32 erf(u) = u P(u^2) / Q(u^2) on |u| <= 4 (XLA's ErfImpl32 / Eigen's generic_fast_erf_float)
_P0, _P1, _P2, _P3, _P4, _P5, _P6 = (-2.72614225801306e-10, 2.77068142495902e-08, -2.10102402082508e-06,
                                     -5.69250639462346e-05, -7.34990630326855e-04, -2.95459980854025e-03,
                                     -1.60960333262415e-02)
_Q0, _Q1, _Q2, _Q3, _Q4 = (-1.45660718464996e-05, -2.13374055278905e-04, -1.68282697438203e-03,
                           -7.37332916720468e-03, -1.42647390514189e-02)
_ERF_CLAMP = 4.0


@lru_cache(maxsize=None)
def make(law, dim: int, precision: str) -> SimpleNamespace:
    T = law_types(law, dim, precision)
    La = warp_linalg(dim, precision)
    scalar, vec, mat, LawState, Params, Weights = T.scalar, T.vec, T.mat, T.LawState, T.Params, T.Weights
    width = int(law.width)
    nin = law.n_inputs(dim)
    nout = dim * dim
    biases = bool(law.no_undeformed)
    no_rot = bool(law.no_rotation)
    shift = 0.0 if law.no_undeformed else 1.0
    alpha = float(law.alpha)
    fast_erf = precision != "fp64"
    vin = wp.types.vector(nin, scalar)
    vh = wp.types.vector(width, scalar)
    vout = wp.types.vector(nout, scalar)

    @wp.func
    def gelu(x: scalar):
        return scalar(0.5) * x * (scalar(1.0) + wp.erf(x * scalar(_SQRT1_2)))

    @wp.func
    def gelu_prime(x: scalar):
        return scalar(0.5) * (scalar(1.0) + wp.erf(x * scalar(_SQRT1_2))) + x * scalar(_INV_SQRT_2PI) * wp.exp(
            scalar(-0.5) * x * x)

    @wp.func
    def horner(u2: vh, c0: float, c1: float, c2: float, c3: float, c4: float, c5: float, c6: float):
        """c0 t^6 + ... + c6 at t = u2, component-wise (unused leading coefficients 0)."""
        p = vh(scalar(c0))
        p = wp.cw_mul(p, u2) + vh(scalar(c1))
        p = wp.cw_mul(p, u2) + vh(scalar(c2))
        p = wp.cw_mul(p, u2) + vh(scalar(c3))
        p = wp.cw_mul(p, u2) + vh(scalar(c4))
        p = wp.cw_mul(p, u2) + vh(scalar(c5))
        return wp.cw_mul(p, u2) + vh(scalar(c6))

    @wp.func
    def erf_u(a: vh):
        """u = a / sqrt 2 clamped to [-4, 4], u^2, P(u^2), Q(u^2)."""
        u = scalar(_SQRT1_2) * a
        u = wp.min(wp.max(u, vh(scalar(-_ERF_CLAMP))), vh(scalar(_ERF_CLAMP)))
        u2 = wp.cw_mul(u, u)
        return u, u2, horner(u2, _P0, _P1, _P2, _P3, _P4, _P5, _P6), horner(u2, 0.0, 0.0, _Q0, _Q1, _Q2, _Q3, _Q4)

    @wp.func
    def act(a: vh):
        """GELU of every hidden unit: exact (libm erf) in fp64, the vectorised rational erf in fp32."""
        if wp.static(fast_erf):
            u, u2, P, Q = erf_u(a)
            return scalar(0.5) * wp.cw_mul(a, vh(scalar(1.0)) + wp.cw_div(wp.cw_mul(u, P), Q))
        else:
            h = vh()
            for i in range(width):
                h[i] = gelu(a[i])
            return h

    @wp.func
    def act_prime(a: vh):
        """The derivative of ``act`` (fp32: of the rational erf as evaluated; 0 where it is clamped)."""
        if wp.static(fast_erf):
            u, u2, P, Q = erf_u(a)
            dP = horner(u2, 0.0, 6.0 * _P0, 5.0 * _P1, 4.0 * _P2, 3.0 * _P3, 2.0 * _P4, _P5)
            dQ = horner(u2, 0.0, 0.0, 0.0, 4.0 * _Q0, 3.0 * _Q1, 2.0 * _Q2, _Q3)
            E = wp.cw_div(wp.cw_mul(u, P), Q)
            dE = wp.cw_div(P, Q) + scalar(2.0) * wp.cw_mul(u2, wp.cw_div(wp.cw_mul(dP, Q) - wp.cw_mul(P, dQ),
                                                                           wp.cw_mul(Q, Q)))
            for i in range(width):
                if wp.abs(a[i]) * scalar(_SQRT1_2) >= scalar(_ERF_CLAMP):
                    dE[i] = scalar(0.0)
            return scalar(0.5) * (vh(scalar(1.0)) + E) + scalar(0.5 * _SQRT1_2) * wp.cw_mul(a, dE)
        else:
            d = vh()
            for i in range(width):
                d[i] = gelu_prime(a[i])
            return d

    @wp.func
    def hidden(z: vin, W1c: wp.array(dtype=vh), W2c: wp.array(dtype=vh), b1: vh, b2: vh):
        """a1 = W1 z + b1, h1 = gelu(a1), a2 = W2 h1 + b2 (column sums, j ascending)."""
        a1 = b1
        for j in range(nin):
            a1 += W1c[j] * z[j]
        h1 = act(a1)
        a2 = b2
        for j in range(width):
            a2 += W2c[j] * h1[j]
        return a1, h1, a2

    def backprop(vg, n_out: int, vx):
        """The adjoint of a layer a = W x (+ b), given g = d/da: returns W^T g, summed over the rows
        W[i, :] (``vx`` vectors, SIMD), and accumulates dW += g x^T into the weights' gradient a row at a
        time (``Gr``: the gradient's rows, the ``grad_rows`` view; empty when W takes no gradient). One
        vector add per row instead of one scalar add per weight: 7x faster for a 64 x 64 layer at 1,000 particles
        (0.16 against 1.15 ms on one CPU thread, measured 2026-12-07)."""

        @wp.func
        def back(g: vg, Wr: wp.array(dtype=vx), x: vx, Gr: wp.array(dtype=vx)):
            gx = vx()
            accumulate = Gr.shape[0] > 0
            for i in range(n_out):
                gi = g[i]
                gx += Wr[i] * gi
                if accumulate:
                    wp.atomic_add(Gr, i, gi * x)
            return gx

        return back

    back_h = backprop(vout, nout, vh)              # layer 3
    back_hh = backprop(vh, width, vh)              # layer 2
    back_z = backprop(vh, width, vin)              # layer 1

    def network(elastic: bool):
        """The MLP of one network, z -> W3 gelu(W2 gelu(W1 z + b1) + b2) + b3, reading the column/row
        copies from the ``Weights`` struct. The struct itself is the argument (not its member arrays):
        inside the custom adjoint ``wp.adjoint[w].e_W1`` is then the weights' gradient array, while the
        adjoint of a member array passed on its own is an empty local in Warp 1.19 (measured: gradients
        silently lost)."""

        @wp.func
        def biases_of(w: Weights):
            b1 = vh()
            b2 = vh()
            b3 = vout()
            if wp.static(biases):
                if wp.static(elastic):
                    b1 = w.e_b1v[0]
                    b2 = w.e_b2v[0]
                    b3 = w.e_b3v[0]
                else:
                    b1 = w.p_b1v[0]
                    b2 = w.p_b2v[0]
                    b3 = w.p_b3v[0]
            return b1, b2, b3

        @wp.func
        def mlp(z: vin, w: Weights):
            if wp.static(elastic):
                W1c = w.e_W1c
                W2c = w.e_W2c
                W3c = w.e_W3c
            else:
                W1c = w.p_W1c
                W2c = w.p_W2c
                W3c = w.p_W3c
            b1, b2, b3 = biases_of(w)
            a1, h1, a2 = hidden(z, W1c, W2c, b1, b2)
            h2 = act(a2)
            out = b3
            for j in range(width):
                out += W3c[j] * h2[j]
            return out

        @wp.func_grad(mlp)
        def adj_mlp(z: vin, w: Weights, adj_ret: vout):
            if wp.static(elastic):
                W1c = w.e_W1c
                W2c = w.e_W2c
                W1r = w.e_W1r
                W2r = w.e_W2r
                W3r = w.e_W3r
                G1 = w.e_W1g
                G2 = w.e_W2g
                G3 = w.e_W3g
            else:
                W1c = w.p_W1c
                W2c = w.p_W2c
                W1r = w.p_W1r
                W2r = w.p_W2r
                W3r = w.p_W3r
                G1 = w.p_W1g
                G2 = w.p_W2g
                G3 = w.p_W3g
            if wp.static(biases):
                if wp.static(elastic):
                    B1 = wp.adjoint[w].e_b1
                    B2 = wp.adjoint[w].e_b2
                    B3 = wp.adjoint[w].e_b3
                else:
                    B1 = wp.adjoint[w].p_b1
                    B2 = wp.adjoint[w].p_b2
                    B3 = wp.adjoint[w].p_b3
            b1, b2, b3 = biases_of(w)
            a1, h1, a2 = hidden(z, W1c, W2c, b1, b2)       # recompute the activations
            h2 = act(a2)
            # layer 3: out = W3 h2 + b3; layer 2: a2 = W2 h1 + b2; layer 1: a1 = W1 z + b1
            g2 = wp.cw_mul(back_h(adj_ret, W3r, h2, G3), act_prime(a2))
            g1 = wp.cw_mul(back_hh(g2, W2r, h1, G2), act_prime(a1))
            gz = back_z(g1, W1r, z, G1)
            if wp.static(biases):
                for o in range(nout):
                    wp.atomic_add(B3, o, adj_ret[o])
                for i in range(width):
                    wp.atomic_add(B2, i, g2[i])
                    wp.atomic_add(B1, i, g1[i])
            wp.adjoint[z] += gz

        # the network input and T1 are built with constructors, not component assignment: Warp 1.19's
        # automatic adjoint drops in-place writes into local vectors/matrices (measured: zero gradients)
        @wp.func
        def response(F: mat, w: Weights):
            """Y = R T, T = sym(T1), T1 = NN(sigma - 1, vec(F^T F - I), det F - 1) (Alg. 4 lines 1-5);
            ``no_rotation``: T1 = NN(vec(F - I)) as is."""
            if wp.static(no_rot):
                return as_matrix(mlp(plain_features(F), w))
            else:
                U, sc, V = La.svd_const(F)
                T1 = as_matrix(mlp(features(F, U, sc, V), w))
                R = La.polar(F, U, sc, V)                  # U V^T with a derivative finite at F = I
                return R @ (scalar(0.5) * (T1 + wp.transpose(T1)))

        return response, mlp

    @wp.func
    def sv(F: mat, U: mat, s: vec, V: mat):
        """The singular values s of U, s, V = svd_const(F), with the derivative ds_i = (U^T dF V)_ii
        (``La.singular_values``' without its second SVD); nothing flows back to U, s, V."""
        return s

    @wp.func_grad(sv)
    def adj_sv(F: mat, U: mat, s: vec, V: mat, adj_ret: vec):
        wp.adjoint[F] += U @ La.diag(adj_ret) @ wp.transpose(V)

    @wp.func
    def plain_features(F: mat):
        """no_rotation: z = vec(F - I) (no_undeformed: vec F)."""
        h = scalar(shift)
        if wp.static(dim == 3):
            return vin(F[0, 0] - h, F[0, 1], F[0, 2], F[1, 0], F[1, 1] - h, F[1, 2], F[2, 0], F[2, 1], F[2, 2] - h)
        else:
            return vin(F[0, 0] - h, F[0, 1], F[1, 0], F[1, 1] - h)

    @wp.func
    def features(F: mat, U: mat, sc: vec, V: mat):
        """z = [sigma - 1, vec(F^T F - I), det F - 1] (no_undeformed: unshifted), sigma = sc of F's SVD."""
        h = scalar(shift)
        s = sv(F, U, sc, V)                  # d s_i = (U^T dF V)_ii: finite at repeated values
        C = wp.transpose(F) @ F
        J = wp.determinant(F)
        # F^T F = I exactly means sigma = 1 exactly, which the iterative svd3 misses by ~1e-17: take the
        # exact value there (s - sc is 0 with the derivative d s), so tau(I) = 0 bit for bit
        rest = int(1)
        for i in range(dim):
            for j in range(dim):
                if C[i, j] != wp.where(i == j, scalar(1.0), scalar(0.0)):
                    rest = 0
        if rest == 1:
            s = vec(scalar(1.0)) + (s - sc)
        if wp.static(dim == 3):
            return vin(s[0] - h, s[1] - h, s[2] - h, C[0, 0] - h, C[0, 1], C[0, 2], C[1, 0], C[1, 1] - h, C[1, 2],
                       C[2, 0], C[2, 1], C[2, 2] - h, J - h)
        else:
            return vin(s[0] - h, s[1] - h, C[0, 0] - h, C[0, 1], C[1, 0], C[1, 1] - h, J - h)

    @wp.func
    def as_matrix(o: vout):
        """T1 from the network output, row-major (as torch's view(-1, 3, 3))."""
        if wp.static(dim == 3):
            return mat(o[0], o[1], o[2], o[3], o[4], o[5], o[6], o[7], o[8])
        else:
            return mat(o[0], o[1], o[2], o[3])

    elastic, mlp_e = network(True)
    plastic, mlp_p = network(False)

    @wp.func
    def kirchhoff(s: LawState, prm: Params, w: Weights):
        return elastic(s.F, w) @ wp.transpose(s.F)         # tau = P F^T, P = R T (Alg. 4 line 6)

    @wp.func
    def update(s: LawState, grad_v: mat, dt: scalar, prm: Params, w: Weights):
        out = s
        Ft = (wp.identity(dim, scalar) + dt * grad_v) @ s.F
        out.F = Ft + scalar(alpha) * plastic(Ft, w)        # Alg. 4 line 9; App. C.3 Eq. 34
        return out

    # the kernels that call these functions (the fused G2P + law kernel, the law's own kernels): -O3 and
    # FMA contraction across statements on the CPU (Warp emits each multiply and add as its own
    # statement, so -ffp-contract=on fuses none of the MLP's 64-wide multiply-adds); see the module doc
    cpu_flags = (wp.config.cpu_compiler_flags or "-march=native") + " -ffp-contract=fast"
    return SimpleNamespace(kirchhoff=kirchhoff, update=update, elastic=elastic, plastic=plastic, mlp_e=mlp_e,
                           features=features, vin=vin,
                           module_options={"optimization_level": 3, "cpu_compiler_flags": cpu_flags})
