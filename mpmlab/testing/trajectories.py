"""JAX vs Warp trajectories of the kit's scenes (``scenes.law_scene``)."""
from __future__ import annotations

from functools import lru_cache

import numpy as np

from ._common import fail, law_instance, law_name, rel_err


def _key(laws) -> tuple:
    from .scenes import _laws

    return tuple(law_instance(l) if not isinstance(l, str) else l for l in _laws(laws))


def rollout(laws, backend: str, transfer: str, dim: int, precision: str = "fp64", steps: int = 50):
    """The trajectory of ``law_scene(laws, dim)`` on ``backend`` (frames 0 and ``steps``) with every
    declared state field (and C for affine transfers). Cached per arguments: one multi-law scene
    serves the checks of all its laws."""
    return _rollout(_key(laws), backend, transfer, dim, precision, steps)


@lru_cache(maxsize=None)
def _rollout(laws, backend, transfer, dim, precision, steps):
    import mpmlab

    from .scenes import law_scene

    st = mpmlab.build_stepper(law_scene(list(laws), dim), backend, transfer, precision)
    fields = []
    for g in st.groups:
        fields += [f for f in g.law.state_fields if f not in fields]
    if st.transfer.needs_affine:
        fields.append("C")
    return st.rollout(steps=steps, every=steps, fields=tuple(fields))


def law_slice(traj, name: str) -> tuple[int, int]:
    """(start, stop) particle indices of the first material group of law ``name``."""
    for m in traj.materials:
        if m["law"] == name:
            return m["start"], m["stop"]
    raise KeyError(f"law '{name}' is not in the trajectory (laws: {[m['law'] for m in traj.materials]})")


def compare_trajectories(a, b, law: str, *, tol: float = 1e-9, moved: float = 1e-3, where: str = "") -> dict:
    """Last frames of ``a`` and ``b`` on law ``law``'s particles: positions, velocities, C and every
    stored law field within ``tol`` relative (max |a - b| / max |b|); and the body moved by more than
    ``moved`` (m) in ``a``, so the comparison means something. Returns {quantity: error, "moved": m}."""
    where = where or f"law '{law}'"
    if a.x.shape != b.x.shape or a.frame_count != 2 or b.frame_count != 2:
        fail(f"{where}: trajectories of shapes {a.x.shape} and {b.x.shape}; expected the same, with 2 frames")
    i, j = law_slice(a, law)
    out = {}
    m = float(np.max(np.abs(a.x[-1, i:j] - a.x[0, i:j])))
    if not m > moved:
        fail(f"{where}: the body moved only {m:.3e} m (<= {moved:g} m): the comparison would not test anything; "
             f"choose Law.test_params that deform it")
    out["moved"] = m
    for q, ea, eb in (("x", a.x[-1, i:j], b.x[-1, i:j]), ("v", a.v[-1, i:j], b.v[-1, i:j])):
        e = rel_err(ea, eb)
        if not e <= tol:
            fail(f"{where}: field '{q}' after {int(a.step[-1])} steps differs: relative error {e:.3e} > tolerance "
                 f"{tol:.0e}")
        out[q] = e
    for f, arr in a.fields.items():
        if f not in b.fields:
            fail(f"{where}: field '{f}' is in one trajectory only")
        if f == "C":
            e = rel_err(arr[-1, i:j], b.fields[f][-1, i:j])
        else:
            idx = a.field_particles[f]
            sel = (idx >= i) & (idx < j)
            if not sel.any():
                continue
            e = rel_err(arr[-1][sel], b.fields[f][-1][sel])
        if not e <= tol:
            fail(f"{where}: field '{f}' after {int(a.step[-1])} steps differs: relative error {e:.3e} > tolerance "
                 f"{tol:.0e}")
        out[f] = e
    return out


def check_backends_agree(law, transfer: str, dim: int, *, steps: int = 50, tol: float = 1e-9,
                         precision: str = "fp64", scene_laws=None, backends=("jax", "warp")) -> dict:
    """JAX and Warp trajectories of ``law_scene`` after ``steps`` steps agree on the law's particles:
    positions, velocities, C and every declared state field within ``tol`` relative; the body must move
    (> 1 mm). ``scene_laws``: the laws sharing the scene (default: this law alone; a list of laws
    compiles one scene for all of them, and the rollouts are cached). Returns the errors by quantity."""
    name = law_name(law)
    laws = [law] if scene_laws is None else scene_laws
    a = rollout(laws, backends[0], transfer, dim, precision, steps)
    b = rollout(laws, backends[1], transfer, dim, precision, steps)
    return compare_trajectories(a, b, name, tol=tol,
                                where=f"law '{name}' {dim}D {transfer} {precision}: {backends[0]} vs {backends[1]}")
