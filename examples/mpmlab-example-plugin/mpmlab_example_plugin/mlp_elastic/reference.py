"""NumPy float64 reference of the MLP hyperelastic law (the conformance oracle)."""
from __future__ import annotations

import numpy as np


def kirchhoff(state, prm, w):
    F = state["F"]
    d = len(F)
    eye = np.eye(d)
    B = F @ F.T
    J = np.linalg.det(F)
    z = np.array([np.trace(B) - d, J - 1.0])
    a, b = np.asarray(w["W2"]) @ np.tanh(np.asarray(w["W1"]) @ z)
    c = np.asarray(w["c"])
    return prm["stress_scale"] * ((c[0] + b) * (B - eye) + (c[1] * (J - 1.0) + a) * eye)


def update(state, grad_v, dt, prm, w):
    F = state["F"]
    return {"F": (np.eye(len(F)) + dt * grad_v) @ F}
