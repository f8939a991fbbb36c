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
cpdi        2^D x 2  linear hat at the domain's corners (Sadeghirad et al. 2011)  per particle
=========== ====== =========================================================== ================

A new shape function: a folder of your package like these, registered under the ``mpmlab.shapes``
entry-point group. A separable one (a product over axes of one 1-D N(r)) writes only N, N', N'' for Warp
and returns ``mpmlab.shapes._common.warp.separable(...)`` from its ``warp.make``, as ``cubic`` and ``ugimp`` do.
"""
from __future__ import annotations

from ..core.errors import InvalidParameterError
from ..core.interfaces import AbstractShape
from .cpdi import Shape as ShapeCPDI
from .cubic import Shape as ShapeCubic
from .quadratic import Shape as ShapeQuadratic
from .ugimp import Shape as ShapeUGIMP

BUILTIN = {"quadratic": ShapeQuadratic, "cubic": ShapeCubic, "ugimp": ShapeUGIMP, "cpdi": ShapeCPDI}

__all__ = ["AbstractShape", "BUILTIN", "inner_bounds", "make_shape", "resolve"]

#: the half width (cells) given to a particle of zero volume (a tracer) by a shape that uses the particle
#: size: uGIMP's weights divide by lp, and as lp -> 0 they tend to the linear hat, which this is close to
LP_MIN = 1e-3


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


def resolve(shape, transfer, dim: int, dx: float, volume) -> tuple[AbstractShape, "np.ndarray | None"]:
    """The shape function a stepper builds with, checked against its transfer and its particles.

    Returns the shape instance and, for shapes that use the particle size, ``lp`` [N] (half each
    particle's initial width in cells, lp = V0^(1/D) / (2 dx); None otherwise). Refuses, in one line,
    a transfer that does not declare the shape, a shape the kernels cannot carry and a particle larger
    than the shape's window holds."""
    import numpy as np

    from ..core.errors import ConfigError

    s = make_shape(shape)
    s.check()
    allowed = getattr(transfer, "shapes", frozenset({"quadratic"}))
    if allowed is not None and s.name not in allowed:
        raise ConfigError(
            f"{transfer.describe()} declares shapes = {sorted(allowed)}: its math assumes those shape functions' "
            f"D_p, so it cannot run with shape '{s.name}'; choose one of them, or declare shapes = None in the "
            f"scheme and read D^-1 from Dinv.")
    if not s.uses_particle_size:
        return s, None
    lp = 0.5 * np.asarray(volume, np.float64) ** (1.0 / dim) / float(dx)
    if lp.size and float(lp.max()) > s.max_particle_size * (1.0 + 1e-9):
        k = int(np.argmax(lp))
        raise ConfigError(
            f"{s.describe()}: particle {k} has half width {lp[k]:.3g} cells (from its volume), more than the "
            f"{s.max_particle_size} cells its window holds; sample at least 1 particle per cell per axis "
            f"(particles_per_cell >= 1) or choose shape quadratic or cubic.")
    return s, np.clip(lp, LP_MIN, s.max_particle_size)


def inner_bounds(shape, scene, x=None, domain=None):
    """(lo, hi): the region a particle may occupy with ``shape``: its window of ``width`` nodes per axis,
    lowest node floor(x/dx - offset), must stay on the grid: offset <= x/dx < cells - (width - 2 - offset)
    (in cells from the origin). For the 3-node shapes (quadratic, uGIMP) this is ``scene.inner_bounds``
    itself; cubic B-splines lose one cell on each side; for CPDI (``kind = "corners"``) it is the region of
    the domain's corners (the whole grid, [origin, origin + cells dx)). With particle positions ``x`` [N, D]
    (and, for CPDI, their domains ``domain`` [N, D, D]), refuses (one line) a particle (a corner) outside it."""
    import numpy as np

    from ..core.errors import ConfigError

    s = make_shape(shape)
    if float(s.offset) == 0.5 and int(s.width) == 3:
        lo, hi = scene.inner_bounds
    else:
        lo = scene.origin + float(s.offset) * scene.dx
        hi = scene.origin + (np.asarray(scene.cells) - (int(s.width) - 2 - float(s.offset))) * scene.dx
    if x is not None:
        x = np.asarray(x)
        pts = x
        if s.kind == "corners":
            from .cpdi.reference import corners

            pts = np.asarray(corners(x.astype(np.float64), np.asarray(domain, np.float64))).reshape(x.shape[0], -1, x.shape[1])
        out = np.nonzero(np.any((pts < lo) | (pts >= hi), axis=tuple(range(1, pts.ndim))))[0]
        if len(out):
            k = int(out[0])
            raise ConfigError(
                f"scene '{scene.name}': particle {k} at {np.round(x[k], 6).tolist()} lies outside the region "
                f"[{np.round(lo, 6).tolist()}, {np.round(hi, 6).tolist()}) where the {s.width}-node window of "
                f"{s.describe()} stays on the grid" + (" (a corner of its domain does)" if s.kind == "corners" else "")
                + "; enlarge the domain by a cell on each side or choose shape quadratic.")
    return lo, hi
