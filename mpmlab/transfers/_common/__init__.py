"""Pieces several built-in schemes share (per backend): the gradient force and APIC's affine field."""


def builtin_implementations(name: str) -> dict:
    """The ``implementations`` of built-in scheme ``name``: its own folder's backend modules."""
    return {"jax": f"mpmlab.transfers.{name}.jax:make", "warp": f"mpmlab.transfers.{name}.warp:make"}
