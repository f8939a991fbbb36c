"""FLIP's PIC blend as a time constant (``transfer.pic_time``): flip_ratio = exp(-dt / pic_time) per step,
so the damping of the particles' deviation from the grid velocity per second does not change with dt
(benchmarks/granular.md, "The scenes' PIC blend is a damper whose strength is set by dt")."""
import math

import numpy as np
import pytest

import mpmlab
from mpmlab.core.errors import ConfigError, InvalidParameterError
from mpmlab.transfers import make_transfer


def noisy_square(dt, dt_every=None):
    """A soft square (E = 1 Pa: nearly no stress) whose particles start with independent random
    velocities: the FLIP part keeps each one, the PIC part pulls it to the grid's smooth field."""
    rng = np.random.default_rng(0)
    body = mpmlab.Body(shape={"kind": "box", "lo": [0.3, 0.3], "hi": [0.7, 0.7]}, material="fixed_corotated",
                       params={"E": 1.0, "nu": 0.3}, density=1000.0, particles_per_cell=4,
                       velocity=lambda x: rng.normal(0.0, 0.1, size=x.shape))
    kw = {} if dt_every is None else {"dt_every": dt_every}
    return mpmlab.Scene(dim=2, dx=0.05, domain=([0.0, 0.0], [1.0, 1.0]), bodies=[body], gravity=[0.0, 0.0],
                        boundaries=[], dt=dt, **kw)


def kinetic(backend, dt, transfer, T=0.05):
    sc = noisy_square(dt)
    st = mpmlab.build_stepper(sc, backend, transfer, "fp64")
    v = st.to_numpy(st._advance(st.init(), int(round(T / dt))))["v"]
    return 0.5 * float(np.sum(np.asarray(sc.particles().mass) * np.sum(v * v, axis=1)))


@pytest.mark.parametrize("backend", ["jax", "warp"])
def test_damping_per_second_does_not_depend_on_dt(backend):
    """After 0.05 s the kinetic energy left is the same at dt and dt/2 with pic_time (to 1e-3); with a
    fixed flip_ratio 0.99 the halved step damps twice as fast per second (0.44 of it left)."""
    pic = make_transfer("flip", pic_time=0.1)
    a, b = kinetic(backend, 1e-3, pic), kinetic(backend, 5e-4, pic)
    assert b / a == pytest.approx(1.0, abs=1e-3)
    fixed = make_transfer("flip", flip_ratio=0.99)
    assert kinetic(backend, 5e-4, fixed) / kinetic(backend, 1e-3, fixed) < 0.5


@pytest.mark.parametrize("backend", ["jax", "warp"])
def test_pic_time_is_flip_ratio_at_the_scene_step(backend):
    """pic_time resolves to flip_ratio = exp(-dt / pic_time) when the stepper is built: the same
    trajectory, bit for bit, as that ratio given directly."""
    dt, tau = 1e-3, 0.05
    sc = noisy_square(dt)
    assert make_transfer("flip", pic_time=tau).for_scene(sc).flip_ratio == math.exp(-dt / tau)
    x = {}
    for name, tr in (("pic_time", make_transfer("flip", pic_time=tau)),
                     ("ratio", make_transfer("flip", flip_ratio=math.exp(-dt / tau)))):
        st = mpmlab.build_stepper(noisy_square(dt), backend, tr, "fp64")
        x[name] = st.to_numpy(st._advance(st.init(), 20))["x"]
    np.testing.assert_array_equal(x["pic_time"], x["ratio"])


def test_pic_time_refusals():
    """A non-positive pic_time, and pic_time with a dt that changes during the run, are refused in one line."""
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(InvalidParameterError, match="pic_time = .* must be a positive number of seconds"):
            make_transfer("flip", pic_time=bad)
    sc = noisy_square("auto", dt_every=10)
    with pytest.raises(ConfigError, match="pic_time needs a time step fixed .* set scene.dt_every=0") as e:
        mpmlab.build_stepper(sc, "jax", make_transfer("flip", pic_time=0.05), "fp64")
    assert "\n" not in str(e.value)
    once = noisy_square("auto", dt_every=0)       # dt: auto computed once: fine
    tr = make_transfer("flip", pic_time=0.05).for_scene(once)
    assert tr.flip_ratio == math.exp(-once.resolve_dt() / 0.05)


def test_pic_time_from_the_config():
    from mpmlab.build import make_transfer_from_config
    from mpmlab.config import compose

    tr = make_transfer_from_config(compose(["transfer=flip", "transfer.pic_time=0.005"]))
    assert tr.pic_time == 0.005 and tr.flip_ratio == 0.99       # resolved at build, against the scene's dt
    assert make_transfer_from_config(compose(["transfer=flip"])).pic_time is None
