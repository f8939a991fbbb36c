"""Built-in grid shape functions, one folder per shape function (like ``mpmlab/transfers/``).

A shape function is the transfer's second choice (``transfer: {name: apic, shape: cubic}``; issue 19):
the weights a particle gives its grid nodes. Each folder holds the declaration (``__init__.py``: window
width and offset, APIC's D_p, whether the weights need the particle's size), the 1-D formulas once for
NumPy and JAX (``reference.py``, written against an array module) and the Warp ``@wp.func``
(``warp.py``). ``AbstractShape`` documents the contract.

=========== ====== =========================================================== ================
shape       window  1-D weight N(r), r = x_p - x_i in cells                      D_p
=========== ====== =========================================================== ================
quadratic    3      quadratic B-spline (Steffen et al. 2008; JAX-MPM Eq. 9)    dx^2/4 I
cubic        4      cubic B-spline (Steffen et al. 2008)                       dx^2/3 I
ugimp        3      hat * box of half width lp (Bardenhagen & Kober 2004)      per particle
cpdi         --     particle-domain corners (Sadeghirad et al. 2011)            not implemented
=========== ====== =========================================================== ================

A new shape function: a folder of your package like these, registered under the ``mpmlab.shapes``
entry-point group.
"""
from __future__ import annotations

from ..core.errors import InvalidParameterError
from ..core.interfaces import AbstractShape
from .cpdi import Shape as ShapeCPDI
from .cubic import Shape as ShapeCubic
from .quadratic import Shape as ShapeQuadratic
from .ugimp import Shape as ShapeUGIMP

BUILTIN = {"quadratic": ShapeQuadratic, "cubic": ShapeCubic, "ugimp": ShapeUGIMP, "cpdi": ShapeCPDI}

__all__ = ["AbstractShape", "BUILTIN", "make_shape"]


def builtin_implementations(name: str) -> dict:
    """The ``implementations`` of built-in shape ``name``: its own folder's backend modules."""
    return {"jax": f"mpmlab.shapes.{name}.jax:make", "warp": f"mpmlab.shapes.{name}.warp:make"}


def make_shape(shape="quadratic", **options) -> AbstractShape:
    """A registered shape function by name (an ``AbstractShape`` instance is returned as it is)."""
    if isinstance(shape, AbstractShape):
        return shape
    from ..core import registry

    cls = registry.shapes.get(shape)
    try:
        return cls(**options)
    except TypeError:
        raise InvalidParameterError(
            f"shape function '{shape}' does not take options {sorted(options)}; "
            f"it takes {sorted(getattr(cls, '__dataclass_fields__', {}))}."
        ) from None
