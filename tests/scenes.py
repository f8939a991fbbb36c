"""Tiny scenes shared by tests (small sizes: the suite runs on 2 CPU cores).

The laws' test parameters live on the law classes (``Law.test_params``), the scene builder in
``mpmlab.testing.law_scene``; this module keeps the names other tests and the benchmarks import."""
from __future__ import annotations

from mpmlab.core import registry
from mpmlab.testing import law_scene

#: the built-in laws, in the order of their bodies in ``all_laws_scene``
BUILTIN_LAWS = ("fixed_corotated", "hencky_drucker_prager", "hencky_von_mises", "weakly_compressible",
                "newtonian_fluid", "drucker_prager_jaumann")
#: the built-in laws' ``Law.test_params`` (parameters that make them deform and, for plastic laws,
#: yield within 50 steps)
LAW_PARAMS = {name: dict(registry.laws.get(name).test_params) for name in BUILTIN_LAWS}


def all_laws_scene(dim: int, laws=None, dt: float = 1e-3):
    """One small body per law (default: the built-ins), spinning and moving, falling onto 2-cell walls
    of a unit box (``mpmlab.testing.law_scene``, each law with its ``test_params``)."""
    return law_scene(list(laws or BUILTIN_LAWS), dim, dt=dt, name=f"all_laws_{dim}d")
