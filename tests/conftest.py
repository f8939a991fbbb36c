"""Shared fixtures. Importing this does not import JAX or Warp until a test asks for a backend."""
import os
import sys

os.environ.setdefault("WARP_QUIET", "1")

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
