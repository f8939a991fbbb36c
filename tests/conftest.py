"""Shared fixtures. Importing this does not import JAX or Warp until a test asks for a backend."""
import os
import sys

os.environ.setdefault("WARP_QUIET", "1")

# One persistent JAX compilation cache for the whole run, shared by the xdist workers and the CLI
# subprocesses (they inherit the environment): many tests build the same small scene in separate
# steppers or processes, and each would otherwise compile the same program again (keyed by the HLO,
# the compile options and jaxlib's version, so a hit is the same executable). About a third of the
# suite's time is XLA compiling; a test that needs a cold compile sets its own directory.
if "JAX_COMPILATION_CACHE_DIR" not in os.environ:
    import tempfile

    os.environ["JAX_COMPILATION_CACHE_DIR"] = os.path.join(tempfile.gettempdir(), f"mpmlab-tests-jax-cache-{os.getuid()}")
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0.2")

# absl (imported by JAX/optax) binds its log handler to the sys.stderr of the moment it is first
# imported: inside a test, that is pytest's capture stream. A later in-process `mpmlab` run has Hydra
# reconfigure logging, which closes every handler, and absl's close() closes any stream that is not
# the current sys.stderr/stdout: pytest's own capture file, which ends the whole session ("lost
# sys.stderr"). Bind absl to the real stderr once, before any test runs.
try:
    from absl import logging as _absl_logging

    _absl_logging.get_absl_handler().python_handler.stream = sys.__stderr__
except ImportError:  # pragma: no cover - absl comes with JAX
    pass


def pytest_collection_modifyitems(config, items):
    """``@pytest.mark.full`` cases run only with MPMLAB_FULL_TESTS=1 (or MPMLAB_FULL_ADJOINT_TESTS=1): the
    rest of a matrix whose default run keeps one case per code path, so that CI stays within its time."""
    import pytest

    if any(os.environ.get(k, "") not in ("", "0") for k in ("MPMLAB_FULL_TESTS", "MPMLAB_FULL_ADJOINT_TESTS")):
        return
    skip = pytest.mark.skip(reason="more of a sampled matrix: set MPMLAB_FULL_TESTS=1 to run it")
    for item in items:
        if "full" in item.keywords:
            item.add_marker(skip)
