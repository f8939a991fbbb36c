"""Shared fixtures. Importing this does not import JAX or Warp until a test asks for a backend."""
import os

os.environ.setdefault("WARP_QUIET", "1")
