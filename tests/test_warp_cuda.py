"""Warp's CUDA form of the step (atomic P2G into one grid, whole-grid update), checked on the CPU.

On CUDA every particle of a P2G launch runs at once into one grid, so the node sums must be atomic;
the CPU form adds without atomics into one private grid copy per thread. A GPU run once showed the
CPU form racing there (``benchmarks/gpu.md``). The CUDA form runs on the CPU too (Warp's CPU atomics
are plain adds), so CI checks that it computes the same step; where a GPU exists, the CUDA device
itself is compared with the CPU.
"""
import numpy as np
import pytest

from mpmlab.simulator import build_stepper
from tests.scenes import all_laws_scene

STEPS = 20


def _final(scene, **options):
    st = build_stepper(scene, "warp", "apic", "fp64", **options)
    traj = st.rollout(steps=STEPS, every=STEPS, progress=False)
    return st, np.concatenate([traj.x[-1], traj.v[-1]], axis=1)


@pytest.fixture(scope="module")
def scene():
    return all_laws_scene(2)


@pytest.fixture(scope="module")
def cpu_result(scene):
    return _final(scene, device="cpu")[1]


@pytest.mark.parametrize("threads", [1, 2])
def test_atomic_p2g_matches_the_cpu_form(scene, cpu_result, threads):
    st, got = _final(scene, device="cpu", p2g_atomic=True, threads=threads)
    assert st.p2g_atomic and st._bbox_np is None          # the CUDA form: no bounding box, whole grid
    np.testing.assert_allclose(got, cpu_result, rtol=0, atol=1e-12)


def test_device_picks_the_p2g_form(scene):
    st = build_stepper(scene, "warp", "apic", "fp64", device="cpu")
    assert not st.p2g_atomic and st._bbox_np is not None


def _cuda_available() -> bool:
    import warp as wp

    wp.init()
    return wp.is_cuda_available()


def test_cuda_matches_cpu(scene, cpu_result):
    if not _cuda_available():
        pytest.skip("no CUDA device here (the GPU run's numbers are in benchmarks/gpu.md)")
    st, got = _final(scene, device="cuda:0")
    assert st.p2g_atomic
    np.testing.assert_allclose(got, cpu_result, rtol=0, atol=1e-10)
