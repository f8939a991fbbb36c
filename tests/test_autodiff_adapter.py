"""The autodiff adapter (mpmlab.core.autodiff; issue #13 item 4): both built-in adapters satisfy the
protocol, the lookup goes through the stepper or the backend registry, and a tiny fit through the
adapter gives exactly the loss history of the same fit written directly against the backend's own
arrays (jax.value_and_grad + optax; torch backward + torch.optim)."""
import math
from types import SimpleNamespace

import numpy as np
import pytest

import mpmlab
from mpmlab.core import autodiff, registry
from mpmlab.core.errors import ConfigError, GradientError
from mpmlab.inverse.fit import Fit
from mpmlab.inverse.lm import LevenbergMarquardt
from mpmlab.inverse.parameters import FitParameter, glorot_mlp
from mpmlab.observations import Lagrangian, ObservationSchedule, apply_numpy
from mpmlab.simulator import build_stepper

BACKENDS = ("jax", "warp")
EPOCHS, LR = 3, 0.05


def tiny_fit(backend):
    """24 particles of a law without an SVD, one observed step: cheap to compile on JAX. The reference is
    the start shifted 2 mm along x (no reference rollout to compile)."""
    body = mpmlab.Body(shape={"kind": "box", "lo": [0.3, 0.3], "hi": [0.45, 0.4]}, material="weakly_compressible",
                       params={"bulk_modulus": 2e4}, density=1000.0, particles_per_cell=4, name="block")
    scene = mpmlab.Scene(dim=2, dx=0.05, domain=([0.0, 0.0], [1.0, 1.0]), bodies=[body], gravity=[0.0, -9.8],
                         dt=1e-3, name="tiny")
    st = build_stepper(scene, backend, "pic", "fp64")
    p = FitParameter(name="alpha", target="initial_velocity", component="x", basis="1 + y", init=0.5,
                     truth=1.5).bind(scene, st, [])
    obs = Lagrangian(quantity="x", particles=8)
    ref = apply_numpy(obs, {"x": st.particles.x + np.array([2e-3, 0.0]), "v": st.particles.v})[None]
    return Fit(st, scene, [p], obs, ObservationSchedule(steps=(1,)), segment=1, reference=ref)


@pytest.mark.parametrize("backend", BACKENDS)
def test_adapters_satisfy_the_protocol(backend):
    ad = autodiff.adapter_for_backend(backend, "fp32")
    assert isinstance(ad, autodiff.AutodiffAdapter) and autodiff.missing_members(ad) == []
    assert ad.name == backend and ad.checkpoint_suffix
    assert set(ad.jacobian_modes) <= set(autodiff.AD_JACOBIANS)
    assert ad.default_jacobian in (*ad.jacobian_modes, "central")
    # arrays and trees: a controls-like tree with a key no adapter knows keeps its structure
    a = ad.asarray([[1.0, 2.0], [3.0, 4.0]])
    np.testing.assert_array_equal(ad.numpy(a), [[1.0, 2.0], [3.0, 4.0]])
    tree = {"x": a, "law": (a, a), "boundary": ({"mu": ad.asarray([0.5])},), "law_weights": ({"w": [a]},)}
    two = ad.tree_map(lambda u, w: u + w, tree, tree)
    assert isinstance(two["law"], tuple) and isinstance(two["law_weights"][0]["w"], list)
    np.testing.assert_array_equal(ad.numpy(two["law_weights"][0]["w"][0]), 2 * ad.numpy(a))
    np.testing.assert_array_equal(ad.numpy(two["boundary"][0]["mu"]), [1.0])
    b = ad.set_column(a, slice(0, 1), 1, ad.asarray(9.0))
    np.testing.assert_array_equal(ad.numpy(b), [[1.0, 9.0], [3.0, 4.0]])
    np.testing.assert_array_equal(ad.numpy(a), [[1.0, 2.0], [3.0, 4.0]])          # not mutated
    x = np.array([-1.0, 0.5])
    np.testing.assert_allclose(ad.numpy(ad.transform("softplus", ad.asarray(x))), np.log1p(np.exp(x)), rtol=1e-6)
    np.testing.assert_allclose(ad.numpy(ad.transform("exp", ad.asarray(x))), np.exp(x), rtol=1e-6)
    np.testing.assert_array_equal(ad.numpy(ad.transform("identity", ad.asarray(x))), x)
    weights = glorot_mlp([1, 3, 1], seed=0)
    X = np.linspace(0.0, 1.0, 5)[:, None]
    h = np.tanh(X @ weights[0][0] + weights[0][1]) @ weights[1][0] + weights[1][1]
    np.testing.assert_allclose(ad.numpy(ad.mlp_apply(ad.mlp(weights), ad.asarray(X), "tanh")), h[:, 0], rtol=1e-5)


def test_lookup_goes_through_the_stepper_then_the_registry(monkeypatch):
    from mpmlab.backends.jax.adapter import JaxAdapter
    from mpmlab.backends.warp.adapter import WarpAdapter

    assert type(autodiff.adapter(SimpleNamespace(backend_name="jax", precision="fp32"))) is JaxAdapter
    ad = autodiff.adapter(SimpleNamespace(backend_name="warp", precision="fp64"))
    assert type(ad) is WarpAdapter and ad.precision == "fp64"

    class OwnAdapterStepper:        # a stepper may name its own adapter (class or "module:attr")
        autodiff_adapter = "mpmlab.backends.warp.adapter:WarpAdapter"
        backend_name, precision = "jax", "fp32"
    assert type(autodiff.adapter(OwnAdapterStepper())) is WarpAdapter

    class BareBackend:
        name = "bare"
    monkeypatch.setitem(registry.backends._objects, "bare", BareBackend)
    with pytest.raises(ConfigError, match="backend 'bare' has no autodiff adapter"):
        autodiff.adapter_for_backend("bare")
    monkeypatch.setattr(BareBackend, "autodiff_adapter", JaxAdapter, raising=False)
    assert type(autodiff.adapter_for_backend("bare")) is JaxAdapter
    monkeypatch.setattr(BareBackend, "autodiff_adapter", "mpmlab.backends.nope:Adapter", raising=False)
    with pytest.raises(ConfigError, match="cannot be imported"):
        autodiff.adapter_for_backend("bare")


