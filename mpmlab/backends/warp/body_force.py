"""Warp implementation of ``body_force`` (``mpmlab.boundaries.body_force``).

One small kernel per (field, its code options, dimension, precision, position), built from a closure
over the field's ``@wp.func`` (``BodyForce.warp_func``: a field without one is refused here, never
replaced by another formula) and cached; it adds ``m_p b(X_p, t)`` (or ``m_p b(x_p, t)`` for a field
of the current position) into the stepper's external-force array before P2G. The field parameters are
a kernel argument (an array), so scenes that differ only in numbers share the compiled kernel. This
module also holds the ``@wp.func`` factories of the built-in fields (same formulas as their NumPy/JAX
``evaluate``; verification note #2a for the MMS).
"""

import hashlib
import math
from functools import lru_cache
from types import SimpleNamespace

import numpy as np
import warp as wp

from .law_structs import _generated_func
from .types import warp_types


def uniform_func(dim: int, precision: str, options=None):
    return _uniform_func(dim, precision)


@lru_cache(maxsize=None)
def _uniform_func(dim: int, precision: str):
    T = warp_types(dim, precision)
    scalar, vec = T.scalar, T.vec

    @wp.func
    def uniform(X: vec, t: scalar, p: wp.array(dtype=scalar)):
        b = vec()
        for d in range(dim):
            b[d] = p[d]
        return b

    return uniform


def mms_axis_aligned_func(dim: int, precision: str, options):
    return _mms_func(dim, precision, options.get("law", "fixed_corotated") == "hencky")


@lru_cache(maxsize=None)
def _mms_func(dim: int, precision: str, hencky: bool):
    T = warp_types(dim, precision)
    scalar, vec = T.scalar, T.vec
    pi = scalar(math.pi)

    @wp.func
    def mms_axis_aligned(X: vec, t: scalar, p: wp.array(dtype=scalar)):
        # verification note #2a; Wallstedt & Guilkey 2008 (axis-aligned MMS)
        A = p[0]
        c = p[1]
        mu = p[2]
        lam = p[3]
        rho = p[4]
        U = vec()
        Fd = vec()
        J = scalar(1.0)
        for d in range(dim):
            s = wp.sin(pi * c * t + pi * p[5 + d])
            U[d] = A * wp.sin(pi * (X[d] + p[8])) * s
            Fd[d] = scalar(1.0) + A * pi * wp.cos(pi * (X[d] + p[8])) * s
            J = J * Fd[d]
        b = vec()
        for d in range(dim):
            coef = scalar(0.0)
            if wp.static(hencky):
                coef = ((scalar(2.0) * mu + lam) - scalar(2.0) * mu * wp.log(Fd[d]) - lam * wp.log(J)) / (Fd[d] * Fd[d])
            else:
                K = J / Fd[d]
                coef = scalar(2.0) * mu + lam * K * K
            b[d] = pi * pi * U[d] * (coef / rho - c * c)
        return b

    return mms_axis_aligned


def expression_func(dim: int, precision: str, options):
    return _expression_func(dim, precision, tuple(options["b"]), tuple(options["constants"]))


@lru_cache(maxsize=None)
def _expression_func(dim: int, precision: str, b: tuple, constants: tuple):
    """The ``expression`` field's component strings as generated Warp code (parsed and whitelisted by
    ``mpmlab.core.expressions``; constants read p[i] in sorted name order, as ``pack`` writes them)."""
    from ...boundaries.body_force import ExpressionField

    T = warp_types(dim, precision)
    exprs, pos = ExpressionField.parsed({"b": b, "constants": constants}, dim)
    ci = {k: f"p[{i}]" for i, k in enumerate(constants)}
    lines = "".join(f"    b[{d}] = {e.warp_source(ci)}\n" for d, e in enumerate(exprs))
    src = (f"def body_force_expression({pos}: vec, t: scalar, p: wp.array(dtype=scalar)):\n"
           f"    b = vec()\n{lines}    return b\n")
    key = hashlib.sha1(f"{src}{dim}{precision}".encode()).hexdigest()[:10]
    return _generated_func("body_force_expression", src, {"wp": wp, "vec": T.vec, "scalar": T.scalar,
                                                          "S": T.scalar}, key)


