"""``mpmlab.testing``: the conformance kit a plugin author runs on a law or a transfer scheme (a plugin's or a built-in).

Every check takes a law by registered name, class or instance (a name or class is built from its
``Law.test_options``), uses the law's own ``Law.test_params`` (parameters that make it deform, and
yield if plastic, within 50 steps of the kit's scenes), returns the errors it measured, and raises
``AssertionError`` with one line naming the law, the backend, the quantity, the error and the
tolerance when a check fails::

    from mpmlab.testing import check_law
    report = check_law("neo_hookean")               # everything cheap, 2D, APIC, JAX and Warp

The checks, each usable alone:

* ``check_reference(law, dim, backend)``: kirchhoff and update on ``backend`` ("jax", "warp") vs the
  NumPy reference (``Law.reference``) on 16 hard states generated from the ``StateField``
  declarations (``mpmlab.testing.states``), fp64, 1e-10 relative;
* ``check_rest_state(law, dim, backends)``: the declared initial state has tau = 0 and stays at rest
  under grad_v = 0;
* ``check_equivariance(law, dim)``: on the reference, tau(Q.s) = Q tau Q^T, the update commutes with
  rotations, tau is symmetric (rotation rules: ``mpmlab.testing.states``; ``Law.test_rotation``
  overrides them per field);
* ``check_backends_agree(law, transfer, dim)``: JAX vs Warp fp64 trajectories of ``law_scene`` after
  50 steps (positions, velocities, C, every declared field) within 1e-9, the body having moved;
* ``check_gradients(law, backend, transfer)``: central differences vs AD of a fixed observation loss
  w.r.t. x, v, the law parameters and the shared weights, fp64, <= 1e-6 relative;
* ``law_scene(laws, dim)``: the small spinning, falling bodies the trajectory checks run.

For a transfer scheme, ``check_transfer("rpic")`` runs ``check_conservation(transfer, dim, backend)``
(a spinning block with no gravity: each quantity the scheme declares in ``conserves`` -- linear
momentum, angular momentum with the affine spin -- stays constant to 1e-11 relative over 40 fp64
steps), ``check_backends_agree`` and ``check_gradients`` with the scheme (law ``fixed_corotated``).

In a plugin's own test suite (pytest shows each failure's one-line message)::

    import pytest
    from mpmlab import testing

    @pytest.mark.parametrize("backend", ("jax", "warp"))
    @pytest.mark.parametrize("dim", (2, 3))
    def test_my_law_matches_its_reference(dim, backend):
        testing.check_reference("my_law", dim, backend)

    def test_my_law():
        testing.check_law("my_law")

Test parameters: ``Law.test_params`` (filled with the declared defaults), ``Law.test_options``
(``material.options`` of the test instance); an optional ``Law.test_rotation`` says how state fields
rotate where the default rules (``mpmlab.testing.states``) do not fit. A law class that is not
registered is registered under its ``name`` when a scene needs it.

Importing ``mpmlab.testing`` imports neither JAX nor Warp; each check imports the backend it runs.
"""
from __future__ import annotations

from ._common import ConformanceError, options_of, params_of, rel_err, resolve_params
from .evaluate import evaluate, jax_law, ref_kirchhoff, ref_update
from .gradients import check_gradients
from .laws import check_equivariance, check_reference, check_rest_state
from .scenes import gradient_scene, law_scene
from .states import deformation_gradients, hard_states, rotate_state, rotation, rotation_rules, velocity_gradients
from .trajectories import check_backends_agree, compare_trajectories, rollout
from .transfers import check_conservation, check_transfer, conservation_scene, momenta

__all__ = [
    "ConformanceError", "check_backends_agree", "check_conservation", "check_equivariance", "check_gradients",
    "check_law", "check_reference", "check_rest_state", "check_transfer", "compare_trajectories",
    "conservation_scene", "momenta", "deformation_gradients", "evaluate",
    "gradient_scene", "hard_states", "jax_law", "law_scene", "options_of", "params_of", "ref_kirchhoff",
    "ref_update", "rel_err", "resolve_params", "rollout", "rotate_state", "rotation", "rotation_rules",
    "velocity_gradients",
]


def check_law(law, *, dims=(2,), backends=("jax", "warp"), transfers=("apic",), gradients=True,
              raise_on_failure: bool = True) -> dict:
    """Every check of the kit on ``law`` for the cheap cases: reference (each backend x dim), rest state
    (reference and each backend), equivariance (each dim), JAX vs Warp trajectories (each transfer x
    dim, when both backends are asked for) and gradients (each backend x transfer, 2D when 2 is in
    ``dims``, else the first dim; ``gradients``: True, False or the backends to run them on).

    Returns a JSON-ready report ``{"law", "checks": {check: measured errors}, "failures": [messages],
    "seconds": {check: s}}``. A failed check does not stop the others; with ``raise_on_failure`` the
    failures are then raised as one ``AssertionError`` (one line: how many failed, each message)."""
    from ._common import Report, law_name

    report = Report("law", law_name(law))
    run = report.run
    for dim in dims:
        for b in backends:
            run(f"reference[{b},{dim}d]", check_reference, law, dim, b)
        run(f"rest_state[{dim}d]", check_rest_state, law, dim, ("reference",) + tuple(backends))
        run(f"equivariance[{dim}d]", check_equivariance, law, dim)
        if {"jax", "warp"} <= set(backends):
            for t in transfers:
                run(f"backends_agree[{t},{dim}d]", check_backends_agree, law, t, dim)
    grad_backends = tuple(backends) if gradients is True else tuple(gradients or ())
    if grad_backends:
        gdim = 2 if 2 in dims else dims[0]
        for b in grad_backends:
            for t in transfers:
                run(f"gradients[{b},{t},{gdim}d]", check_gradients, law, b, t, gdim)
    return report.finish(raise_on_failure)
