"""The reduced stepper on Warp (``mpmlab.rom.stepper_warp``, ROM paper Sec. 3, Alg. 2): the rigid-translation
manifold's free fall matches the full-order model, a body at rest stays at rest, the same draws give the
JAX stepper's latent trajectory on a nonlinear map (both quadratures, both projections), and what it
refuses. Its gradients: tests/test_rom_grad.py."""
from __future__ import annotations

import numpy as np
import pytest

import mpmlab
from mpmlab.core.errors import ConfigError
from mpmlab.rom.stepper import ReducedStepper, reduced_stepper
from mpmlab.rom.stepper_warp import WarpReducedStepper
from mpmlab.simulator import build_stepper

from .test_rom_stepper import _boundary_scene, random_map, scene, translation


COMBINATIONS = [(q, p) for q in ("lagrangian", "eulerian") for p in ("linear", "nonlinear")]


@pytest.mark.parametrize("quadrature,projection", COMBINATIONS)
def test_free_fall_on_the_translation_manifold_matches_the_full_order_model(quadrature, projection):
    sc = scene(velocity=[0.3, 0.1])
    ref = mpmlab.simulate(sc, 60, 60, "warp", "pic", "fp64")
    rom = reduced_stepper(build_stepper(sc, "warp", "pic", "fp64"), translation(2), samples=12, quadrature=quadrature,
                          projection=projection)
    assert isinstance(rom, WarpReducedStepper)
    out = rom.rollout(steps=60, every=60)
    assert np.max(np.abs(out["x"][-1] - ref.x[-1])) <= 1e-10
    assert np.max(np.abs(rom.to_numpy(out["state"])["v"] - ref.v[-1])) <= 1e-10


@pytest.mark.parametrize("quadrature", ("lagrangian", "eulerian"))
def test_a_body_at_rest_stays_at_rest(quadrature):
    rom = reduced_stepper(build_stepper(scene(gravity=(0.0, 0.0)), "warp", "pic", "fp64"), translation(2), samples=8,
                          quadrature=quadrature)
    assert np.max(np.abs(rom.rollout(steps=20, every=20)["z"])) == 0.0


def test_a_body_that_outgrows_the_eulerian_budget_stops_the_rollout():
    """As on JAX (tests/test_rom_stepper.py): a translation onto more lattice points than the budget holds."""
    import torch

    rom = reduced_stepper(build_stepper(scene(gravity=(0.0, 0.0), shift=0.015), "warp", "pic", "fp64"), translation(2),
                          samples=32, quadrature="eulerian", eulerian_capacity=1.0)
    s = rom.init()
    rom.rollout(s, steps=2)
    with pytest.raises(ConfigError, match="raise eulerian_capacity"):
        rom.rollout(s._replace(z=torch.tensor([-0.015, -0.015], dtype=torch.float64)), steps=2)


@pytest.fixture(scope="module")
def beam():
    """The 2D beam at `tiny` (clamped by sticky walls) on both backends, and a random smooth map (a random
    MLP, displacements of a few mm; as tests/test_rom_grad.py)."""
    from mpmlab.build import build_scene
    from mpmlab.config import compose

    sc = build_scene(compose(["scene=rom_beam_2d", "scene.resolution=tiny"]))
    fj, fw = build_stepper(sc, "jax", "pic", "fp64"), build_stepper(sc, "warp", "pic", "fp64")
    return fj, fw, random_map(np.asarray(fj.particles.x), 2, seed=3)


@pytest.mark.parametrize("quadrature,projection,samples,tol_z,tol_x",
                         [("lagrangian", "linear", 30, 1e-11, 1e-14), ("lagrangian", "nonlinear", 30, 1e-6, 1e-9),
                          ("eulerian", "linear", 10, 1e-11, 1e-14), ("eulerian", "nonlinear", 10, 2e-5, 1e-8)])
def test_warp_replays_the_jax_reduced_rollout(beam, quadrature, projection, samples, tol_z, tol_x):
    """100 steps, the JAX stepper's draws replayed on Warp: the latent trajectories agree (x_hat moves
    by 3-6 over the run) and so do the Eulerian quadrature's off-body counts. Linear: to round-off
    (measured 1e-14 / 6e-14). Nonlinear: Gauss-Newton's fixed iterations and backtracking amplify the
    two LAPACKs' round-off (measured 6e-8 / 5e-6 in x_hat, 1e-11 / 6e-10 m)."""
    fj, fw, w = beam
    rj = ReducedStepper(fj, w, samples=samples, quadrature=quadrature, projection=projection)
    rw = reduced_stepper(fw, w, samples=samples, quadrature=quadrature, projection=projection, draws=rj.draws(100))
    oj, ow = rj.rollout(steps=100, every=20), rw.rollout(steps=100, every=20)
    assert np.ptp(oj["z"], axis=0).max() > 1.0
    assert np.max(np.abs(oj["z"] - ow["z"])) <= tol_z
    assert np.max(np.abs(oj["x"] - ow["x"])) <= tol_x
    assert int(ow["state"].outside) == int(oj["state"].outside)
    assert int(ow["state"].unconverged) == int(oj["state"].unconverged) == 0
    if quadrature == "lagrangian" and projection == "linear":
        # its own seeded draws are other points: another (close) trajectory, not the same one
        own = reduced_stepper(fw, w, samples=samples, projection=projection).rollout(steps=100, every=20)
        assert np.max(np.abs(own["z"] - oj["z"])) > 1e-6


