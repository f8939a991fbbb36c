"""The reduced rollout as a differentiable function (issue 16, item 7, JAX): gradients in the initial
latent state and a law parameter against central differences, on the 2D beam with a random smooth
deformation map (a random MLP, displacements of a few mm)."""
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


@pytest.mark.parametrize("projection,h,rel", [("linear", 1e-6, 1e-6), ("nonlinear", 1e-3, 2e-3)])
def test_reverse_mode_gradient_of_a_lagrangian_rollout_matches_central_differences(beam, projection, h, rel):
    """jax.grad through 20 reduced steps (Lagrangian quadrature) in x_hat_0 and E. The nonlinear
    projection's Gauss-Newton stops after a fixed number of backtracked iterations, which makes the
    rollout itself noisy at the 1e-12 level of the loss: its differences need a larger step, and agree
    to 2e-3 (measured 2e-4 at h = 1e-3 and 1e-4)."""
    import jax

    from mpmlab.rom.stepper import ReducedStepper

    fom, w = beam
    rom = ReducedStepper(fom, w, samples=30, quadrature="lagrangian", projection=projection)
    loss, z0 = _loss(rom)
    loss = jax.jit(loss)
    gz, gE = jax.grad(loss, argnums=(0, 1))(z0, 1.0)
    fd_E = (loss(z0, 1.0 + h) - loss(z0, 1.0 - h)) / (2 * h)
    assert abs(float(gE)) > 0 and float(gE) == pytest.approx(float(fd_E), rel=rel)
    for k in range(z0.shape[0]):
        e = np.zeros(z0.shape[0]); e[k] = h
        fd = (loss(z0 + e, 1.0) - loss(z0 - e, 1.0)) / (2 * h)
        assert float(gz[k]) == pytest.approx(float(fd), rel=rel, abs=1e-9 * float(np.abs(gz).max()))


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
