"""Warp NCLaw (Ma et al. 2023, App. C Alg. 4), built per (law instance, dim, precision).

The two networks are evaluated inside the kernels (the law update is fused into G2P) as one
``@wp.func`` each. How (``FORM``; measured in ``benchmarks/nclaw_warp.py``):

* ``"adjoint"`` (the default): loops over the hidden units are dynamic (compact code) and the MLP has
  a hand-written adjoint (``wp.func_grad``: recompute the activations, back-propagate layer by layer,
  accumulate the weight gradients with ``wp.atomic_add``). Warp's own adjoint of a dynamic loop that
  accumulates into a scalar is wrong in Warp 1.19 (0.7 % on mlp_elastic's dtau/dF), so the automatic
  one is not used for these loops.
* ``"unrolled"``: every loop ``range(wp.static(n))`` with Warp's automatic adjoint (mlp_elastic's
  form); about 5,500 multiply-adds per network are unrolled, forward and adjoint. Kept for the
  measurement only: its gradients are wrong (the writes h[i] = ... into local vectors lose their
  adjoint; measured vs jax.grad: dW2, dW3 zero, dW1 and dF 11-12 % off).

Measured (2-core CPU, 1 Warp thread, NCLaw's 1,000-particle cube, 3D MLS fp32,
``benchmarks/nclaw_warp.py``): cold build + first step 17.7 s for both forms (fixed_corotated: 15.3 s;
the nclaw G2P kernel alone ~11.5 s), forward 13.9 ms/step ("adjoint") vs 14.6 ms ("unrolled") vs
1.6 ms for fixed_corotated; JAX: 8.6 ms/step (fixed_corotated 2.7 ms). Vector/matrix types of size 64
would need the weights as matrix-typed arrays (the generated ``Weights`` struct holds scalar arrays),
and a tile kernel cannot be fused into the per-particle G2P kernel; neither was tried.
"""

import math
from functools import lru_cache
from types import SimpleNamespace

import warp as wp

from ...backends.warp.law_structs import law_types
from ...backends.warp.linalg import warp_linalg

#: how the networks are evaluated (module doc); read when a (law, dim, precision) is first built
FORM = "adjoint"
FORMS = ("adjoint", "unrolled")

_SQRT1_2 = 1.0 / math.sqrt(2.0)
_INV_SQRT_2PI = 1.0 / math.sqrt(2.0 * math.pi)


def make(law, dim: int, precision: str) -> SimpleNamespace:
    return _make(law, dim, precision, FORM)


