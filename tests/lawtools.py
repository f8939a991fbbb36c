"""Evaluate a law's kirchhoff/update on batches, on the NumPy reference, JAX or Warp (test helper).

The evaluators live in ``mpmlab.testing.evaluate`` (the conformance kit); these are the names the
law tests import, with parameters given as a row in declared order or by name."""
from __future__ import annotations

import numpy as np

from mpmlab.testing._common import resolve_params
from mpmlab.testing.evaluate import EVAL, jax_law, ref_kirchhoff  # noqa: F401


def default_params(law) -> np.ndarray:
    """The law's declared defaults, as a row in declared order."""
    prm = resolve_params(law, "defaults")
    return np.array([prm[k] for k in law.param_names()])
