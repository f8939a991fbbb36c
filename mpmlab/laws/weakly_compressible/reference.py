"""NumPy float64 reference of the weakly compressible fluid (NCLaw App. B, Eqs. 20-21), the conformance
oracle. The state is J alone (see ``Law``), so ``kirchhoff`` needs the dimension ``dim`` passed in."""
from __future__ import annotations

import numpy as np

from .._common import named_params


def _named(prm):
    """Parameters by name (a mapping, or an array in the law's declared order)."""
    from . import Law

    return named_params(prm, Law.param_names())


def kirchhoff(state, prm, w=None, dim=None):
    """tau = P F^T = lambda J (J - 1) I (NCLaw Eq. 20 with lambda = bulk_modulus, mu = 0).

    A scalar J carries no dimension, so ``dim`` (2 or 3) is required.
    """
    prm = _named(prm)
    if dim is None:
        raise TypeError("weakly_compressible.reference.kirchhoff: the law state is J alone; pass dim=2 or dim=3.")
    J = state["J"]
    return prm["bulk_modulus"] * J * (J - 1.0) * np.eye(dim)


def update(state, grad_v, dt, prm, w=None):
    """J <- J det(I + dt grad_v): what F <- (I + dt grad_v) F followed by Eq. 21's projection
    F <- J^(1/d) I gives, since det(J^(1/d) I) = J and tau depends on F only through J."""
    prm = _named(prm)
    return {"J": state["J"] * np.linalg.det(np.eye(len(grad_v)) + dt * grad_v)}
