"""The reduced stepper (ROM paper Sec. 3, Alg. 2) on the rigid-translation manifold g = X + x_hat: free
fall matches the full-order model, a body at rest stays at rest, and what it refuses."""
from __future__ import annotations

import numpy as np
import pytest

import mpmlab
from mpmlab.core.errors import ConfigError
from mpmlab.rom import networks as N
from mpmlab.rom.stepper import _EULER_REACH, ReducedStepper, eulerian_footprint
from mpmlab.simulator import build_stepper


def scene(gravity=(0.0, -9.8), dim=2, law="fixed_corotated", velocity=None, shift=0.0):
    g = list(gravity) + [0.0] * (dim - len(gravity))
    lo, hi = [0.3 + shift] * dim, [0.5 + shift] + [0.4 + shift] * (dim - 1)
    body = mpmlab.Body(shape={"kind": "box", "lo": lo, "hi": hi}, material=law,
                       params={"E": 2e4, "nu": 0.3}, density=1000.0, particles_per_cell=4 if dim == 2 else 8,
                       velocity=velocity)
    return mpmlab.Scene(dim=dim, dx=0.05, domain=([0.0] * dim, [1.0] * dim), bodies=[body], gravity=g, dt=1e-3,
                        name="rom_free_fall")


def translation(dim):
    spec = N.RomSpec(dim=dim, latent=dim)
    return N.RomWeights(N.linear_params(spec, np.zeros((dim, dim)), np.eye(dim)), N.identity_norm(dim), spec, 0)


COMBINATIONS = [(q, p) for q in ("lagrangian", "eulerian") for p in ("linear", "nonlinear")]


@pytest.mark.parametrize("quadrature,projection", COMBINATIONS)
def test_free_fall_on_the_translation_manifold_matches_the_full_order_model(quadrature, projection):
    sc = scene(velocity=[0.3, 0.1])
    fom = build_stepper(sc, "jax", "pic", "fp64")
    ref = mpmlab.simulate(sc, 60, 60, "jax", "pic", "fp64")
    rom = ReducedStepper(fom, translation(2), samples=12, quadrature=quadrature, projection=projection)
    out = rom.rollout(steps=60, every=60)
    assert np.max(np.abs(out["x"][-1] - ref.x[-1])) <= 1e-10
    assert np.max(np.abs(rom.to_numpy(out["state"])["v"] - ref.v[-1])) <= 1e-10


@pytest.mark.parametrize("quadrature", ("lagrangian", "eulerian"))
def test_a_body_at_rest_stays_at_rest(quadrature):
    fom = build_stepper(scene(gravity=(0.0, 0.0)), "jax", "pic", "fp64")
    rom = ReducedStepper(fom, translation(2), samples=8, quadrature=quadrature)
    out = rom.rollout(steps=20, every=20)
    assert np.max(np.abs(out["z"])) == 0.0


def test_eulerian_quadrature_points_carry_the_body_mass():
    """Alg. 4 on g = X + x_hat: the points reaching the samples' nodes sit on the half-cell lattice, their
    X_q = x_q - x_hat exactly, and those inside the reference body carry rho_0 V_q each: with every
    material point a sample, the quadrature mass is the body's mass (a box aligned with the cells)."""
    import jax.numpy as jnp

    sc = scene(gravity=(0.0, 0.0))
    fom = build_stepper(sc, "jax", "pic", "fp64")
    n = fom.particles.count
    rom = ReducedStepper(fom, translation(2), samples=n, quadrature="eulerian")
    s = rom.init()._replace(z=jnp.asarray([0.00625, -0.025]))        # no lattice point on a voxel face
    x, v, law, prm, rows, (outside, unconverged, overflow), _ = rom._eulerian_points(s, jnp.arange(n))
    body = float(np.sum(fom.particles.mass))
    assert float(jnp.sum(prm["mass"])) == pytest.approx(body, rel=1e-12)
    assert int(unconverged) == 0 and int(outside) > 0 and int(overflow) == 0    # outside: the ring of cells around the box
    m = np.asarray(prm["mass"][:rom._q_size])
    assert np.allclose(m[m > 0], 1000.0 * 0.05 ** 2 / 4, rtol=1e-12)


