"""Stability guards: refused time steps, divergence detection naming step/particle/field, frames kept."""
import numpy as np
import pytest

import mpmlab

BACKENDS = ("jax", "warp")


def cube(dt, E=1e4, velocity=None, cfl_limit=0.5, walls=True, squeeze=0.0):
    body = mpmlab.Body(shape={"kind": "box", "lo": [0.35, 0.35], "hi": [0.65, 0.65]}, material="fixed_corotated",
                       params={"E": E, "nu": 0.3}, density=1000.0, particles_per_cell=4, velocity=velocity)
    scene = mpmlab.Scene(dim=2, dx=0.05, domain=([0.0, 0.0], [1.0, 1.0]), bodies=[body], gravity=[0.0, -9.8],
                         boundaries=[mpmlab.boundaries.Walls()] if walls else [], dt=dt, cfl_limit=cfl_limit)
    return scene


def test_dt_above_cfl_is_refused():
    with pytest.raises(mpmlab.TimeStepError, match="CFL number"):
        mpmlab.build_stepper(cube(dt=0.1), "jax", "pic", "fp64")


def test_dt_auto_uses_safety_factor():
    scene = cube(dt="auto")
    dt = scene.resolve_dt()
    # dt (c_p + |v| + |g| n dt) = C dx: the speed gravity adds before the next update (n = dt_every) counts
    assert np.isclose(scene.cfl_number(dt, speed=9.8 * scene.dt_every * dt), scene.cfl)
    assert scene.cfl_number(dt) < scene.cfl


@pytest.mark.parametrize("backend", BACKENDS)
def test_unstable_time_step_diverges_with_named_step_and_particle(backend):
    scene = cube(dt=2.5e-2, E=1e5, cfl_limit=1e9)   # C ~ 6: far beyond the explicit limit
    st = mpmlab.build_stepper(scene, backend, "pic", "fp64", check_every=5)
    with pytest.raises(mpmlab.SimulationDiverged) as err:
        st.rollout(steps=400, every=10)
    e = err.value
    assert e.step >= 1 and 0 <= e.particle < scene.particles().count
    assert f"step {e.step}" in str(e) and f"particle {e.particle}" in str(e) and "CFL number" in str(e)
    assert e.trajectory is not None and e.trajectory.frame_count >= 1
    assert np.all(np.isfinite(e.trajectory.x))  # frames kept before the failure are sound
    # the guard named the first bad step: replaying to the step before it is clean
    if e.step > 1:
        st2 = mpmlab.build_stepper(scene, backend, "pic", "fp64")
        s = st2._advance(st2.init(), e.step - 1)
        assert st2.locate_failure(st2.to_numpy(s)) is None


@pytest.mark.parametrize("backend", BACKENDS)
def test_inverted_element_is_reported(backend):
    """A body squeezed through itself in one step inverts (J <= 0); the guard names field J."""
    scene = cube(dt=2e-3, E=1e-3, walls=False, cfl_limit=1e9)
    x = scene.particles().x
    c = x.mean(axis=0)
    st = mpmlab.build_stepper(scene, backend, "pic", "fp64", check_every=1)
    s = st.init()
    v = np.zeros_like(x)
    v[:, 0] = -600.0 * (x[:, 0] - c[0])   # det(I + dt grad v) = 1 - 600 dt < 0: the body turns inside out in x
    if backend == "jax":
        import jax.numpy as jnp
        s = dict(s, v=jnp.asarray(v))
    else:
        import warp as wp
        s.v.assign(wp.array(v, dtype=s.v.dtype))
    with pytest.raises(mpmlab.SimulationDiverged) as err:
        st.rollout(s, steps=60, every=5)
    assert err.value.field == "J"
    assert err.value.value <= 0
