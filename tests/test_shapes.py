"""Shape functions (``mpmlab.shapes``; issue 19 item 1): the 1-D weights of every separable shape function
(NumPy reference and JAX ``weights``, equal to 1e-15), checked in fp64 at random positions and random particle half
widths lp in (0, 1/2]:

* partition of unity and linear completeness of the weights (sum w = 1, sum w k = fx) and of their
  gradients (sum dw = 0, sum dw k = 1), and dw = the derivative of w (central differences);
* APIC's D_p: sum w (k - fx)^2 = 1/inv_D_cells for the B-splines (1/4 quadratic, 1/3 cubic);
* uGIMP in closed form: at lp = 1/2 it is the quadratic B-spline (hat * box of width 1 = the quadratic
  B-spline), as lp -> 0 the linear hat, and at any lp the hat averaged over the particle's box (quadrature);
* the config's ``transfer.shape`` reaches the stepper (not the transfer) and the trajectory records it;
* CPDI's reference formulas (``cpdi/reference.py``) for random rotated, sheared and stretched domains in
  2-D and 3-D: partition of unity and linear completeness of S_ip and grad S_ip, D_p against its
  definition, the Cayley domain update exactly rigid for a rotation and second order against expm;
* ``resolve`` / ``inner_bounds`` / the registry refuse, in one line: a shape the transfer does not
  declare, a particle too large for uGIMP's window, an unknown name, a particle outside a cubic
  window's region.

Seconds in all (one small JAX trace per shape)."""
from __future__ import annotations

import importlib

import numpy as np
import pytest

import mpmlab
from mpmlab.core.errors import ConfigError, UnknownPluginError
from mpmlab.shapes import inner_bounds, make_shape, resolve

SEPARABLE = ("quadratic", "cubic", "ugimp")
N = 2000


def _reference(name):
    return importlib.import_module(f"mpmlab.shapes.{name}.reference")


def _samples(name, seed=0):
    """Random fx in the shape's range [offset, offset + 1) and lp in (0, 1/2] (lp[0] = 1/2 exactly)."""
    s = make_shape(name)
    rng = np.random.default_rng(seed)
    fx = s.offset + rng.random(N)
    lp = 0.5 * (1.0 - rng.random(N))                   # (0, 0.5]
    lp[0] = 0.5
    return s, fx, lp


def _sums(w, dw, fx):
    k = np.arange(w.shape[-1], dtype=float)
    return {"sum w": w.sum(-1) - 1.0, "sum w k - fx": (w * k).sum(-1) - fx,
            "sum dw": dw.sum(-1), "sum dw k - 1": (dw * k).sum(-1) - 1.0}


@pytest.mark.parametrize("name", SEPARABLE)
def test_reference_weights_partition_of_unity_and_linear_completeness(name):
    s, fx, lp = _samples(name)
    w, dw = _reference(name).weights_1d(fx, lp if s.uses_particle_size else None)
    assert w.shape == dw.shape == (N, s.width)
    assert np.all(w >= -1e-15)
    for what, r in _sums(w, dw, fx).items():
        assert np.abs(r).max() <= 1e-13, (name, what, np.abs(r).max())
    # dw is dN/dx_p in cells: central differences of w
    h = 1e-6
    wp, _ = _reference(name).weights_1d(fx + h, lp if s.uses_particle_size else None)
    wm, _ = _reference(name).weights_1d(fx - h, lp if s.uses_particle_size else None)
    fd = (wp - wm) / (2 * h)
    assert np.abs(fd - dw).max() <= 1e-6, (name, np.abs(fd - dw).max())


@pytest.mark.parametrize("name", SEPARABLE)
def test_jax_weights_are_the_reference_ones(name):
    import jax
    import jax.numpy as jnp

    jax.config.update("jax_enable_x64", True)
    s, fx1, lp = _samples(name, seed=1)
    D = 3
    fx = np.stack([np.roll(fx1, d) for d in range(D)], -1)              # [N, D]
    fns = s.implementation("jax", "shape")(s, D)
    w, dw = fns.weights(jnp.asarray(fx), jnp.asarray(lp))
    w, dw = np.asarray(w), np.asarray(dw)
    assert w.shape == dw.shape == (N, s.width, D) and w.dtype == np.float64
    for d in range(D):
        wr, dwr = _reference(name).weights_1d(fx[:, d], lp if s.uses_particle_size else None)
        assert np.abs(w[:, :, d] - wr).max() <= 1e-15 and np.abs(dw[:, :, d] - dwr).max() <= 1e-15
        for what, r in _sums(w[:, :, d], dw[:, :, d], fx[:, d]).items():
            assert np.abs(r).max() <= 1e-13, (name, what)


@pytest.mark.parametrize("name, D", [("quadratic", 1 / 4), ("cubic", 1 / 3)])
def test_bspline_inertia_is_constant(name, D):
    s, fx, _ = _samples(name)
    w, _ = _reference(name).weights_1d(fx)
    k = np.arange(s.width, dtype=float)
    Dp = (w * (k - fx[:, None]) ** 2).sum(-1)
    assert np.abs(Dp - D).max() <= 1e-14 and s.inv_D_cells == pytest.approx(1 / D)


