"""Input/output: HDF5 trajectories (``mpmlab.trajectory`` v1), rerun recordings, per-frame metrics and
the LagrangeBench export.

Names are imported lazily, so ``import mpmlab.io`` costs nothing until one is used (h5py and rerun
are imported by the submodules ``mpmlab.io.h5`` and ``mpmlab.io.rerun``).
"""
from __future__ import annotations

import importlib

_EXPORTS = {
    "write_trajectory": "h5", "read_trajectory": "h5", "read_attrs": "h5", "TrajectoryWriter": "h5",
    "export_lagrangebench": "lagrangebench", "SCHEMA": "h5", "SCHEMA_VERSION": "h5",
    "write_recording": "rerun", "RecordingWriter": "rerun", "read_recording_positions": "rerun",
    "read_recording_metrics": "rerun", "read_recording_component": "rerun", "color_choices": "rerun",
    "read_particle_values": "rerun", "read_blueprint_views": "rerun", "read_series_names": "rerun",
    "EpochRecorder": "rerun", "write_comparison_recording": "rerun", "open_trajectory": "h5",
    "compute_metrics": "metrics", "frame_metrics": "metrics", "state_metrics": "metrics",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(importlib.import_module(f".{_EXPORTS[name]}", __name__), name)
    raise AttributeError(f"module 'mpmlab.io' has no attribute '{name}'")


def __dir__():
    return sorted(set(globals()) | set(_EXPORTS))
