"""The reduced model's position-level hold of particle_velocity boundaries (``mpmlab.rom.kinematic``; the
paper's Eq. 3 is a condition on positions): the closed-form prescribed positions are where the full-order
model's exactly rigid steps put the held particles, a drifted reduced state returns to them in one step
(the velocity-level hold keeps the drift), both backends agree, and what is refused."""
from __future__ import annotations

import numpy as np
import pytest

from mpmlab.core.errors import ConfigError
from mpmlab.rom.stepper import reduced_stepper
from mpmlab.simulator import build_stepper

from .test_rom_stepper import _boundary_scene, random_map, translation


@pytest.mark.parametrize("dim", (2, 3))
def test_the_prescribed_positions_are_where_the_full_order_steps_put_the_held_particles(dim):
    """200 full-order steps of a grip pulled at 0.2 m/s (and spun at 3 rad/s in 3D: 34 degrees): the held
    particles sit at the closed form x_bar(t) = c(t) + R(omega t) (X - c(0)) to round-off."""
    import jax.numpy as jnp

    from mpmlab.backends.jax.boundaries import _rotation
    from mpmlab.rom.kinematic import Holds

    sc = _boundary_scene(dim)
    fom = build_stepper(sc, "jax", "pic", "fp64")
    X = np.asarray(fom.particles.x)
    holds = Holds(sc, X, "position")
    held = np.nonzero(holds.which >= 0)[0]
    assert len(held) > 5 and holds.active
    x = np.asarray(fom.rollout(steps=200, every=200).x[-1])
    t1 = 200 * float(fom.dt)
    params = [{**{k: jnp.asarray(v) for k, v in (("velocity", b.velocity), ("angular_velocity", b.angular_velocity))
                  if v is not None}, "center": jnp.asarray(c)} for b, c in zip(holds.bcs, holds.centers)]
    target, on = holds.targets(jnp, lambda th: _rotation(th, dim), jnp.asarray(holds.which[held]), jnp.asarray(X[held]),
                               t1, params)
    assert bool(np.all(np.asarray(on)))
    moved = np.max(np.linalg.norm(x[held] - X[held], axis=1))
    assert moved > 0.03
    assert np.max(np.abs(np.asarray(target) - x[held])) <= 1e-12, np.max(np.abs(np.asarray(target) - x[held]))


def _held_only(backend):
    """The 2D grip scene on the translation manifold g = X + x_hat, with only the grip's 5 forced points as
    samples: every least-squares row is a held point."""
    fom = build_stepper(_boundary_scene(2), backend, "pic", "fp64")
    return fom, translation(2)


@pytest.mark.parametrize("backend", ("jax", "warp"))
@pytest.mark.parametrize("projection", ("linear", "nonlinear"))
def test_a_drifted_reduced_state_returns_to_the_prescribed_positions(backend, projection):
    """Started 1 cm off (x_hat = (0.01, 0)), one step with the position-level hold puts the held rows, and so
    the translating body, back on x_bar(dt) = X + v0 dt; the velocity-level hold keeps the 1 cm. v_hat is
    the prescribed velocity either way. Closing the error over 4 steps (``hold_steps``) closes a quarter of it."""
    fom, w = _held_only(backend)
    v0 = np.array([0.2, 0.0])
    ends = {}
    for mode, k in (("position", 1), ("velocity", 1), ("position", 4)):
        rom = reduced_stepper(fom, w, samples=5, projection=projection, kinematic=mode, hold_steps=k)
        s0 = rom.init()
        if backend == "jax":
            import jax.numpy as jnp
            s0 = s0._replace(z=jnp.asarray([0.01, 0.0]), z_prev=jnp.asarray([0.01, 0.0]))
        else:
            import torch
            s0 = s0._replace(z=torch.tensor([0.01, 0.0], dtype=torch.float64),
                             z_prev=torch.tensor([0.01, 0.0], dtype=torch.float64))
        s1 = rom.step(s0)
        ends[mode, k] = (np.asarray(rom._np(s1.z)), np.asarray(rom._np(s1.zdot)))
    dt = float(fom.dt)
    z, zdot = ends["position", 1]
    assert np.max(np.abs(z - v0 * dt)) <= 1e-12, z
    assert np.max(np.abs(zdot - v0)) <= 1e-9, zdot
    z, zdot = ends["velocity", 1]
    assert np.max(np.abs(z - (np.array([0.01, 0.0]) + v0 * dt))) <= 1e-12, z
    z, zdot = ends["position", 4]
    assert np.max(np.abs(z - (np.array([0.0075, 0.0]) + v0 * dt))) <= 1e-12, z