@lru_cache(maxsize=None)
def _field_func(field, name: str, options: tuple, dim: int, precision: str):
    """The field's ``@wp.func``, once per (field class, code options, dim, precision): the kernel cache
    below keys on the function object, so a user factory that builds a new one per call still compiles
    once."""
    from ...boundaries.body_force import warp_func_of

    return warp_func_of(field, name, dim, precision, dict(options))


@lru_cache(maxsize=None)
def body_force_kernel(bfunc, dim: int, precision: str, current: bool, atomic: bool = False):
    """``bfunc``: the field's ``@wp.func``; ``current``: it reads the current positions x (else the
    reference X0); ``atomic``: the tape-safe form (an atomic add instead of a read-add-write of ext)."""
    T = warp_types(dim, precision)
    scalar, vec = T.scalar, T.vec

    @wp.kernel(module="unique")
    def add_body_force(ext: wp.array(dtype=vec), X0: wp.array(dtype=vec), x: wp.array(dtype=vec),
                       mass: wp.array(dtype=scalar), idx: wp.array(dtype=int), p: wp.array(dtype=scalar), t: scalar):
        k = wp.tid()
        i = idx[k]
        f = mass[i] * bfunc(x[i] if wp.static(current) else X0[i], t, p)
        if wp.static(atomic):
            wp.atomic_add(ext, i, f)
        else:
            ext[i] = ext[i] + f

    return add_body_force


def body_force(b, scene, stepper):
    P = scene.particles()
    T, dev = stepper.T, stepper.device
    idx = np.nonzero(b.mask(scene) > 0)[0].astype(np.int32)
    current = b.position == "current"
    # refuses a field without a Warp implementation (MissingImplementationError), before anything runs
    bfunc = _field_func(b.field_impl, b.field, tuple(sorted(b.options.items())), scene.dim, stepper.precision)
    kernel = body_force_kernel(bfunc, scene.dim, stepper.precision, current)
    bc = SimpleNamespace(kind="particle_force")
    X0 = wp.array(P.x, dtype=T.vec, device=dev)
    mass = wp.array(P.mass, dtype=T.scalar, device=dev)
    ia = wp.array(idx, dtype=int, device=dev)
    bc.params = {"field": wp.array(b.packed(scene.dim), dtype=T.scalar, device=dev)}

    def positions(x):
        if x is None and current:
            raise ValueError("body_force: a field of the current position needs the positions x")
        return X0 if x is None else x

    def add_force(ext, t, x=None):
        # the stepper keeps scene order when it has particle forces (no cell sorting), so ext[i] and
        # x[i] are particle i
        if b.t_start <= t < b.t_end:
            wp.launch(kernel, dim=len(idx), inputs=[ext, X0, positions(x), mass, ia, bc.params["field"], T.scalar(t)],
                      device=dev)
            return True
        return False

    def tape():
        # the differentiable path: the mass is the control's (gradients reach it), X0 the scene's
        # reference positions, x the tape's current positions, as on JAX (backends/jax/body_force.py)
        k_tape = body_force_kernel(bfunc, scene.dim, stepper.precision, current, atomic=True)

        def force(ext, p, t, ctl, x=None):
            if b.t_start <= t < b.t_end and len(idx):
                wp.launch(k_tape, dim=len(idx), inputs=[ext, X0, positions(x), ctl.mass, ia, p["field"], T.scalar(t)],
                          device=dev)

        return SimpleNamespace(stage="particle_force", params={"field": np.asarray(b.packed(scene.dim), float)},
                               param_kinds={"field": "scalar"}, force=force)

    bc.add_force = add_force
    bc.tape = tape
    return bc
