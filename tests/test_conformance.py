"""JAX and Warp give the same trajectory for every registered law x transfer x dimension.

One multi-material scene per (transfer, dim) holds a body of every registered law, built-in or
installed plugin, each with its own ``Law.test_params`` (``mpmlab.testing.law_scene``), so the
assertions are parametrised per law (ids name the law, transfer and dimension) while each backend
compiles one step per (transfer, dim) -- the suite stays small on 2 cores. fp64: relative
difference <= 1e-9 after 50 steps (issue #2; ``mpmlab.testing.check_backends_agree``). fp32:
positions within 1e-5 of the fp64 scale (stated tolerance: fp32 round-off in different summation
orders -- atomics vs scatter -- compounds over 50 steps).
"""
import numpy as np
import pytest

from mpmlab import testing
from mpmlab.core import registry

TRANSFERS = registry.transfers.names()
LAWS = registry.laws.names()
STEPS = 50


def laws_for(transfer):
    """The laws paired with ``transfer`` (a law's ``test_transfers``; None: every transfer): a neural
    law's fused kernels compile slowly, so it declares a few transfers and the scenes of the others
    leave it out."""
    return [n for n in LAWS if registry.laws.get(n).test_transfers is None
            or transfer in registry.laws.get(n).test_transfers]


CASES = [(law, transfer) for transfer in TRANSFERS for law in laws_for(transfer)]


def run(backend, transfer, dim, precision):
    return testing.rollout(laws_for(transfer), backend, transfer, dim, precision, STEPS)


@pytest.mark.parametrize("dim", (2, 3))
@pytest.mark.parametrize("law,transfer", CASES)
def test_jax_warp_agree_fp64(law, transfer, dim):
    testing.check_backends_agree(law, transfer, dim, steps=STEPS, tol=1e-9, scene_laws=laws_for(transfer))


@pytest.mark.parametrize("dim", (2, 3))
@pytest.mark.parametrize("transfer", ("pic", "mls"))
def test_jax_warp_agree_fp32(transfer, dim):
    a = run("jax", transfer, dim, "fp32")
    b = run("warp", transfer, dim, "fp32")
    ref = run("jax", transfer, dim, "fp64")
    assert np.max(np.abs(a.x[-1] - b.x[-1])) <= 1e-5 * np.max(np.abs(ref.x[-1]))
    assert np.max(np.abs(a.x[-1] - ref.x[-1])) <= 1e-5 * np.max(np.abs(ref.x[-1]))
