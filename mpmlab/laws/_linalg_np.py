"""NumPy float64 helpers shared by the law references (the conformance oracles)."""
from __future__ import annotations

import numpy as np


def svd_rotations(F: np.ndarray):
    """F = U diag(s) V^T with U, V proper rotations; the last singular value carries det(F)'s sign."""
    U, s, Vt = np.linalg.svd(F)
    V = Vt.T
    if np.linalg.det(U) < 0:
        U = U.copy(); U[:, -1] *= -1; s = s.copy(); s[-1] *= -1
    if np.linalg.det(V) < 0:
        V = V.copy(); V[:, -1] *= -1; s = s.copy(); s[-1] *= -1
    return U, s, V


def polar_rotation(F: np.ndarray) -> np.ndarray:
    U, _, V = svd_rotations(F)
    return U @ V.T


def lame(E: float, nu: float) -> tuple[float, float]:
    """(mu, lambda) from Young's modulus and Poisson ratio."""
    return E / (2.0 * (1.0 + nu)), E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))


#: Singular values are clamped to at least this before taking the Hencky log (taichi_elements' guard
#: against inverted or collapsed elements, verification note "J<=0 and inversion").
HENCKY_MIN_STRETCH = 1e-4


def hencky_strain(F: np.ndarray):
    """(U, eps = log(clamped singular values), V) for the Hencky-strain laws (NCLaw Eqs. 14-19)."""
    U, s, V = svd_rotations(F)
    return U, np.log(np.maximum(s, HENCKY_MIN_STRETCH)), V


def deviatoric_stretch(F) -> tuple[np.ndarray, np.ndarray]:
    """(max_i |log(s_i / |J|^(1/D))| [N], J = det F [N]) of ``F`` [N, D, D]; the stretch is inf where
    J <= 0 (an inverted or collapsed F) or F is not finite."""
    F = np.asarray(F, np.float64)
    D = F.shape[-1]
    finite = np.all(np.isfinite(F.reshape(len(F), -1)), axis=1)
    Fs = np.where(finite[:, None, None], F, np.eye(D))
    J = np.where(finite, np.linalg.det(Fs), np.nan)
    s = np.linalg.svd(Fs, compute_uv=False)
    ok = finite & (J > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        iso = np.log(np.where(ok[:, None], s, 1.0)) - np.log(np.where(ok, J, 1.0))[:, None] / D
    dev = np.where(ok, np.abs(iso).max(axis=1), np.inf)
    return dev, J
