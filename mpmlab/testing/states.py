"""Hard law states generated from a law's ``StateField`` declarations, and how they rotate.

Generation rules (per field, in declared order, one batch of 16 states):

* the first square ``("D", "D")`` field with ``init="identity"`` or ``check="positive_det"`` (a
  deformation gradient F) takes the 16 hard deformation gradients of :func:`deformation_gradients`:
  random near identity, rotated, near-singular (a singular value of 1e-3) and large-strain (stretch 3),
  all with det > 0; further such fields: I + 0.1 N (det > 0);
* a scalar with ``check="positive"`` (a volume ratio J): |det F_k| of the k-th hard F (near 1 and far
  from it, also for laws that carry J without F);
* a ``("D", "D")`` field with a numeric ``init`` and ``unit="Pa"`` (a stress): a symmetric random
  matrix of the law's stress scale S, sym(0.3 S N) - 0.5 S I (compressive on average), S the largest
  parameter in Pa (1e4 if there is none);
* any other scalar: init + 0.01 |N| (such fields are often non-negative: plastic strain, damage);
* anything else: init + 0.01 N.

Rotation rules (``rotate_state``), for a rotation Q of space:

* ``("D", "D")`` fields with ``init="identity"`` / ``check="positive_det"`` are two-point tensors:
  F -> Q F;
* other ``("D", "D")`` fields are spatial tensors (stress-like): S -> Q S Q^T;
* ``("D",)`` fields are spatial vectors: n -> Q n;
* scalars and fixed-size fields are invariant.

A law whose fields transform otherwise declares it in an optional class attribute
``test_rotation = {"field": rule}``, rule one of ``"left"`` (Q A), ``"conjugate"`` (Q A Q^T),
``"vector"`` (Q a) or ``"invariant"``; e.g. a plastic deformation gradient F_p in the reference
configuration is ``"invariant"``.
"""
from __future__ import annotations

import numpy as np

from ._common import law_class

ROTATION_RULES = ("left", "conjugate", "vector", "invariant")
#: the kind of each of the 16 hard deformation gradients, in order
KINDS = ("random", "rotated", "near-singular", "large-strain") * 4


def rotation(dim: int, rng: np.random.Generator) -> np.ndarray:
    """A uniformly random rotation (3D: scipy's ``Rotation.random``; 2D: a random angle)."""
    if dim == 3:
        from scipy.spatial.transform import Rotation

        return Rotation.random(random_state=int(rng.integers(1 << 31))).as_matrix()
    th = rng.uniform(0, 2 * np.pi)
    return np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])


def deformation_gradients(dim: int, rng: np.random.Generator) -> np.ndarray:
    """16 F's: random near identity, rotated, near-singular and large-strain (all with det > 0)."""
    Fs = []
    for k in range(4):
        Fs.append(np.eye(dim) + 0.2 * rng.standard_normal((dim, dim)))
        Fs.append(rotation(dim, rng) @ (np.eye(dim) + 0.05 * rng.standard_normal((dim, dim))))
        s = np.ones(dim); s[-1] = 1e-3; s[0] = 1.0 + 0.1 * k
        Fs.append(rotation(dim, rng) @ np.diag(s) @ rotation(dim, rng).T)
        s = np.ones(dim); s[0] = 3.0; s[-1] = 0.6
        Fs.append(rotation(dim, rng) @ np.diag(s) @ rotation(dim, rng).T)
    return np.array([F if np.linalg.det(F) > 0 else F @ np.diag([1.0] * (dim - 1) + [-1.0]) for F in Fs])


def velocity_gradients(n: int, dim: int, rng: np.random.Generator, scale: float = 2.0) -> np.ndarray:
    return scale * rng.standard_normal((n, dim, dim))


def stress_scale(law, prm) -> float:
    """The largest parameter in Pa (the scale of generated stress-like fields); 1e4 if there is none."""
    vals = [abs(float(prm[p.name])) for p in law_class(law).params if p.unit == "Pa" and p.name in prm]
    s = max(vals, default=0.0)
    return s if s > 0 else 1e4


def _is_two_point(f, dim) -> bool:
    shape = f.resolved_shape(dim)
    return shape == (dim, dim) and (f.init == "identity" or f.check == "positive_det")


def hard_states(law, dim: int, rng: np.random.Generator, prm) -> list[dict]:
    """16 states of ``law`` (see the module docstring); the deformation gradients are drawn first."""
    cls = law_class(law)
    Fs = deformation_gradients(dim, rng)
    S = stress_scale(cls, prm)
    first_F = next((f.name for f in cls.state if _is_two_point(f, dim)), None)
    out = []
    for F in Fs:
        s = {}
        for f in cls.state:
            shape = f.resolved_shape(dim)
            if f.name == first_F:
                s[f.name] = F
            elif _is_two_point(f, dim):
                A = np.eye(dim) + 0.1 * rng.standard_normal((dim, dim))
                s[f.name] = A if np.linalg.det(A) > 0 else A @ np.diag([1.0] * (dim - 1) + [-1.0])
            elif shape == () and f.check == "positive":
                s[f.name] = abs(np.linalg.det(F))
            elif shape == (dim, dim) and f.unit == "Pa":
                A = rng.standard_normal(shape) * 0.3 * S
                s[f.name] = 0.5 * (A + A.T) - 0.5 * S * np.eye(dim)
            elif shape == ():
                s[f.name] = float(f.init) + abs(rng.standard_normal()) * 0.01
            else:
                s[f.name] = f.initial(1, dim)[0] + 0.01 * rng.standard_normal(shape)
        out.append(s)
    return out


def rest_state(law, dim: int) -> dict:
    """One particle's declared initial state."""
    return {k: v[0] for k, v in law_class(law).initial_state(1, dim).items()}


def rotation_rules(law, dim: int) -> dict[str, str]:
    """{field: rule} (module docstring); ``Law.test_rotation`` overrides the default per field."""
    cls = law_class(law)
    given = dict(getattr(cls, "test_rotation", None) or {})
    bad = {k: r for k, r in given.items() if k not in cls.state_fields or r not in ROTATION_RULES}
    if bad:
        raise ValueError(f"law '{cls.name}': test_rotation {bad}: each key must be a declared state field "
                         f"{list(cls.state_fields)} and each rule one of {', '.join(ROTATION_RULES)}.")
    out = {}
    for f in cls.state:
        shape = f.resolved_shape(dim)
        if f.name in given:
            out[f.name] = given[f.name]
        elif _is_two_point(f, dim):
            out[f.name] = "left"
        elif shape == (dim, dim) and f.shape == ("D", "D"):
            out[f.name] = "conjugate"
        elif f.shape == ("D",):
            out[f.name] = "vector"
        else:
            out[f.name] = "invariant"
    return out


def rotate_state(state: dict, Q: np.ndarray, rules: dict[str, str]) -> dict:
    out = dict(state)
    for k, rule in rules.items():
        a = np.asarray(state[k])
        if rule == "left":
            out[k] = Q @ a
        elif rule == "conjugate":
            out[k] = Q @ a @ Q.T
        elif rule == "vector":
            out[k] = Q @ a
    return out