def test_ugimp_closed_forms():
    ref = _reference("ugimp")
    fx = 0.5 + np.random.default_rng(2).random(N)
    # lp = 1/2 (one particle per cell): the hat averaged over a unit box is the quadratic B-spline
    w, dw = ref.weights_1d(fx, np.full(N, 0.5))
    wq, dwq = _reference("quadratic").weights_1d(fx)
    assert np.abs(w - wq).max() <= 1e-14 and np.abs(dw - dwq).max() <= 1e-14
    # lp -> 0: the linear hat max(0, 1 - |r|)
    r = fx[:, None] - np.arange(3.0)
    w0, _ = ref.weights_1d(fx, np.full(N, 1e-7))
    assert np.abs(w0 - np.maximum(0.0, 1.0 - np.abs(r))).max() <= 1e-7
    # any lp: (1 / 2lp) int_{r-lp}^{r+lp} hat(s) ds (the hat is piecewise linear: Simpson per piece is exact)
    lp = 0.05 + 0.45 * np.random.default_rng(3).random(N)
    w, _ = ref.weights_1d(fx, lp)
    knots = np.array([-1.0, 0.0, 1.0])
    for k in range(3):
        a, b = r[:, k] - lp, r[:, k] + lp
        pts = np.sort(np.concatenate([np.stack([a, b], 1), np.clip(knots[None, :], a[:, None], b[:, None])], 1), 1)
        hat = lambda s: np.maximum(0.0, 1.0 - np.abs(s))                          # noqa: E731
        lo, hi = pts[:, :-1], pts[:, 1:]
        integral = ((hi - lo) / 6 * (hat(lo) + 4 * hat(0.5 * (lo + hi)) + hat(hi))).sum(1)
        assert np.abs(w[:, k] - integral / (2 * lp)).max() <= 1e-13


# ---- CPDI (reference formulas, mpmlab/shapes/cpdi/reference.py) -------------------------------------------------
def _domains(D, n=200, seed=4):
    """Random particles and domains: rotated, sheared and stretched (singular values 0.2 .. 3 half cells)."""
    rng = np.random.default_rng(seed)
    x = 2.0 + 3.0 * rng.random((n, D))
    U, _ = np.linalg.qr(rng.standard_normal((n, D, D)))
    V, _ = np.linalg.qr(rng.standard_normal((n, D, D)))
    sv = 0.1 + 1.4 * rng.random((n, D))                            # half widths in cells (dx = 1 below)
    return x, np.einsum("nij,nj,nkj->nik", U, sv, V)


@pytest.mark.parametrize("D", [2, 3])
def test_cpdi_partition_of_unity_linear_completeness_and_inertia(D):
    """S_ip = 2^-D sum_c N_i(x_c), grad S_ip = 2^-D sum_c N_i(x_c) R^-T s_c: sum S = 1, sum S x_i = x_p,
    sum grad S = 0, sum x_i grad S^T = I for any domain, and ``inertia`` is sum S (x_i - x_p)(x_i - x_p)^T."""
    ref = _reference("cpdi")
    x, R = _domains(D)
    dx = 0.5
    x, R = x * dx, R * dx
    for k in range(0, len(x), 20):
        nodes, S, dS = ref.node_weights(x[k:k + 20], R[k:k + 20], dx)
        X = nodes * dx
        assert S.min() >= 0.0
        assert np.abs(S.sum(1) - 1).max() <= 1e-14
        assert np.abs(S @ X - x[k:k + 20]).max() <= 1e-13
        assert np.abs(dS.sum(1)).max() <= 1e-12
        assert np.abs(np.einsum("nki,kj->nij", dS, X) - np.eye(D)).max() <= 1e-12
        r = X[None] - x[k:k + 20, None]
        Dp = np.einsum("nk,nki,nkj->nij", S, r, r)
        assert np.abs(Dp - ref.inertia(x[k:k + 20], R[k:k + 20], dx)).max() <= 1e-14


def test_cpdi_domain_update_rotates_rigidly_and_is_second_order():
    """The Cayley update keeps R^T R for a skew velocity gradient (a rigid rotation) to round-off, and
    follows R(t) = expm(t L) R0 at second order in dt for any L."""
    from scipy.linalg import expm

    ref = _reference("cpdi")
    x, R = _domains(3, n=50)
    rng = np.random.default_rng(5)
    W = rng.standard_normal((50, 3, 3))
    W = W - W.transpose(0, 2, 1)
    Rn = R
    for _ in range(100):
        Rn = ref.update_domain(Rn, W, 0.05)
    gram = lambda A: np.einsum("nji,njk->nik", A, A)               # noqa: E731
    assert np.abs(gram(Rn) - gram(R)).max() <= 1e-12 * np.abs(gram(R)).max()
    L = rng.standard_normal((50, 3, 3))
    errs = []
    for n in (10, 20):
        Rn = R
        for _ in range(n):
            Rn = ref.update_domain(Rn, L, 0.5 / n)
        errs.append(np.abs(Rn - np.stack([expm(0.5 * l) @ r for l, r in zip(L, R)])).max())
    assert 3.6 < errs[0] / errs[1] < 4.4, errs


