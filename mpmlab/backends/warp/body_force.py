"""Warp implementation of ``body_force`` (``mpmlab.boundaries.body_force``).

One small kernel per (field, law option, dimension, precision), built from a closure over the field's
``@wp.func`` and cached; it adds ``m_p b(X_p, t)`` into the stepper's external-force array before P2G.
The field parameters are a kernel argument (an array), so scenes that differ only in numbers share the
compiled kernel. Same formulas as the NumPy/JAX ``evaluate`` of the field (verification note #2a).
"""

import math
from functools import lru_cache
from types import SimpleNamespace

import numpy as np
import warp as wp

from .types import warp_types


@lru_cache(maxsize=None)
def _field_func(field: str, law: str, dim: int, precision: str):
    T = warp_types(dim, precision)
    scalar, vec = T.scalar, T.vec
    pi = scalar(math.pi)

    if field == "uniform":
        @wp.func
        def uniform(X: vec, t: scalar, p: wp.array(dtype=scalar)):
            b = vec()
            for d in range(dim):
                b[d] = p[d]
            return b

        return uniform

    hencky = law == "hencky"

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


@lru_cache(maxsize=None)
def body_force_kernel(field: str, law: str, dim: int, precision: str, atomic: bool = False):
    """``atomic``: the tape-safe form (an atomic add instead of a read-add-write of ext)."""
    T = warp_types(dim, precision)
    scalar, vec = T.scalar, T.vec
    bfunc = _field_func(field, law, dim, precision)

    @wp.kernel(module="unique")
    def add_body_force(ext: wp.array(dtype=vec), X0: wp.array(dtype=vec), mass: wp.array(dtype=scalar),
                       idx: wp.array(dtype=int), p: wp.array(dtype=scalar), t: scalar):
        k = wp.tid()
        i = idx[k]
        if wp.static(atomic):
            wp.atomic_add(ext, i, mass[i] * bfunc(X0[i], t, p))
        else:
            ext[i] = ext[i] + mass[i] * bfunc(X0[i], t, p)

    return add_body_force


def body_force(b, scene, stepper):
    P = scene.particles()
    T, dev = stepper.T, stepper.device
    idx = np.nonzero(b.mask(scene) > 0)[0].astype(np.int32)
    kernel = body_force_kernel(b.field, b.options.get("law", ""), scene.dim, stepper.precision)
    bc = SimpleNamespace(kind="particle_force")
    X0 = wp.array(P.x, dtype=T.vec, device=dev)
    mass = wp.array(P.mass, dtype=T.scalar, device=dev)
    ia = wp.array(idx, dtype=int, device=dev)
    bc.params = {"field": wp.array(b.packed(scene.dim), dtype=T.scalar, device=dev)}

    def add_force(ext, t):
        # the stepper keeps scene order when it has particle forces (no cell sorting), so ext[i] is particle i
        if b.t_start <= t < b.t_end:
            wp.launch(kernel, dim=len(idx), inputs=[ext, X0, mass, ia, bc.params["field"], T.scalar(t)], device=dev)
            return True
        return False

    def tape():
        # the differentiable path: the mass is the control's (gradients reach it), X0 the scene's
        # reference positions, as on JAX (backends/jax/body_force.py)
        k_tape = body_force_kernel(b.field, b.options.get("law", ""), scene.dim, stepper.precision, atomic=True)

        def force(ext, p, t, ctl):
            if b.t_start <= t < b.t_end and len(idx):
                wp.launch(k_tape, dim=len(idx), inputs=[ext, X0, ctl.mass, ia, p["field"], T.scalar(t)], device=dev)

        return SimpleNamespace(stage="particle_force", params={"field": np.asarray(b.packed(scene.dim), float)},
                               param_kinds={"field": "scalar"}, force=force)

    bc.add_force = add_force
    bc.tape = tape
    return bc
