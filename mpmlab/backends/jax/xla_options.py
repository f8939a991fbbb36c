"""XLA CPU options for reverse-mode work.

XLA CPU (jaxlib 0.10) fuses some element-wise/reduction chains into YNNPACK calls. For the transposed
P2G force scatter of the backward pass these fusions are about 2x slower than XLA's own loops
(benchmarks/gradients.py: fwd+bwd / fwd 10-12x with them, 5.4-6.5x without), while forward-only runs
gain or lose a few per cent depending on the law. XLA reads ``XLA_FLAGS`` once, when the CPU client is
created, so ``task=inverse`` calls :func:`disable_ynn_fusions` before its first JAX computation.
"""
from __future__ import annotations

import logging
import os

log = logging.getLogger("mpmlab")
YNN_FLAG = "--xla_cpu_experimental_ynn_fusion_type="


def disable_ynn_fusions() -> bool:
    """Add ``--xla_cpu_experimental_ynn_fusion_type=`` (no YNNPACK fusions) to ``XLA_FLAGS``.

    Leaves ``XLA_FLAGS`` alone when it already sets that option (the user's choice wins) and returns
    False when the CPU client already exists (the flag would not take effect in this process)."""
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_cpu_experimental_ynn_fusion_type" in flags:
        return False
    from jax._src import xla_bridge

    if getattr(xla_bridge, "_backends", None):
        log.info("XLA backends already initialised: YNNPACK fusions stay as they are in this process")
        return False
    os.environ["XLA_FLAGS"] = (flags + " " + YNN_FLAG).strip()
    return True
