"""Hydra config groups contributed to mpmlab (found through the ``mpmlab.configs`` entry point)."""
