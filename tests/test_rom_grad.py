"""The reduced rollout as a differentiable function (issue 16, item 7, JAX and Warp): gradients in the
initial latent state and a law parameter against central differences and across backends, on the 2D
beam with a random smooth deformation map (a random MLP, displacements of a few mm)."""
from __future__ import annotations

import numpy as np
import pytest

from mpmlab.core.errors import ConfigError


@pytest.fixture(scope="module")
def beam():
    import jax

    jax.config.update("jax_enable_x64", True)
    from mpmlab.build import build_scene
    from mpmlab.config import compose
    from mpmlab.rom import networks as N
    from mpmlab.simulator import build_stepper

    scene = build_scene(compose(["scene=rom_beam_2d", "scene.resolution=tiny"]))
    fom = build_stepper(scene, "jax", "pic", "fp64")
    spec = N.RomSpec(dim=2, latent=3)
    X = np.asarray(fom.particles.x)
    norm = {"X_min": X.min(0), "X_max": X.max(0), "u_mean": np.zeros(2), "u_std": np.full(2, 3e-3)}
    return fom, N.RomWeights(N.init_params(spec, seed=3), norm, spec, 3)


def _loss(rom, steps=20, every=10):
    import jax.numpy as jnp

    from mpmlab.rom import networks as N

    f = rom.rollout_fn(steps, every)
    s0 = rom.init()
    Xo = rom.X[::3]
    target = Xo + jnp.array([0.0, -0.002])

    def loss(z0, scale):
        law = (rom.law_params[0] * jnp.array([scale, 1.0]),)          # rows [E, nu]: scale E
        zs = f(z0, s0.zdot + 0.05, law)
        return jnp.sum((N.g_apply(rom.params, rom.norm, Xo, zs[-1][None]) - target) ** 2)

    return loss, s0.z


_JAX = {}


def jax_gradient(beam, projection):
    """(rom, loss, z0, dloss/dz0, dloss/dE) of the JAX reduced rollout, computed once per projection."""
    import jax

    from mpmlab.rom.stepper import ReducedStepper

    if projection not in _JAX:
        fom, w = beam
        rom = ReducedStepper(fom, w, samples=30, quadrature="lagrangian", projection=projection)
        loss, z0 = _loss(rom)
        loss = jax.jit(loss)
        gz, gE = jax.grad(loss, argnums=(0, 1))(z0, 1.0)
        _JAX[projection] = (rom, loss, z0, np.asarray(gz), float(gE))
    return _JAX[projection]


@pytest.mark.parametrize("projection,h,rel", [("linear", 1e-6, 1e-6), ("nonlinear", 1e-3, 2e-3)])
def test_reverse_mode_gradient_of_a_lagrangian_rollout_matches_central_differences(beam, projection, h, rel):
    """jax.grad through 20 reduced steps (Lagrangian quadrature) in x_hat_0 and E. The nonlinear
    projection's Gauss-Newton stops after a fixed number of backtracked iterations, which makes the
    rollout itself noisy at the 1e-12 level of the loss: its differences need a larger step, and agree
    to 2e-3 (measured 2e-4 at h = 1e-3 and 1e-4)."""
    rom, loss, z0, gz, gE = jax_gradient(beam, projection)
    fd_E = (loss(z0, 1.0 + h) - loss(z0, 1.0 - h)) / (2 * h)
    assert abs(gE) > 0 and gE == pytest.approx(float(fd_E), rel=rel)
    for k in range(z0.shape[0]):
        e = np.zeros(z0.shape[0]); e[k] = h
        fd = (loss(z0 + e, 1.0) - loss(z0 - e, 1.0)) / (2 * h)
        assert float(gz[k]) == pytest.approx(float(fd), rel=rel, abs=1e-9 * float(np.abs(gz).max()))


@pytest.mark.parametrize("projection,rel", [("linear", 1e-10), ("nonlinear", 1e-5)])
def test_warp_reduced_rollout_gradient_matches_jax_and_differences(beam, projection, rel):
    """The Warp reduced rollout (torch autograd through g and the projections, a wp.Tape per Warp step),
    the JAX stepper's draws replayed: its gradient in x_hat_0 and E is JAX's (measured 5e-14 relative,
    linear), and its E derivative matches its own central differences."""
    import torch

    from mpmlab.rom import networks_torch as NT
    from mpmlab.rom.stepper import reduced_stepper
    from mpmlab.simulator import build_stepper

    rj, _, _, gz, gE = jax_gradient(beam, projection)
    fom, w = beam
    rom = reduced_stepper(build_stepper(fom.scene, "warp", "pic", "fp64"), w, samples=30, projection=projection,
                          draws=rj.draws(20))
    f, s0 = rom.rollout_fn(20, 10), rom.init()
    Xo = rom.X[::3]
    target = Xo + torch.tensor([0.0, -0.002], dtype=torch.float64)
    one = torch.ones((), dtype=torch.float64)

    def loss(z0, scale):
        zs = f(z0, s0.zdot + 0.05, (rom.law_params[0] * torch.stack([scale, one]),))
        return torch.sum((NT.g_apply(rom.params, rom.norm, Xo, zs[-1][None]) - target) ** 2)

    z0 = s0.z.clone().requires_grad_(True)
    scale = torch.tensor(1.0, dtype=torch.float64, requires_grad=True)
    loss(z0, scale).backward()
    assert np.max(np.abs(z0.grad.numpy() - gz)) <= rel * np.max(np.abs(gz))
    assert scale.grad.item() == pytest.approx(gE, rel=rel)
    if projection == "linear":
        h = 1e-6
        with torch.no_grad():
            fd = (loss(s0.z, one + h) - loss(s0.z, one - h)) / (2 * h)
        assert scale.grad.item() == pytest.approx(fd.item(), rel=1e-6)


def test_forward_mode_derivative_of_an_eulerian_rollout_matches_central_differences(beam):
    """The Eulerian quadrature's inverse map is a Newton loop with a data-dependent end, which reverse
    mode refuses; forward mode runs through it."""
    import jax

    from mpmlab.rom.stepper import ReducedStepper

    fom, w = beam
    rom = ReducedStepper(fom, w, samples=10, quadrature="eulerian", projection="linear")
    loss, z0 = _loss(rom, steps=10, every=10)
    loss = jax.jit(loss)
    _, dE = jax.jvp(lambda s: loss(z0, s), (1.0,), (1.0,))
    h = 1e-6
    fd = (loss(z0, 1.0 + h) - loss(z0, 1.0 - h)) / (2 * h)
    assert abs(float(dE)) > 0 and float(dE) == pytest.approx(float(fd), rel=1e-5)


def test_rollout_fn_refuses_steps_that_are_not_frames(beam):
    from mpmlab.rom.stepper import ReducedStepper

    fom, w = beam
    rom = ReducedStepper(fom, w, samples=10)
    with pytest.raises(ConfigError, match="multiple of every"):
        rom.rollout_fn(15, 10)