def test_cpdi_initial_domain():
    ref = _reference("cpdi")
    R = ref.initial_domain([1e-6, 8e-6], 3)                     # cubes of side 0.01 and 0.02
    assert np.allclose(R, [0.005 * np.eye(3), 0.01 * np.eye(3)])
    F = np.array([[[1.0, 0.5, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 2.0]]] * 2)
    assert np.allclose(ref.initial_domain([1e-6, 8e-6], 3, F), F @ R)


def _scene(ppc=4, lo=0.4, hi=0.6, dx=0.05, **body):
    return mpmlab.Scene(dim=2, dx=dx, domain=([0.0, 0.0], [1.0, 1.0]),
                        bodies=[mpmlab.Body(shape={"kind": "box", "lo": [lo, lo], "hi": [hi, hi]},
                                            material="fixed_corotated", params={"E": 1e4, "nu": 0.3},
                                            density=1000.0, particles_per_cell=ppc, **body)], dt=1e-3)


def test_resolve_refusals():
    from mpmlab.transfers import make_transfer

    apic = make_transfer("apic")
    # a scheme that keeps AbstractTransfer's default declaration (quadratic only): cubic refused
    legacy = type("Legacy", (type(apic),), {"shapes": frozenset({"quadratic"})})()
    assert resolve("quadratic", legacy, 2, 0.1, [1e-4])[1] is None
    with pytest.raises(ConfigError, match=r"declares shapes = \['quadratic'\].*cannot run with shape 'cubic'"):
        resolve("cubic", legacy, 2, 0.1, [1e-4])
    # uGIMP: lp = V^(1/D) / (2 dx) in cells, at most 1/2 (one particle per cell)
    s, lp = resolve("ugimp", apic, 2, 0.1, [0.05 ** 2, 0.1 ** 2])
    assert s.name == "ugimp" and np.allclose(lp, [0.25, 0.5])
    with pytest.raises(ConfigError, match=r"particle 1 has half width 0.6 cells.*particles_per_cell >= 1"):
        resolve("ugimp", apic, 2, 0.1, [0.01 ** 2, 0.12 ** 2])
    assert resolve("cpdi", apic, 2, 0.1, [1e-4])[1] is None        # CPDI's state is its domain, not lp
    with pytest.raises(UnknownPluginError, match=r"unknown shape 'quintic'.*cpdi, cubic, quadratic, ugimp"):
        make_shape("quintic")
    # a tracer (zero volume) gets a small positive lp, not 0 (uGIMP divides by it)
    assert resolve("ugimp", apic, 2, 0.1, [0.0])[1][0] > 0


def test_cubic_window_region_and_stepper_refusals():
    scene = _scene(lo=0.03, hi=0.2)                     # particles less than a cell from the lower edge
    lo, hi = inner_bounds("quadratic", scene)
    assert np.array_equal(lo, scene.inner_bounds[0]) and np.array_equal(hi, scene.inner_bounds[1])
    lo, hi = inner_bounds("cubic", scene)
    assert np.allclose(lo, 0.05) and np.allclose(hi, 0.95)
    with pytest.raises(ConfigError, match=r"outside the region .* 4-node window .*cubic"):
        mpmlab.build_stepper(scene, "jax", "apic", "fp64", shape="cubic")
    with pytest.raises(ConfigError, match=r"half width 1 cells"):
        mpmlab.build_stepper(_scene(ppc=1, dx=0.025, **{"particle_volume": 0.05 ** 2}), "jax", "apic", "fp64",
                             shape="ugimp")


def test_config_shape_goes_to_the_stepper_not_the_transfer():
    from mpmlab.config import compose, make_transfer_from_config, shape_options_from_config

    cfg = compose(["transfer=apic", "transfer.shape=cubic"])
    assert cfg.transfer.shape == "cubic" and make_transfer_from_config(cfg).name == "apic"
    assert shape_options_from_config(cfg) == {"shape": "cubic"}
    assert shape_options_from_config(compose(["transfer=pic"])) == {}          # quadratic: the default
    with pytest.raises(UnknownPluginError, match=r"unknown shape 'cubik'"):
        shape_options_from_config(compose(["transfer.shape=cubik"]))


def test_trajectory_records_the_shape(tmp_path):
    from mpmlab.io.h5 import read_attrs, read_trajectory, write_trajectory

    st = mpmlab.build_stepper(_scene(), "jax", "pic", "fp32", shape="cubic")
    traj = st.rollout(steps=2, every=1)
    assert traj.meta["shape"] == "cubic"
    write_trajectory(tmp_path / "t.h5", traj)
    assert read_attrs(tmp_path / "t.h5")["shape_function"] == "cubic"
    assert read_trajectory(tmp_path / "t.h5").meta["shape"] == "cubic"