@pytest.mark.parametrize("dim", (2, 3))
def test_eulerian_footprint_counts_the_lattice_points_reaching_the_body(dim):
    """The separable dilation gives the distinct lattice points 2 base + [-3, 6]^d of a point cloud (those
    inside the lattice), as the brute-force set does; a point near the grid's edge clips there."""
    rng = np.random.default_rng(dim)
    grid, dx, origin = (12,) * dim, 0.1, np.full(dim, -0.2)
    x = origin + rng.uniform(0.05, 1.15, size=(40, dim))
    base = np.floor((x - origin) / dx - 0.5).astype(int)
    off = np.stack(np.meshgrid(*[_EULER_REACH] * dim, indexing="ij"), -1).reshape(-1, dim)
    j = (2 * base[:, None, :] + off[None]).reshape(-1, dim)
    j = j[np.all((j >= 0) & (j < 2 * np.asarray(grid)), axis=1)]
    assert eulerian_footprint(x, origin, dx, grid) == len(np.unique(j, axis=0)) > 0


def test_the_eulerian_point_budget_changes_no_step():
    """The budget (1.5 x the body's footprint, far below |M| 10^d here) drops only padding: the rollout of a
    nonlinear map is the one with every |M| 10^d slot."""
    fom = build_stepper(scene(gravity=(0.0, -3.0)), "jax", "pic", "fp64")
    spec = N.RomSpec(dim=2, latent=3)
    X = np.asarray(fom.particles.x)
    norm = {"X_min": X.min(0), "X_max": X.max(0), "u_mean": np.zeros(2), "u_std": np.full(2, 3e-3)}
    w = N.RomWeights(N.init_params(spec, seed=3), norm, spec, 3)
    small = ReducedStepper(fom, w, samples=20, quadrature="eulerian")
    full = ReducedStepper(fom, w, samples=20, quadrature="eulerian", eulerian_capacity=1e9)
    assert small._q_size < full._q_size == 20 * 10 ** 2
    a, b = small.rollout(steps=20, every=10), full.rollout(steps=20, every=10)
    assert np.ptp(a["z"], axis=0).max() > 1e-3 and np.array_equal(a["z"], b["z"])


def random_map(X, dim, seed=5, latent=3):
    """A random smooth map (a random MLP, displacements of a few mm) for the points X [N, dim]."""
    spec = N.RomSpec(dim=dim, latent=latent)
    norm = {"X_min": X.min(0), "X_max": X.max(0), "u_mean": np.zeros(dim), "u_std": np.full(dim, 3e-3)}
    return N.RomWeights(N.init_params(spec, seed=seed), norm, spec, seed)


def _boundary_scene(dim):
    """A body on a Coulomb floor, gripped at one end (particle_velocity + grid_velocity, rotating in 3D),
    between separating walls, under gravity: every built-in grid boundary kind the ROM scenes use."""
    lo, hi = [0.3] * dim, [0.55] + [0.45] * (dim - 1)
    body = mpmlab.Body(shape={"kind": "box", "lo": lo, "hi": hi}, material="fixed_corotated",
                       params={"E": 2e4, "nu": 0.3}, density=1000.0, particles_per_cell=4 if dim == 2 else 8)
    grip = {"kind": "box", "lo": [0.5] + [0.0] * (dim - 1), "hi": [1.0] * dim}
    spin = {} if dim == 2 else {"angular_velocity": [3.0, 0.0, 0.0]}
    bcs = {"walls": {"kind": "walls", "default": "separate", "thickness": 2},
           "floor": {"kind": "friction_walls", "face": "y-", "along": "x", "mu": [0.3], "thickness": 7},
           "grip": {"kind": "particle_velocity", "region": grip, "velocity": [0.2] + [0.0] * (dim - 1), **spin},
           "grip_grid": {"kind": "grid_velocity", "region": grip, "velocity": [0.2] + [0.0] * (dim - 1), **spin}}
    from mpmlab.boundaries import make_boundary

    return mpmlab.Scene(dim=dim, dx=0.05, domain=([0.0] * dim, [1.0] * dim), bodies=[body],
                        boundaries=[make_boundary(v) for v in bcs.values()], gravity=[0.0, -9.8] + [0.0] * (dim - 2), dt=1e-3, name="rom_compact_nodes")


