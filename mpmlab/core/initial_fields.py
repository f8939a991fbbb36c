"""A body's initial fields: velocity, deformation gradient F and affine velocity C per particle.

``Body(velocity=..., F=..., C=...)`` takes, for each, any of

* a constant: ``[D]`` (velocity) or ``[D, D]`` (F, C), the same for every particle;
* an array with one entry per sampled particle: ``[N, D]`` or ``[N, D, D]`` (N: the particles this
  body samples, in sampling order);
* a callable ``f(x) -> array``: ``x`` the body's sampled positions ``[N, D]``; it returns one of the
  two forms above;
* nested lists whose entries are numbers or expression strings in the position ``x[k]`` (``X[k]`` is
  the same point: at t = 0 reference and current positions coincide) and ``pi``, e.g.
  ``["0.1 * sin(pi * x[0] / 25)", 0]`` -- the form a scene YAML uses (``mpmlab.core.expressions``,
  the same safe parser as the ``expression`` body force).

They are evaluated once, after sampling (``Scene.particles``), and checked here: shapes, finite
values, det F > 0. Which law state an initial F sets is decided by ``law_state_from_F``; whether the
transfer carries C is checked when a stepper is built (``BaseStepper``).
"""
from __future__ import annotations

from typing import Any

import numpy as np

from .errors import ConfigError
from .expressions import is_expression, parse_components


def resolve(value: Any, x: np.ndarray, shape: tuple[int, ...], name: str, where: str) -> np.ndarray | None:
    """``value`` (any form of the module docstring) as a float64 array ``[N, *shape]``; None for None."""
    if value is None:
        return None
    n, dim = x.shape
    if callable(value):
        try:
            a = value(x.copy())
        except ConfigError:
            raise
        except Exception as e:     # a user function: say whose it is, keep the cause
            raise ConfigError(f"{where}: the {name} function failed on the body's {n} positions "
                              f"({type(e).__name__}: {e}).") from e
    elif is_expression(value):
        exprs = parse_components(value, shape, f"{where}: {name}", vectors=("x", "X"), scalars=(), constants=(),
                                 dim=dim)
        env = {"x": x, "X": x}
        # nested lists -> [N, D] or [N, D, D]: entry [i][j] lands at [:, i, j]
        ev = lambda e: np.stack([ev(c) for c in e], axis=1) if isinstance(e, list) else e.evaluate(np, env, n)
        a = ev(exprs)
    else:
        a = value
    try:
        a = np.asarray(a, dtype=float)
    except (TypeError, ValueError):
        raise ConfigError(f"{where}: {name} = {value!r} is not numeric (numbers, arrays, a function of the "
                          f"positions or expression strings).") from None
    if a.shape == shape:
        a = np.broadcast_to(a, (n, *shape))
    if a.shape != (n, *shape):
        raise ConfigError(f"{where}: {name} has shape {list(a.shape)}; give {list(shape)} (every particle) or "
                          f"{[n, *shape]} (one per particle: this body samples {n}).")
    bad = np.nonzero(~np.all(np.isfinite(a.reshape(n, -1)), axis=1))[0]
    if len(bad):
        raise ConfigError(f"{where}: {name} of particle {bad[0]} at {np.round(x[bad[0]], 6).tolist()} is not finite.")
    return np.array(a, dtype=float)


def check_F(F: np.ndarray, x: np.ndarray, where: str) -> None:
    """det F > 0 at every particle (an inverted or flat element cannot start a run)."""
    det = np.linalg.det(F)
    bad = np.nonzero(~(det > 0))[0]
    if len(bad):
        i = bad[0]
        raise ConfigError(f"{where}: F of particle {i} at {np.round(x[i], 6).tolist()} has det F = {det[i]:.4g}; "
                          f"an initial deformation gradient needs det F > 0.")


def law_state_from_F(law, F: np.ndarray, where: str) -> dict[str, np.ndarray]:
    """The law-state entries an initial F sets: ``F`` itself when the law's state has F (the elastic
    part, for a plastic law); ``J = det F`` when it has J but no F (a fluid or a rate law keeps only
    the volume; the rest of its state, e.g. a stored stress, starts at its declared initial value);
    refused for a law with neither."""
    fields = law.state_fields
    if "F" in fields:
        return {"F": F}
    if "J" in fields:
        return {"J": np.linalg.det(F)}
    raise ConfigError(f"{where}: law '{law.name}' has no F or J in its state ({', '.join(fields) or 'none'}); "
                      f"an initial F cannot be given to it.")
