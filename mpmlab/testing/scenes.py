"""Small scenes for the kit (tiny, so a plugin's checks run on a laptop CPU in seconds).

``law_scene``: one small body per law, spinning and moving, falling onto 2-cell walls of a unit box
(six bodies per row; further laws go into rows above, the box grows). ``gradient_scene``: one block
of 36 particles (2D) away from every wall for the gradient horizon."""
from __future__ import annotations

import numpy as np

from ._common import DENSITY, ensure_registered, law_class, options_of, params_of

#: bodies per row of ``law_scene``; the first row is the historical ``tests/scenes.py`` layout
PER_ROW = 6
ROW_HEIGHT = 0.35


def _laws(laws) -> list:
    if isinstance(laws, (str, type)) or not hasattr(laws, "__iter__"):
        return [laws]
    return list(laws)


def law_scene(laws, dim: int, *, dt: float = 1e-3, params=None, name: str | None = None):
    """One small body (0.08 wide, 2^D particles per cell, density 1000) per law in ``laws`` (a name,
    class or instance, or a list of them), with a spin (2 rad/s; 3D: (0, 1, 2)), a sideways velocity
    (+-0.3 m/s) and -0.5 m/s downwards, under gravity, in a unit box with 2-cell ``separate`` walls
    (dx = 0.05). Parameters: each law's ``test_params`` (``params``: {law name: {...}} overrides),
    options: ``test_options`` (an instance: its own fields)."""
    import mpmlab
    from mpmlab.boundaries import Walls

    laws = _laws(laws)
    rows = (len(laws) + PER_ROW - 1) // PER_ROW
    bodies = []
    dx = 0.05
    for k, law in enumerate(laws):
        reg = ensure_registered(law)
        c = np.full(dim, 0.5)
        c[0] = 0.15 + 0.14 * (k % PER_ROW)
        c[1] = 0.2 + 0.05 * (k % 3) + ROW_HEIGHT * (k // PER_ROW)
        h = 0.04
        w = 2.0 if dim == 2 else [0.0, 1.0, 2.0]
        v = np.zeros(dim); v[0] = 0.3 * (-1) ** k; v[1] = -0.5
        prm = (params or {}).get(reg, params_of(law))
        bodies.append(mpmlab.Body(shape={"kind": "box", "lo": (c - h).tolist(), "hi": (c + h).tolist()},
                                  material=reg, params=prm, density=DENSITY, velocity=v.tolist(),
                                  angular_velocity=w, particles_per_cell=2**dim, name=reg,
                                  options=options_of(law)))
    hi = [1.0] * dim
    hi[1] = 1.0 + ROW_HEIGHT * (rows - 1)
    g = np.zeros(dim); g[1] = -9.8
    if name is None:
        name = (f"law_scene_{law_class(laws[0]).name}_{dim}d" if len(laws) == 1
                else f"law_scene_{len(laws)}_laws_{dim}d")
    return mpmlab.Scene(dim=dim, dx=dx, domain=([0.0] * dim, hi), bodies=bodies, gravity=g.tolist(),
                        boundaries=[Walls(default="separate", thickness=2)], dt=dt, name=name)


def gradient_scene(law, dim: int = 2, *, dt: float = 1e-3):
    """One block [0.4, 0.55]^2 (3D: [0.4, 0.5]^3) of the law at rest, 2^D particles per cell, in a unit
    box with ``separate`` walls, gravity -9.8: the controls' sheared velocity (``gradients.SHEAR``)
    loads it so plastic laws yield, and no particle meets a wall within the gradient horizon."""
    import mpmlab
    from mpmlab.boundaries import Walls

    reg = ensure_registered(law)
    lo, hi = [0.4] * dim, [0.55 if dim == 2 else 0.5] * dim
    g = [0.0, -9.8] + [0.0] * (dim - 2)
    body = mpmlab.Body(shape={"kind": "box", "lo": lo, "hi": hi}, material=reg, params=params_of(law),
                       density=DENSITY, particles_per_cell=2**dim, options=options_of(law))
    return mpmlab.Scene(dim=dim, dx=0.05, domain=([0.0] * dim, [1.0] * dim), bodies=[body], gravity=g,
                        boundaries=[Walls(default="separate", thickness=2)], dt=dt, name=f"grad_{reg}")
