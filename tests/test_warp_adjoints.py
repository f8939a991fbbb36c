"""Hand-written Warp adjoints and ``segment="auto"`` (issue 17, item 1, Warp half).

* The hand-written P2G and G2P adjoints (``mpmlab/backends/warp/adjoints.py``, registered on the tape
  with ``Tape.record_func``) against Warp's generated adjoints of the same forward kernels
  (``GradPath.adjoints = "generated"``): P2G alone, one launch on random inputs per transfer x dim x
  external force (every term the kernel compiles: momentum affine/gradient, force affine/gradient, the
  external force alone or inside a term); then whole gradients (fp64, 1e-12 relative) for every law x
  transfer in 2D, every transfer and every law in 3D (every law x transfer with
  ``MPMLAB_FULL_ADJOINT_TESTS=1``), and every boundary, with both.
* ``segment="auto"``: the same gradient as a recomputed segment, with the recomputation skipped (the
  path's step counter), the fallback to recomputation when the budget is too small, no recording
  under ``torch.no_grad``, and two kept graphs alive at once.

Mutations checked to fail (by hand, 2026-12-06): dropping P2G's Hessian term (``H Tg^T a_q``) fails the
APIC launch tests and the newtonian/apic 2D gradient (d/dx off by 4.7e-2 of 3.3); dropping G2P's
``(a_vp . v_i) grad w`` term fails the newtonian/apic 2D gradient (6.2 of 3.3); ``segment="auto"``
never keeping fails the step count (52 steps run instead of 26) and the reuse check.
"""
import os
from functools import lru_cache

import numpy as np
import pytest
import torch
import warp as wp

import mpmlab
from mpmlab.backends.warp import adjoints as ADJ
from mpmlab.backends.warp import grad as G
from mpmlab.backends.warp import kernels as K
from mpmlab.backends.warp.transfers import warp_transfer
from mpmlab.backends.warp.types import warp_types
from mpmlab.core import registry
from mpmlab.observations import Lagrangian

from .test_boundaries import KINDS as BOUNDARY_KINDS
from .test_boundaries import scene_for
from .test_grad_warp import law_scene, sheared_controls

LAWS = registry.laws.names()
TRANSFERS = registry.transfers.names()
TOL = 1e-12
CASES = [(law, t) for law in LAWS for t in TRANSFERS
         if registry.laws.get(law).test_transfers is None or t in registry.laws.get(law).test_transfers]