@pytest.mark.parametrize("dim", (2, 3))
def test_the_compact_node_set_steps_as_the_scene_grid_does(dim):
    """The Eulerian quadrature on windows around the samples (backends/jax/node_windows.py) gives the
    scene grid's steps to round-off: overlapping windows summed, every boundary read at the windows' nodes,
    the grip applied to the samples only. A nonlinear map, so the points carry different F and v."""
    fom = build_stepper(_boundary_scene(dim), "jax", "pic", "fp64")
    w = random_map(np.asarray(fom.particles.x), dim)
    # velocity-level hold: this random map starts the grip 0.7 mm off, and the position-level hold's corrections
    # amplify round-off ~1e4-fold in 12 steps (tests/test_rom_kinematic.py), which is not what is tested here
    kw = dict(samples=12, quadrature="eulerian", projection="linear", eulerian_capacity=1e9, kinematic="velocity")
    a = ReducedStepper(fom, w, nodes="compact", **kw).rollout(steps=12, every=4)
    b = ReducedStepper(fom, w, nodes="scene", **kw).rollout(steps=12, every=4)
    assert np.ptp(b["z"], axis=0).max() > 1e-4
    assert np.max(np.abs(a["z"] - b["z"])) <= 1e-12 * max(1.0, np.max(np.abs(b["z"])))


def test_a_body_that_outgrows_the_eulerian_budget_stops_the_rollout():
    """With the budget at exactly the initial footprint, a translation that moves the body onto more lattice
    points (from 4 x 2 base cells to 5 x 3) needs more points than it has: a one-line ConfigError, not
    dropped mass."""
    import jax.numpy as jnp

    fom = build_stepper(scene(gravity=(0.0, 0.0), shift=0.015), "jax", "pic", "fp64")
    rom = ReducedStepper(fom, translation(2), samples=fom.particles.count, quadrature="eulerian", eulerian_capacity=1.0)
    s = rom.init()
    rom.rollout(s, steps=2)                                       # in place: within the budget
    with pytest.raises(ConfigError, match="raise eulerian_capacity"):
        rom.rollout(s._replace(z=jnp.asarray([-0.015, -0.015])), steps=2)
    with pytest.raises(ConfigError, match="at least 1"):
        ReducedStepper(fom, translation(2), samples=8, quadrature="eulerian", eulerian_capacity=0.5)


def test_refusals():
    fom = build_stepper(scene(), "jax", "pic", "fp64")
    w = translation(2)
    for kw, msg in (({"samples": 1}, "at least the latent size"), ({"quadrature": "gauss"}, "lagrangian or eulerian"),
                    ({"projection": "exact"}, "choose linear or nonlinear")):
        with pytest.raises(ConfigError, match=msg):
            ReducedStepper(fom, w, **kw)
    with pytest.raises(ConfigError, match="PIC"):
        ReducedStepper(build_stepper(scene(), "jax", "apic", "fp64"), w)
    with pytest.raises(ConfigError, match="not hyperelastic"):
        sc = scene(law="hencky_von_mises")
        sc.bodies[0].params = {"E": 2e4, "nu": 0.3, "yield_stress": 100.0}
        ReducedStepper(build_stepper(sc, "jax", "pic", "fp64"), w)
    with pytest.raises(ConfigError, match="3D"):
        ReducedStepper(fom, translation(3))