def test_levenberg_marquardt_asks_the_adapter_for_its_jacobian():
    jax_ad, warp_ad = (autodiff.adapter_class(b) for b in BACKENDS)
    assert LevenbergMarquardt().jacobian_kind(jax_ad) == "forward" == LevenbergMarquardt().jacobian_kind("jax")
    assert LevenbergMarquardt().jacobian_kind(warp_ad) == "central"
    for ad in (jax_ad, warp_ad):
        assert LevenbergMarquardt(jacobian="reverse").jacobian_kind(ad) == "reverse"
        assert LevenbergMarquardt(jacobian="central").jacobian_kind(ad) == "central"
    with pytest.raises(ConfigError, match="needs forward-mode AD, which backend 'warp' does not have"):
        LevenbergMarquardt(jacobian="forward").jacobian_kind(warp_ad)


def _direct_jax(fit, p, epochs, lr):
    """The fit written against JAX directly (as fit.py's JAX loop did before the adapter)."""
    import jax
    import jax.numpy as jnp
    import optax

    from mpmlab.backends.jax import differentiable as JD

    st, c0 = fit.stepper, fit.stepper.controls()
    mask = fit._mask()
    norm = float(mask.sum() * fit.reference.shape[2])
    ref, m = jnp.asarray(fit.reference, st.dtype), jnp.asarray(mask, st.dtype)[..., None]
    basis = jnp.asarray(p._basis, st.dtype)

    def loss(raw):
        c = dict(c0)
        c["v"] = c0["v"].at[p._rows, p._col].set(raw["alpha"] * basis)
        pred, bad = JD.observe(st, c, fit.observation, fit.steps, fit.segment, health=True)
        r = (pred - ref) * m
        return (r * r).sum() / norm, bad

    vg = jax.jit(jax.value_and_grad(loss, has_aux=True))
    opt = optax.adam(lr)
    raw = {"alpha": jnp.asarray(float(p.init), st.dtype)}
    state = opt.init(raw)
    out = []
    for _ in range(epochs):
        (val, bad), g = vg(raw)
        assert not bool(bad)
        out.append((float(val), float(optax.global_norm(g)), float(raw["alpha"])))
        updates, state = opt.update(g, state, raw)
        raw = optax.apply_updates(raw, updates)
    return out, float(loss(raw)[0])


def _direct_warp(fit, p, epochs, lr):
    """The fit written against torch directly (as fit.py's torch loop did before the adapter)."""
    import torch

    st, c0 = fit.stepper, fit.stepper.controls()
    mask = fit._mask()
    norm = float(mask.sum() * fit.reference.shape[2])
    dt = torch.float64
    ref, m = torch.as_tensor(fit.reference, dtype=dt), torch.as_tensor(mask, dtype=dt)[..., None]
    basis = torch.as_tensor(p._basis, dtype=dt)
    alpha = torch.as_tensor(np.asarray(float(p.init)), dtype=dt).clone().requires_grad_(True)
    opt = torch.optim.Adam([alpha], lr=lr)

    def loss():
        c = dict(c0)
        c["v"] = c0["v"].clone()
        c["v"][p._rows, p._col] = alpha * basis
        r = (st.observe(c, fit.observation, fit.steps, fit.segment) - ref) * m
        return (r * r).sum() / norm

    out = []
    for _ in range(epochs):
        opt.zero_grad()
        val = loss()
        val.backward()
        out.append((float(val.detach()), float(torch.sqrt((alpha.grad ** 2).sum())), float(alpha.detach())))
        opt.step()
    with torch.no_grad():
        return out, float(loss())


@pytest.mark.parametrize("backend", BACKENDS)
def test_tiny_fit_through_the_adapter_equals_the_direct_computation(backend):
    fit = tiny_fit(backend)
    p = fit.parameters[0]
    if backend == "jax":
        import optax

        opt = (optax.adam(LR),)
    else:
        import torch

        opt = (lambda prm: torch.optim.Adam(prm, lr=LR),)
    fit.run(EPOCHS, *opt)
    got = [(h["loss"], h["grad_norm"], h["values"]["alpha"]) for h in fit.history]
    want, final = (_direct_jax if backend == "jax" else _direct_warp)(fit, p, EPOCHS, LR)
    assert got == want                                       # bit for bit: same steps, same numbers
    assert fit.final_loss == final
    assert got[-1][0] < got[0][0] and all(math.isfinite(v) for row in got for v in row)


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_non_finite_loss_derivative_is_located(backend):
    """locate_nan_gradient names the observed step when the loss's derivative is NaN, on either backend."""
    fit = tiny_fit(backend)
    st = fit.stepper
    with pytest.raises(GradientError, match="step 1") as err:
        fit.adapter.locate_nan_gradient(st, st.controls(), fit.observation, fit.steps,
                                        lambda y: (y * float("nan")).sum(), fit.segment)
    assert err.value.step == 1