# ---- one P2G launch, random inputs ----------------------------------------------------------------------
@pytest.mark.parametrize("ext", (False, True))
@pytest.mark.parametrize("dim", (2, 3))
@pytest.mark.parametrize("transfer", TRANSFERS)
def test_p2g_adjoint_launch(transfer, dim, ext):
    """The hand-written P2G adjoint equals Warp's generated one for random particles (random stress, C,
    mass, volume, external force) and random node adjoints, in every input."""
    T = warp_types(dim, "fp64")
    tr = warp_transfer(registry.transfers.get(transfer)(), dim, "fp64")
    fwd = K.p2g_kernel(dim, "fp64", tr, ext, atomic=True)
    adj = ADJ.p2g_adjoint_kernels(dim, "fp64", tr, ext).adjoint
    rng = np.random.default_rng(1)
    n_side, dx = 9, 0.1
    shape = (n_side,) * dim
    Gn = n_side**dim
    strides = T.ivec(*[n_side ** (dim - 1 - d) for d in range(dim)])
    N = 40
    arr = lambda a, dtype, grad=True: wp.array(a, dtype=dtype, requires_grad=grad)
    x = rng.uniform(0.25, 0.65, (N, dim))
    x[-1] = 5.0                                   # off the grid: contributes nothing, gets no adjoint
    ins = dict(x=arr(x, T.vec), v=arr(rng.standard_normal((N, dim)), T.vec),
               C=arr(rng.standard_normal((N, dim, dim)), T.mat), tau=arr(rng.standard_normal((N, dim, dim)), T.mat),
               mass=arr(rng.uniform(0.5, 2.0, N), T.scalar), vol=arr(rng.uniform(0.5, 2.0, N), T.scalar),
               ext=arr(rng.standard_normal((N, dim)), T.vec))
    gvec = K.grid_vec_type(dim, "fp64")
    tp = wp.array([0.7], dtype=T.scalar)
    origin, dx_s, dt_s = T.vec(), T.scalar(dx), T.scalar(0.3)
    grid_mm = wp.zeros(Gn, dtype=gvec, requires_grad=True)
    grid_f = wp.zeros(Gn if tr.split_force else 1, dtype=T.vec, requires_grad=True)
    bbox = wp.zeros(2, dtype=T.ivec)
    lp = wp.zeros(1, dtype=T.scalar)              # the particles' half widths: unused by the quadratic B-spline
    args = [ins["x"], ins["v"], ins["C"], ins["tau"], ins["mass"], ins["vol"], ins["ext"], lp, origin, dx_s, dt_s,
            tp, strides]
    tape = wp.Tape()
    with tape:
        wp.launch(fwd, dim=N, inputs=args + [0, 0, grid_mm, grid_f, bbox, 0, wp.zeros(1, dtype=T.mat)])  # domain: CPDI only
    a_mm = rng.standard_normal((Gn, dim + 1))
    a_f = rng.standard_normal((grid_f.shape[0], dim))
    grid_mm.grad.assign(wp.array(a_mm, dtype=gvec))
    grid_f.grad.assign(wp.array(a_f, dtype=T.vec))
    tape.backward()
    gen = {k: a.grad.numpy().copy() for k, a in ins.items()}
    assert np.abs(grid_mm.numpy()).max() > 0 and shape
    for a in ins.values():
        a.grad.zero_()
    out = wp.zeros(N, dtype=T.scalar)
    ones = wp.full(N, value=T.scalar(1.0), dtype=T.scalar)
    wp.launch(adj, dim=N, inputs=args + [grid_mm.grad, grid_f.grad], outputs=[out],
              adj_inputs=[a.grad for a in ins.values()] + [None] * 8, adj_outputs=[ones], adjoint=True)
    hand = {k: a.grad.numpy() for k, a in ins.items()}
    used = {"x", "v", "mass", "tau", "vol"} | ({"C"} if tr.carries_C else set()) | ({"ext"} if ext else set())
    for k in ins:
        scale = np.abs(gen[k]).max()
        if k in used:
            assert scale > 0, f"{k}: the generated adjoint is zero, nothing is compared"
        assert np.abs(hand[k] - gen[k]).max() <= TOL * max(scale, 1e-300), \
            (k, np.abs(hand[k] - gen[k]).max(), scale)
        assert np.all(hand[k][-1] == 0), f"{k}: the off-grid particle got an adjoint"


# ---- whole gradients --------------------------------------------------------------------------------------
@lru_cache(maxsize=None)
def stepper(kind, *args):
    scene = law_scene(*args[:2]) if kind == "law" else scene_for(args[0], 2)
    transfer = args[-1]
    return mpmlab.build_stepper(scene, "warp", transfer, "fp64")


def gradients(st, adjoints, steps, segment=None, shear=True, noise=0.0, prep=None):
    """{control: gradient} of a random weighting of the observed velocities, with ``adjoints``; ``noise``:
    relative perturbation of the weights (the gradient's own sensitivity to rounding)."""
    path = G.path_of(st)
    path.adjoints = adjoints
    c = sheared_controls(st) if shear else st.controls()
    if prep is not None:
        c = prep(dict(c))
    leaves = {}

    def req(t, name):
        t = t.detach().clone().requires_grad_(True)
        leaves[name] = t
        return t

    c = dict(c)
    for k in ("x", "v", "mass", "volume", "gravity") + (("C",) if "C" in c else ()):
        c[k] = req(c[k], k)
    c["law"] = tuple(req(a, f"law[{i}]") for i, a in enumerate(c["law"]))
    c["boundary"] = tuple({k: req(a, f"boundary[{i}].{k}") for k, a in d.items()} for i, d in enumerate(c["boundary"]))
    y = st.observe(c, Lagrangian(quantity="v"), steps, segment)
    w = np.random.default_rng(0).standard_normal(tuple(y.shape))
    w = torch.tensor(w * (1.0 + noise * np.random.default_rng(1).standard_normal(w.shape)))
    (y * w).sum().backward()
    return {k: (t.grad.numpy().copy() if t.grad is not None else np.zeros(t.shape)) for k, t in leaves.items()}