def folded(dim):
    """g = X + x_hat + A X with A = diag(-2, 0, ..): F = diag(-1, 1, ..), det F = -1 everywhere."""
    spec = N.RomSpec(dim=dim, latent=dim)
    A = np.zeros((dim, dim))
    A[0, 0] = -2.0
    return N.RomWeights(N.linear_params(spec, A, np.eye(dim)), N.identity_norm(dim), spec, 0)


@pytest.mark.parametrize("backend", ("jax", "warp"))
def test_a_folded_map_stops_the_rollout(backend):
    """The full-order guard's J > 0 check on the reduced model: a map with det dg/dX <= 0 raises
    SimulationDiverged (field J) at the first kept frame."""
    from mpmlab.core.errors import SimulationDiverged
    from mpmlab.rom.stepper import reduced_stepper

    rom = reduced_stepper(build_stepper(scene(gravity=(0.0, 0.0)), backend, "pic", "fp64"), folded(2), samples=8)
    with pytest.raises(SimulationDiverged, match="deformation map folded") as e:
        rom.rollout(steps=2, every=1)
    assert e.value.field == "J" and e.value.step == 0 and e.value.value == pytest.approx(-1.0)


def curved_translation(dim, c=-0.5):
    """g(X; x_hat) = X + phi(x_hat) - phi(0) per component, phi = ELU applied depth times to x_hat + c: a
    rigid translation whose dg/dx_hat = diag(phi'(x_hat)) changes along the manifold (c < 0 puts x_hat
    near 0 in ELU's curved branch); F = I everywhere."""
    spec, offset = N.RomSpec(dim=dim, latent=dim), 10.0
    p = N.linear_params(spec, np.zeros((dim, dim)), np.eye(dim), offset)
    p["g_b0"][:dim] = c
    h = np.full(dim, c)
    for _ in range(spec.depth):
        h = np.where(h > 0, h, np.expm1(h))
    last = spec.depth
    p[f"g_b{last}"][:] += p[f"g_W{last}"][:, :dim] @ (np.full(dim, offset) - h)    # u = 0 at x_hat = 0
    return N.RomWeights(p, N.identity_norm(dim), spec, 0)


@pytest.mark.parametrize("backend", ("jax", "warp"))
@pytest.mark.parametrize("quadrature,projection", [("lagrangian", "nonlinear"), ("eulerian", "linear")])
def test_a_free_translation_on_a_curved_manifold_keeps_its_velocity(backend, quadrature, projection):
    """No force acts on a body translating freely at v0, and the full-order model keeps v0 exactly. The map
    is a translation whose dg/dx_hat changes with x_hat: with the velocity fitted in the tangent space at
    x_hat_{n+1} (tangent "next") the reduced velocity stays v0 to round-off; with the paper's explicit
    dg/dx_hat(x_hat_n) ("current") it drifts by (dg/dx_hat(x_hat_{n+1}) - dg/dx_hat(x_hat_n)) v_hat a step
    (percent here), a change no force makes."""
    from mpmlab.rom.stepper import reduced_stepper

    v0 = np.array([0.3, 0.1])
    fom = build_stepper(scene(gravity=(0.0, 0.0), velocity=v0.tolist()), backend, "pic", "fp64")
    w = curved_translation(2)
    drift = {}
    for tangent in ("next", "current"):
        rom = reduced_stepper(fom, w, samples=12, quadrature=quadrature, projection=projection, tangent=tangent)
        out = rom.rollout(steps=60, every=60)
        v = rom.to_numpy(out["state"])["v"]
        drift[tangent] = float(np.max(np.abs(v - v0)) / np.linalg.norm(v0))
    assert drift["next"] <= 1e-10 and drift["current"] >= 1e-2, drift


def test_an_unknown_tangent_is_refused():
    with pytest.raises(ConfigError, match="choose next or current"):
        ReducedStepper(build_stepper(scene(), "jax", "pic", "fp64"), translation(2), tangent="middle")


