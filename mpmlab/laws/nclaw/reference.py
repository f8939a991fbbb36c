"""NumPy float64 reference of NCLaw (Ma et al. 2023, App. C Alg. 4), the conformance oracle.

The functions take the law instance as ``law=`` (its options: variant, alpha); the conformance kit
passes it to references that accept it. Without it, the default configuration is used.
"""
from __future__ import annotations

import math

import numpy as np
from scipy.special import erf

from .._linalg_np import svd_rotations

_SQRT1_2 = 1.0 / math.sqrt(2.0)
_INV_SQRT_2PI = 1.0 / math.sqrt(2.0 * math.pi)


def _law(law):
    if law is None:
        from . import Law

        return Law()
    return law


def gelu(x):
    """Exact (erf) GELU, torch.nn.GELU()'s default: x Phi(x)."""
    return 0.5 * x * (1.0 + erf(x * _SQRT1_2))


def gelu_prime(x):
    return 0.5 * (1.0 + erf(x * _SQRT1_2)) + x * _INV_SQRT_2PI * np.exp(-0.5 * x * x)


def mlp(z, w, net: str, biases: bool):
    """W3 gelu(W2 gelu(W1 z + b1) + b2) + b3 (biases only with ``no_undeformed``)."""
    W = lambda k: np.asarray(w[f"{net}_{k}"], dtype=float)  # noqa: E731
    a1 = W("W1") @ z + (W("b1") if biases else 0.0)
    a2 = W("W2") @ gelu(a1) + (W("b2") if biases else 0.0)
    return W("W3") @ gelu(a2) + (W("b3") if biases else 0.0)


def features(F, law):
    """The network input (paper Sec. 3.3; App. C.2): [sigma - 1, vec(F^T F - I), det F - 1] (``no_undeformed``:
    without the shifts); ``no_rotation``: vec(F - I) (or vec F)."""
    d = len(F)
    eye = np.eye(d)
    shift = 0.0 if law.no_undeformed else 1.0
    if law.no_rotation:
        return (F - shift * eye).reshape(-1), None
    U, s, V = svd_rotations(F)
    C = F.T @ F
    if np.all(C == eye):        # F^T F = I exactly: sigma = 1 exactly (an SVD may miss it by round-off)
        s = np.ones(d)
    z = np.concatenate([s - shift, (C - shift * eye).reshape(-1), [np.linalg.det(F) - shift]])
    return z, U @ V.T


def response(F, w, net: str, law):
    """Y of Alg. 4: R T with T = sym(T1), T1 = NN(invariants of F) (``no_rotation``: T1 itself)."""
    d = len(F)
    z, R = features(F, law)
    T1 = mlp(z, w, net, law.no_undeformed).reshape(d, d)       # row-major, as torch's view(-1, 3, 3)
    if law.no_rotation:
        return T1
    return R @ (0.5 * (T1 + T1.T))


def kirchhoff(state, prm, w, law=None):
    """tau = P F^T with P = R T_e(F) (Alg. 4 line 6, Alg. 2 line 1; the release returns P F^T)."""
    law = _law(law)
    F = np.asarray(state["F"], dtype=float)
    return response(F, w, "e", law) @ F.T


def update(state, grad_v, dt, prm, w, law=None):
    """F_trial = (I + dt grad_v) F; F <- F_trial + alpha R T_p(F_trial) (Alg. 2 line 3, Alg. 4 line 9,
    App. C.3 Eq. 34)."""
    law = _law(law)
    F = np.asarray(state["F"], dtype=float)
    Ft = (np.eye(len(F)) + dt * np.asarray(grad_v, dtype=float)) @ F
    return {"F": Ft + float(law.alpha) * response(Ft, w, "p", law)}


def rest_tangent(w, dim: int, law=None, net: str = "e"):
    """C_ijkl = d tau_ij / d F_kl at F = I (= dP/dF there when the rest stress vanishes), with the
    singular values' derivative of the backends at U = V = I: d sigma_i = dF_ii (sigma is not
    differentiable at F = I: along a non-diagonal dF it moves by the sorted eigenvalues of sym(dF); this
    is the one-sided convention the gradients use, an estimate for the CFL bound). Exact otherwise: the
    network's Jacobian at the rest input is W3 diag(gelu'(a2)) W2 diag(gelu'(a1)) W1."""
    law = _law(law)
    eye = np.eye(dim)
    z0, _ = features(eye, law)
    b = law.no_undeformed
    W = lambda k: np.asarray(w[f"{net}_{k}"], dtype=float)  # noqa: E731
    a1 = W("W1") @ z0 + (W("b1") if b else 0.0)
    a2 = W("W2") @ gelu(a1) + (W("b2") if b else 0.0)
    Jn = W("W3") @ (gelu_prime(a2)[:, None] * (W("W2") @ (gelu_prime(a1)[:, None] * W("W1"))))
    T1_0 = mlp(z0, w, net, b).reshape(dim, dim)
    T0 = T1_0 if law.no_rotation else 0.5 * (T1_0 + T1_0.T)
    C = np.zeros((dim, dim, dim, dim))
    for k in range(dim):
        for l in range(dim):
            dF = np.zeros((dim, dim))
            dF[k, l] = 1.0
            if law.no_rotation:
                dz = dF.reshape(-1)
            else:
                dz = np.concatenate([np.diag(dF), (dF.T + dF).reshape(-1), [np.trace(dF)]])
            dT1 = (Jn @ dz).reshape(dim, dim)
            if law.no_rotation:
                dP = dT1
            else:
                dP = 0.5 * (dF - dF.T) @ T0 + 0.5 * (dT1 + dT1.T)   # dR = skew(dF) at F = I
            C[:, :, k, l] = dP + T0 @ dF.T                           # tau = P F^T, P(I) = R(I) T0 = T0
    return C