def assert_same(gen, hand, where):
    """Hand vs generated gradients: within ``TOL`` (1e-12) of the largest gradient entry of the test
    (normwise over every control: gradients that are rounding noise, e.g. d/dx of a block that never
    reaches the obstacle, 1e-13 with a 1e-13 difference, are compared against what they are noise of),
    and every control whose gradient is not negligible (>= 1e-6 of the largest) within 1e-10 of its
    own largest entry (the 3D plastic laws' parameter gradients are sums of cancelling terms: 8e-4 made
    of O(1) terms, where the two adjoints' different summation orders differ by up to 6e-12 of it)."""
    S = max(np.abs(g).max() for g in gen.values())
    assert S > 0, f"{where}: every gradient is zero, nothing is compared"
    nonzero = 0
    for k in gen:
        scale = np.abs(gen[k]).max()
        err = np.abs(hand[k] - gen[k]).max()
        assert err <= TOL * S, f"{where}: d/d{k} hand vs generated {err:.2e} > {TOL:g} x {S:.2e} (largest gradient)"
        if scale >= 1e-6 * S:
            nonzero += 1
            assert err <= 1e-10 * scale, f"{where}: d/d{k} hand vs generated {err:.2e} (its scale {scale:.2e})"
    assert nonzero >= 3, f"{where}: too few non-zero gradients to compare"


@pytest.mark.parametrize("law,transfer", CASES)
def test_gradients_law_transfer_2d(law, transfer):
    st = stepper("law", law, 2, transfer)
    assert_same(gradients(st, "generated", (3, 6)), gradients(st, "hand", (3, 6)), f"{law}/{transfer} 2D")


#: 3D: every transfer (one law) and every law (one transfer) by default. The hand-written G2P adjoint is
#: compiled per law x transfer x dim (its law update is the forward's), so every law x transfer in 3D
#: compiles ~30 more kernels (several minutes on 2 cores): MPMLAB_FULL_ADJOINT_TESTS=1 runs them all.
#: (The P2G adjoint does not depend on the law: its stress is an input, random in test_p2g_adjoint_launch.)
FULL_3D = os.environ.get("MPMLAB_FULL_ADJOINT_TESTS", "") not in ("", "0")
CASES_3D = CASES if FULL_3D else sorted(
    {("fixed_corotated", t) for t in TRANSFERS} | {(law, "apic") for law, t in CASES if t == "apic"}
    | {(law, t) for law, t in CASES if law == "nclaw"})


@pytest.mark.parametrize("law,transfer", CASES_3D)
def test_gradients_3d(law, transfer):
    st = stepper("law", law, 3, transfer)
    assert_same(gradients(st, "generated", (2, 4)), gradients(st, "hand", (2, 4)), f"{law}/{transfer} 3D")


#: steps that reach each boundary's action (the load acts from t = 0.01 s, step 20 at dt = 5e-4)
BOUNDARY_STEPS = {"particle_load": (22, 26), "body_force": (11, 16)}


def _moved(dy, vy):
    """Controls with the bodies moved by dy and given a downward velocity: the block of the plane and
    box-obstacle scenes starts 0.1 m above the surface (hundreds of steps away); this brings it to it."""
    def prep(c):
        c["x"] = c["x"] + torch.tensor([0.0, dy], dtype=c["x"].dtype)
        c["v"] = c["v"] + torch.tensor([0.0, vy], dtype=c["v"].dtype)
        return c
    return prep


BOUNDARY_PREP = {"plane": _moved(-0.09, -1.0), "box_obstacle": _moved(-0.13, 0.0)}