@pytest.mark.parametrize("dim", (2, 3))
def test_a_particle_velocity_boundary_on_a_subset_of_rows_is_the_full_one_restricted(dim):
    """``apply_particles(..., rows=M)`` (a reduced model's samples: O(|M|), not O(N)) gives the rows M of
    the all-particle call, inside and outside the region, rotating in 3D."""
    import jax.numpy as jnp

    from mpmlab.backends.jax.boundaries import particle_velocity

    sc = _boundary_scene(dim)
    b = next(b for b in sc.boundaries if b.stage == "particle_velocity")
    impl = particle_velocity(b, sc, jnp.float64)
    n = sc.particles().count
    rng = np.random.default_rng(dim)
    x = jnp.asarray(sc.particles().x + rng.normal(0, 1e-3, (n, dim)))
    vp, vpic = jnp.asarray(rng.normal(size=(n, dim))), jnp.asarray(rng.normal(size=(n, dim)))
    M = jnp.asarray(rng.choice(n, 40, replace=False))
    full = impl.apply_particles(x, vp, vpic, 0.01, 1e-3, impl.params)
    sub = impl.apply_particles(x[M], vp[M], vpic[M], 0.01, 1e-3, impl.params, rows=M)
    inside = np.asarray(b.select(np.asarray(sc.particles().x)))
    assert 0 < np.isin(np.asarray(M), inside).sum() < len(M)
    for a, c in zip(full, sub):
        assert np.max(np.abs(np.asarray(a)[np.asarray(M)] - np.asarray(c))) <= 1e-14


def test_floyds_samples_are_distinct_and_uniform():
    """The large-body sampler (O(|M|^2), not a permutation of every point): distinct indices in range, and
    each index drawn with frequency m / n (chi-squared over 4,000 draws of 5 of 20, within 4 sigma)."""
    import jax

    from mpmlab.rom.stepper import _floyd_sample

    draws = np.asarray(jax.vmap(lambda k: _floyd_sample(k, 20, 5))(jax.random.split(jax.random.PRNGKey(0), 4000)))
    assert all(len(set(r)) == 5 for r in draws) and draws.min() >= 0 and draws.max() < 20
    counts = np.bincount(draws.ravel(), minlength=20)
    expect = 4000 * 5 / 20
    chi2 = np.sum((counts - expect) ** 2 / expect)
    assert chi2 < 19 + 4 * np.sqrt(2 * 19)
    big = np.asarray(_floyd_sample(jax.random.PRNGKey(1), 800_000, 50))
    assert len(set(big)) == 50 and big.max() < 800_000


def test_the_samples_hold_five_points_of_each_kinematic_boundary():
    """Sec. 3.3: every step's samples include 5 points of each boundary that declares ``kinematic`` (a
    prescribed motion: particle_velocity, grid_velocity), and none of a load (particle_load)."""
    from mpmlab.boundaries import GridVelocity, ParticleLoad, ParticleVelocity, make_boundary

    assert ParticleVelocity.kinematic and GridVelocity.kinematic and not ParticleLoad.kinematic
    sc = _boundary_scene(2)
    grip = np.asarray(sc.boundaries[2].select(sc.particles().x))
    rom = ReducedStepper(build_stepper(sc, "jax", "pic", "fp64"), translation(2), samples=12)
    assert len(rom._forced) == 5 and set(rom._forced) <= set(grip.tolist())
    assert all(set(rom._forced) <= set(np.asarray(m).tolist()) for m in rom.draws(3))
    loaded = scene()
    region = {"kind": "box", "lo": [0.3, 0.3], "hi": [0.35, 0.4]}
    loaded.boundaries = [make_boundary({"kind": "particle_load", "region": region, "force": [1.0, 0.0]})]
    assert len(ReducedStepper(build_stepper(loaded, "jax", "pic", "fp64"), translation(2), samples=12)._forced) == 0