@lru_cache(maxsize=None)
def _make(law, dim: int, precision: str, form: str) -> SimpleNamespace:
    if form not in FORMS:
        raise ValueError(f"nclaw warp FORM = {form!r}; use one of {FORMS}.")
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

    def network(elastic: bool):
        """The MLP of one network, z -> W3 gelu(W2 gelu(W1 z + b1) + b2) + b3, reading its arrays from the
        ``Weights`` struct. The struct itself is the argument (not its member arrays): inside a custom
        adjoint ``wp.adjoint[w].e_W1`` is then the weights' gradient array, while the adjoint of a member
        array passed on its own is an empty local in Warp 1.19 (measured: gradients silently lost)."""
        if form == "adjoint":
            @wp.func
            def mlp(z: vin, w: Weights):
                if wp.static(elastic):
                    W1 = w.e_W1
                    W2 = w.e_W2
                    W3 = w.e_W3
                else:
                    W1 = w.p_W1
                    W2 = w.p_W2
                    W3 = w.p_W3
                if wp.static(biases):
                    if wp.static(elastic):
                        b1 = w.e_b1
                        b2 = w.e_b2
                        b3 = w.e_b3
                    else:
                        b1 = w.p_b1
                        b2 = w.p_b2
                        b3 = w.p_b3
                h1 = vh()
                for i in range(width):
                    a = scalar(0.0)
                    if wp.static(biases):
                        a = b1[i]
                    for j in range(nin):
                        a = a + W1[i, j] * z[j]
                    h1[i] = gelu(a)
                h2 = vh()
                for i in range(width):
                    a = scalar(0.0)
                    if wp.static(biases):
                        a = b2[i]
                    for j in range(width):
                        a = a + W2[i, j] * h1[j]
                    h2[i] = gelu(a)
                out = vout()
                for o in range(nout):
                    a = scalar(0.0)
                    if wp.static(biases):
                        a = b3[o]
                    for j in range(width):
                        a = a + W3[o, j] * h2[j]
                    out[o] = a
                return out

            @wp.func_grad(mlp)
            def adj_mlp(z: vin, w: Weights, adj_ret: vout):
                if wp.static(elastic):
                    W1 = w.e_W1
                    W2 = w.e_W2
                    W3 = w.e_W3
                    G1 = wp.adjoint[w].e_W1
                    G2 = wp.adjoint[w].e_W2
                    G3 = wp.adjoint[w].e_W3
                else:
                    W1 = w.p_W1
                    W2 = w.p_W2
                    W3 = w.p_W3
                    G1 = wp.adjoint[w].p_W1
                    G2 = wp.adjoint[w].p_W2
                    G3 = wp.adjoint[w].p_W3
                if wp.static(biases):
                    if wp.static(elastic):
                        b1 = w.e_b1
                        b2 = w.e_b2
                        b3 = w.e_b3
                        B1 = wp.adjoint[w].e_b1
                        B2 = wp.adjoint[w].e_b2
                        B3 = wp.adjoint[w].e_b3
                    else:
                        b1 = w.p_b1
                        b2 = w.p_b2
                        b3 = w.p_b3
                        B1 = wp.adjoint[w].p_b1
                        B2 = wp.adjoint[w].p_b2
                        B3 = wp.adjoint[w].p_b3
                # recompute the activations
                a1 = vh()
                h1 = vh()
                for i in range(width):
                    a = scalar(0.0)
                    if wp.static(biases):
                        a = b1[i]
                    for j in range(nin):
                        a = a + W1[i, j] * z[j]
                    a1[i] = a
                    h1[i] = gelu(a)
                a2 = vh()
                h2 = vh()
                for i in range(width):
                    a = scalar(0.0)
                    if wp.static(biases):
                        a = b2[i]
                    for j in range(width):
                        a = a + W2[i, j] * h1[j]
                    a2[i] = a
                    h2[i] = gelu(a)
                # layer 3: out = W3 h2 + b3
                g2 = vh()
                for j in range(width):
                    g = scalar(0.0)
                    for o in range(nout):
                        g = g + W3[o, j] * adj_ret[o]
                        wp.atomic_add(G3, o, j, adj_ret[o] * h2[j])
                    g2[j] = g * gelu_prime(a2[j])
                if wp.static(biases):
                    for o in range(nout):
                        wp.atomic_add(B3, o, adj_ret[o])
                # layer 2: a2 = W2 h1 + b2
                g1 = vh()
                for j in range(width):
                    g = scalar(0.0)
                    for i in range(width):
                        g = g + W2[i, j] * g2[i]
                    g1[j] = g * gelu_prime(a1[j])
                for i in range(width):
                    gi = g2[i]
                    for j in range(width):
                        wp.atomic_add(G2, i, j, gi * h1[j])
                    if wp.static(biases):
                        wp.atomic_add(B2, i, gi)
                # layer 1: a1 = W1 z + b1
                gz = vin()
                for i in range(width):
                    gi = g1[i]
                    for j in range(nin):
                        gz[j] = gz[j] + W1[i, j] * gi
                        wp.atomic_add(G1, i, j, gi * z[j])
                    if wp.static(biases):
                        wp.atomic_add(B1, i, gi)
                wp.adjoint[z] += gz
        else:
            # every loop unrolled, Warp's automatic adjoint (timing comparison only: the in-place writes
            # h[i] = ... into local vectors lose their adjoint in Warp 1.19, so its gradients are wrong)
            @wp.func
            def mlp(z: vin, w: Weights):
                if wp.static(elastic):
                    W1 = w.e_W1
                    W2 = w.e_W2
                    W3 = w.e_W3
                else:
                    W1 = w.p_W1
                    W2 = w.p_W2
                    W3 = w.p_W3
                if wp.static(biases):
                    if wp.static(elastic):
                        b1 = w.e_b1
                        b2 = w.e_b2
                        b3 = w.e_b3
                    else:
                        b1 = w.p_b1
                        b2 = w.p_b2
                        b3 = w.p_b3
                h1 = vh()
                for i in range(wp.static(width)):
                    a = scalar(0.0)
                    if wp.static(biases):
                        a = b1[i]
                    for j in range(wp.static(nin)):
                        a = a + W1[i, j] * z[j]
                    h1[i] = gelu(a)
                h2 = vh()
                for i in range(wp.static(width)):
                    a = scalar(0.0)
                    if wp.static(biases):
                        a = b2[i]
                    for j in range(wp.static(width)):
                        a = a + W2[i, j] * h1[j]
                    h2[i] = gelu(a)
                out = vout()
                for o in range(wp.static(nout)):
                    a = scalar(0.0)
                    if wp.static(biases):
                        a = b3[o]
                    for j in range(wp.static(width)):
                        a = a + W3[o, j] * h2[j]
                    out[o] = a
                return out

        # the network input and T1 are built with constructors, not component assignment: Warp 1.19's
        # automatic adjoint drops in-place writes into local vectors/matrices (measured: zero gradients)
        @wp.func
        def response(F: mat, w: Weights):
            """Y = R T, T = sym(T1), T1 = NN(sigma - 1, vec(F^T F - I), det F - 1) (Alg. 4 lines 1-5);
            ``no_rotation``: T1 = NN(vec(F - I)) as is."""
            T1 = as_matrix(mlp(features(F), w))
            if wp.static(no_rot):
                return T1
            else:
                U, sc, V = La.svd_const(F)
                R = La.polar(F, U, sc, V)                      # U V^T with a derivative finite at F = I
                return R @ (scalar(0.5) * (T1 + wp.transpose(T1)))

        return response, mlp

    @wp.func
    def features(F: mat):
        """z = [sigma - 1, vec(F^T F - I), det F - 1] (no_undeformed: unshifted); no_rotation: vec(F - I)."""
        h = scalar(shift)
        if wp.static(no_rot):
            if wp.static(dim == 3):
                return vin(F[0, 0] - h, F[0, 1], F[0, 2], F[1, 0], F[1, 1] - h, F[1, 2], F[2, 0], F[2, 1], F[2, 2] - h)
            else:
                return vin(F[0, 0] - h, F[0, 1], F[1, 0], F[1, 1] - h)
        else:
            s = La.singular_values(F)            # d s_i = (U^T dF V)_ii: finite at repeated values
            C = wp.transpose(F) @ F
            J = wp.determinant(F)
            # F^T F = I exactly means sigma = 1 exactly, which the iterative svd3 misses by ~1e-17: take
            # the exact value there (s - s_const is 0 with the derivative d s), so tau(I) = 0 bit for bit
            rest = int(1)
            for i in range(dim):
                for j in range(dim):
                    if C[i, j] != wp.where(i == j, scalar(1.0), scalar(0.0)):
                        rest = 0
            if rest == 1:
                U0, s0, V0 = La.svd_const(F)
                s = vec(scalar(1.0)) + (s - s0)
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

    return SimpleNamespace(kirchhoff=kirchhoff, update=update, elastic=elastic, plastic=plastic)