@pytest.mark.parametrize("transfer", ("apic", "flip"))
@pytest.mark.parametrize("kind", BOUNDARY_KINDS)
def test_gradients_boundaries(kind, transfer):
    st = stepper("boundary", kind, transfer)
    steps = BOUNDARY_STEPS.get(kind, (5, 10))
    prep = BOUNDARY_PREP.get(kind)
    gen = gradients(st, "generated", steps, shear=False, prep=prep)
    hand = gradients(st, "hand", steps, shear=False, prep=prep)
    assert_same(gen, hand, f"{kind}/{transfer}")
    bnd = [k for k in gen if k.startswith("boundary")]
    assert all(np.abs(gen[k]).max() > 0 for k in bnd if kind != "walls"), \
        f"{kind}: a boundary datum has no gradient in this window: {[(k, np.abs(gen[k]).max()) for k in bnd]}"


# ---- segment="auto" ---------------------------------------------------------------------------------------
def _auto_stepper():
    return stepper("boundary", "particle_load", "flip")


def _run(st, segment, steps=(22, 26)):
    path = G.path_of(st)
    n0 = path.steps_run
    g = gradients(st, "hand", steps, segment=segment, shear=False)
    return g, path.steps_run - n0


def test_auto_same_gradient_without_recomputation():
    st = _auto_stepper()
    g5, n5 = _run(st, 5)
    ga, na = _run(st, "auto")
    assert n5 == 2 * 26                       # forward + every segment recomputed
    assert na == 26                           # recorded once, nothing recomputed
    for k in g5:
        assert np.abs(ga[k] - g5[k]).max() <= TOL * max(np.abs(g5[k]).max(), 1e-300), k
    # the gradient is reused across calls (pool kept) and stays the same
    gb, nb = _run(st, "auto")
    assert nb == 26 and all(np.array_equal(ga[k], gb[k]) for k in ga)


def test_auto_falls_back_when_it_does_not_fit(monkeypatch):
    import mpmlab.core.budget as B

    st = _auto_stepper()
    path = G.path_of(st)
    monkeypatch.setattr(B, "available_memory", lambda: 4 * path.bytes_per_step())   # room for 1 step, not 26
    g, n = _run(st, "auto")
    assert n == 2 * 26
    assert B.resolve_segment("auto", 26, path.bytes_per_step(), default=G.DEFAULT_SEGMENT) == (26, False)


def test_auto_no_grad_records_nothing():
    st = _auto_stepper()
    path = G.path_of(st)
    c = st.controls()
    with torch.no_grad():
        y0 = st.observe(c, Lagrangian(quantity="x"), (5, 26), segment=26)
        n0 = path.steps_run
        y = st.observe(c, Lagrangian(quantity="x"), (5, 26), segment="auto")
    assert path.steps_run - n0 == 26
    assert torch.equal(y, y0)


def test_auto_two_kept_graphs():
    """Two kept rollouts alive at once (the second cannot reuse the first's step buffers), backward in
    reverse order, and repeated backward passes (retain_graph, as the reverse-mode Jacobian does): every
    gradient equals the recomputed one; a backward pass after the buffers were reused is refused."""
    st = _auto_stepper()
    obs = Lagrangian(quantity="v")
    ref, got = [], []
    for scale in (1.0, 1.3):
        c = st.controls()
        v = (c["v"] * scale).requires_grad_(True)
        y = st.observe({**c, "v": v}, obs, (10, 24), segment=4)
        y.sum().backward()
        ref.append(v.grad.clone())
    ys, vs = [], []
    for scale in (1.0, 1.3):
        c = st.controls()
        v = (c["v"] * scale).detach().requires_grad_(True)
        ys.append(st.observe({**c, "v": v}, obs, (10, 24), segment="auto"))
        vs.append(v)
    for i in (1, 0):
        g1, = torch.autograd.grad(ys[i].sum(), vs[i], retain_graph=True)
        g2, = torch.autograd.grad(ys[i].sum(), vs[i], retain_graph=True)
        assert torch.equal(g1, g2)
        got.append(g1)
    for r, g in zip(ref, got[::-1]):
        assert (r - g).abs().max() <= TOL * r.abs().max()
    _run(st, "auto")                                   # takes the shared buffers again
    with pytest.raises(RuntimeError, match="reused by a later gradient"):
        ys[0].sum().backward()


def test_adjoints_option_is_checked():
    st = _auto_stepper()
    with pytest.raises(mpmlab.core.errors.ConfigError):
        G.path_of(st).adjoints = "fast"
