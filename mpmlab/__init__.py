"""mpmlab: differentiable Material Point Method on swappable JAX and Warp backends.

Importing mpmlab imports neither JAX nor Warp; a backend is imported when a stepper is built.

    >>> import mpmlab
    >>> scene = mpmlab.Scene(dim=2, dx=0.05, domain=([0, 0], [1, 1]), bodies=[
    ...     mpmlab.Body(shape={"kind": "box", "lo": [0.3, 0.3], "hi": [0.6, 0.6]}, material="fixed_corotated")],
    ...     gravity=[0, -9.8], boundaries=[mpmlab.boundaries.Walls()], dt=1e-4)
    >>> traj = mpmlab.simulate(scene, steps=100, every=10, backend="jax", transfer="mls", precision="fp64")
    >>> traj.x.shape   # [frames, particles, dim]
"""
from __future__ import annotations

__version__ = "0.1.0"

from . import boundaries
from .core import registry
from .core.errors import (ConfigError, InvalidParameterError, MissingImplementationError, MpmlabError,
                          SimulationDiverged, TimeStepError, UnknownPluginError)
from .core.geometry import Box, Cylinder, Mesh, Sphere
from .core.scene import Body, Scene
from .core.state import Trajectory
from .simulator import build_stepper, simulate
from .transfers import make_transfer

__all__ = [
    "Body", "Box", "ConfigError", "Cylinder", "InvalidParameterError", "Mesh", "MissingImplementationError",
    "MpmlabError", "Scene", "SimulationDiverged", "Sphere", "TimeStepError", "Trajectory", "UnknownPluginError",
    "boundaries", "build_stepper", "make_transfer", "registry", "simulate",
]
