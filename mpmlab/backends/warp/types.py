"""Warp vector/matrix/struct types per (dimension, precision), created once and cached.

Every Warp kernel and law function in mpmlab is built by a factory over these types, so one
source serves 2D/3D and fp32/fp64 (Warp's kernel-factory pattern).
"""

from functools import lru_cache
from types import SimpleNamespace

import warp as wp

# Warp 1.19 prints a line per module compile/load at INFO; mpmlab keeps the console for its own output
# (``debug=true`` on the CLI turns them back on).
wp.config.log_level = wp.LOG_WARNING
wp.config.quiet = True

SCALARS = {"fp32": wp.float32, "fp64": wp.float64}


@lru_cache(maxsize=None)
def warp_types(dim: int, precision: str) -> SimpleNamespace:
    scalar = SCALARS[precision]
    vec = wp.types.vector(dim, scalar)
    mat = wp.types.matrix((dim, dim), scalar)
    # per-law structs (LawState, Params, Weights) are generated from each law's declarations: law_types.py
    return SimpleNamespace(dim=dim, precision=precision, scalar=scalar, vec=vec, mat=mat,
                           ivec=wp.types.vector(dim, wp.int32))