@pytest.mark.parametrize("dim", (2, 3))
def test_warp_replays_the_jax_eulerian_rollout_with_every_boundary_kind(dim):
    """The Eulerian quadrature with walls, a Coulomb floor and a grip (particle_velocity + grid_velocity,
    rotating in 3D) on both backends, JAX's draws replayed on Warp: the grip acts on the samples through
    Warp's scratch arrays (written at the samples' rows only, never cleared) and through JAX's
    ``apply_particles(..., rows=)``; the latent trajectories agree. The initial states (Eq. 19's
    Gauss-Newton on this random map, |x_hat| up to 22 in 3D) already differ by what the two linear-algebra
    libraries make of it on the machine, and the steps add little: 3D 2.9e-8 at step 0, 4.9e-8 after 12 (an
    Intel Xeon); 2D 2.5e-9 and 4.1e-9 on an AMD EPYC, where 2D was 1e-11 on the Xeon. So the test bounds the
    initial difference and what the steps add to it; a grip about another centre moves x_hat by orders more."""
    sc = _boundary_scene(dim)
    fj, fw = build_stepper(sc, "jax", "pic", "fp64"), build_stepper(sc, "warp", "pic", "fp64")
    w = random_map(np.asarray(fj.particles.x), dim)
    # the velocity-level hold: with the position-level one this map's grip misfit amplifies the initial
    # states' difference ~1e4-fold (tests/test_rom_kinematic.py replays it from one initial state)
    kw = dict(samples=12, quadrature="eulerian", projection="linear", eulerian_capacity=1e9, kinematic="velocity")
    rj = ReducedStepper(fj, w, **kw)
    oj = rj.rollout(steps=12, every=4)
    ow = reduced_stepper(fw, w, draws=rj.draws(12), **kw).rollout(steps=12, every=4)
    assert np.ptp(oj["z"], axis=0).max() > 1e-4
    scale = max(1.0, np.max(np.abs(oj["z"])))
    d0, d = np.max(np.abs(oj["z"][0] - ow["z"][0])), np.max(np.abs(oj["z"] - ow["z"]))
    assert d0 <= 5e-9 * scale and d <= 3.0 * d0 + 1e-11 * scale, (d0, d)


@pytest.mark.parametrize("dim", (2, 3))
def test_the_compact_node_set_steps_as_the_scene_grid_does(dim):
    """Warp's Eulerian quadrature with its grid update over the samples' windows' nodes only
    (backends/warp/node_list.py) gives the scene grid's steps exactly: walls, a Coulomb floor and a grip.
    The list must hold every node the points reach and each once: a missed node keeps its P2G sums into
    the next step, a node listed twice is updated from cleared sums."""
    fw = build_stepper(_boundary_scene(dim), "warp", "pic", "fp64")
    w = random_map(np.asarray(fw.particles.x), dim)
    # few samples, so that windows overlap little and a window's edge nodes are listed by it alone (with 12
    # samples a list one node short per axis still passed: measured)
    kw = dict(samples=4, per_boundary=1, quadrature="eulerian", projection="linear", eulerian_capacity=1e9)
    compact = WarpReducedStepper(fw, w, nodes="compact", **kw)
    assert compact._pseudo.node_list is not None
    a = compact.rollout(steps=12, every=4)
    assert not compact._pseudo.grid_mm.numpy().any()          # every P2G sum was read and cleared
    b = WarpReducedStepper(fw, w, nodes="scene", **kw).rollout(steps=12, every=4)
    assert np.ptp(b["z"], axis=0).max() > 1e-4
    assert np.array_equal(a["z"], b["z"])


def test_a_node_list_holds_each_window_node_once():
    """Overlapping windows list their shared nodes once, nodes off the grid are skipped, and a release
    leaves the claims clear for the next step."""
    from mpmlab.backends.warp.node_list import NodeList

    nl = NodeList(2, (6, 5), width=3, windows=3)
    origins = np.array([[0, 0], [1, 1], [4, 3]])
    expect = sorted({(i + a) * 5 + (j + b) for i, j in origins for a in range(3) for b in range(3)
                     if 0 <= i + a < 6 and 0 <= j + b < 5})
    for _ in range(2):
        nl.claim_windows(origins)
        assert nl.listed().tolist() == expect
        nl.release()
        assert not nl.flag.numpy().any()


def test_refusals(beam):
    fj, fw, w = beam
    with pytest.raises(ConfigError, match="differentiable reduced rollout uses the Lagrangian quadrature"):
        reduced_stepper(fw, w, samples=10, quadrature="eulerian").rollout_fn(10)
    with pytest.raises(ConfigError, match="multiple of every"):
        reduced_stepper(fw, w).rollout_fn(15, 10)
    with pytest.raises(ConfigError, match="on backend 'warp'; build it with backend 'jax'"):
        ReducedStepper(fw, w)
    with pytest.raises(ConfigError, match="on backend 'jax'; build it with backend 'warp'"):
        WarpReducedStepper(fj, w)
    with pytest.raises(ConfigError, match="PIC"):
        reduced_stepper(build_stepper(scene(), "warp", "apic", "fp64"), translation(2))
    rw = reduced_stepper(fw, w, samples=30, draws=[np.arange(30)])
    s = rw.step(rw.init())
    with pytest.raises(ConfigError, match="step 2 has no sample rows"):
        rw.step(s)