@pytest.mark.parametrize("quadrature", ("lagrangian", "eulerian"))
@pytest.mark.parametrize("dim", (2, 3))
def test_warp_replays_the_jax_rollout_with_the_position_hold(dim, quadrature):
    """A random smooth map on the grip scene (rotating in 3D), both backends from the same initial state (JAX's
    Eq. 19 fit) and JAX's draws replayed on Warp, the position-level hold on: the latent trajectories agree.
    This map starts the grip's points 0.7 mm off their prescribed positions, so the hold's first steps are
    1 m/s corrections and the rollout amplifies any difference ~1e4-fold in 12 steps (measured: a 7.8e-8 change
    of JAX's own initial latent ends 1.3e-3 apart; the velocity-level hold: 3.9e-7): hence one start. Measured,
    relative to max |x_hat|: Lagrangian 3e-15 (2D), 2e-11 (3D); Eulerian (its inverse map's Newton iterations
    add round-off) 1e-13 (2D), 1e-9 (3D)."""
    import torch

    sc = _boundary_scene(dim)
    fj, fw = build_stepper(sc, "jax", "pic", "fp64"), build_stepper(sc, "warp", "pic", "fp64")
    w = random_map(np.asarray(fj.particles.x), dim)
    kw = dict(samples=12, quadrature=quadrature, eulerian_capacity=1e9)
    rj = reduced_stepper(fj, w, **kw)
    assert rj.kinematic == "position" and rj._holds.active
    sj = rj.init()
    oj = rj.rollout(sj, steps=12, every=4)
    rw = reduced_stepper(fw, w, draws=rj.draws(12), **kw)
    as_t = lambda a: torch.as_tensor(np.array(a), dtype=torch.float64)      # noqa: E731
    sw = rw.init()._replace(z=as_t(sj.z), zdot=as_t(sj.zdot), z_prev=as_t(sj.z_prev))
    ow = rw.rollout(sw, steps=12, every=4)
    assert np.ptp(oj["z"], axis=0).max() > 1e-2
    d = np.max(np.abs(oj["z"] - ow["z"])) / max(1.0, np.max(np.abs(oj["z"])))
    assert d <= (1e-9 if quadrature == "lagrangian" else 1e-8), d
    # the hold changes the trajectory (the grip's rows reach their prescribed positions)
    ov = reduced_stepper(fj, w, kinematic="velocity", **kw).rollout(sj, steps=12, every=4)
    assert np.max(np.abs(ov["z"] - oj["z"])) > 1e-2


def test_refusals():
    from mpmlab.boundaries import make_boundary

    fom = build_stepper(_boundary_scene(2), "jax", "pic", "fp64")
    with pytest.raises(ConfigError, match="choose position or velocity"):
        reduced_stepper(fom, translation(2), samples=12, kinematic="force")
    with pytest.raises(ConfigError, match="hold_steps = 0.5; .* at least 1"):
        reduced_stepper(fom, translation(2), samples=12, hold_steps=0.5)
    sc = _boundary_scene(2)
    late = {"kind": "particle_velocity", "region": {"kind": "box", "lo": [0.5, 0.0], "hi": [1.0, 1.0]},
            "velocity": [0.2, 0.0], "t_start": 0.1}
    sc.boundaries = [b for b in sc.boundaries if b.stage != "particle_velocity"] + [make_boundary(late)]
    fom = build_stepper(sc, "jax", "pic", "fp64")
    with pytest.raises(ConfigError, match="t_start = 0.1 s; kinematic='position'"):
        reduced_stepper(fom, translation(2), samples=12)
    assert reduced_stepper(fom, translation(2), samples=12, kinematic="velocity").kinematic == "velocity"
