"""Rigid PIC (RPIC; Jiang et al. 2015, Sec. 5.3): a particle carries only the rotational part of its
local velocity field, C = skew(B D^-1), so P2G and G2P conserve angular momentum (like APIC) while
the shear and stretch parts of the velocity field are filtered out (more dissipative than APIC).

A transfer none of mpmlab's five built-ins is, written entirely in this folder: the declaration here,
its math in ``jax.py`` and ``warp.py``. ``mpmlab.testing.check_transfer`` tests it: JAX = Warp
trajectories, gradients against finite differences, and the conservation it declares.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from mpmlab.core.interfaces import AbstractTransfer


@dataclass(frozen=True)
class RPIC(AbstractTransfer):
    """P2G: momentum m (v + C (x_i - x_p)) with C skew-symmetric, and the gradient force (JAX-MPM Eq. 12);
    G2P: C = skew(B D^-1), D^-1 read as ``Dinv`` (dx^2/4 I for quadratic B-splines), so every shape function
    works (``shapes = None``); where D_p is not isotropic (uGIMP) C = [omega]_x with omega = K^-1 axial(B),
    K = tr(D) I - D the particle's inertia tensor (the same for D = d I), so that C puts B's angular
    momentum back on the grid; F updated with sum v_i (grad w)^T (JAX-MPM Eq. 18)."""

    name: ClassVar[str] = "rpic"
    implementations: ClassVar[dict] = {"jax": "mpmlab_example_plugin.rpic.jax:make",
                                       "warp": "mpmlab_example_plugin.rpic.warp:make"}
    carries_C: ClassVar[bool] = True
    momentum_terms: ClassVar[frozenset] = frozenset({"affine", "gradient"})
    moments: ClassVar[frozenset] = frozenset({"first", "gradient"})
    conserves: ClassVar[frozenset] = frozenset({"linear_momentum", "angular_momentum"})
    shapes: ClassVar[frozenset | None] = None            # reads D^-1 as Dinv (mpmlab.shapes)
