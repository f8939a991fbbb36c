"""A conveyor-belt floor: the example of a plugin boundary that is differentiable on both backends.

Grid nodes within ``thickness`` cells of the floor (the y- face) take the belt's tangential velocity
``speed`` along x and lose any velocity into the floor (v_y < 0 -> 0; separating motion is kept). The
belt speed is the boundary's differentiable datum: ``controls()["boundary"][i]["speed"]`` on both
backends (JAX differentiates its function; Warp records its ``tape()`` kernel on the tape).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from mpmlab.core.errors import ConfigError
from mpmlab.core.interfaces import AbstractBoundary


@dataclass(frozen=True)
class Conveyor(AbstractBoundary):
    name: ClassVar[str] = "conveyor"
    stage: ClassVar[str] = "grid"
    implementations: ClassVar[dict] = {"jax": "mpmlab_example_plugin.conveyor.jax:conveyor",
                                       "warp": "mpmlab_example_plugin.conveyor.warp:conveyor"}
    gradients: ClassVar[tuple] = ("jax", "warp")
    #: belt speed along x [m/s]
    speed: float = 0.1
    #: floor layer, in cells
    thickness: int = 2

    def validate(self, scene) -> None:
        if not 1 <= int(self.thickness) <= min(scene.cells) // 2:
            raise ConfigError(f"boundary 'conveyor': thickness = {self.thickness} cells must be in "
                              f"[1, {min(scene.cells) // 2}].")
