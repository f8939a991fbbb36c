"""The divergence diagnosis (issue 19, item 5): each cause is classified from measured quantities of the
states just before the failure, on a small constructed case, and the message says what grew, where,
the number and what to try (``mpmlab.core.diagnosis``).

Cases (2D, dx = 0.05, a 0.3 m square of 4 particles per cell unless said):

* ``cfl`` -- a stiff square (E = 1e5, c_p = 11.6 m/s) with dt = 2.5e-2 s: dt c / dx = 5.8;
* ``compression`` -- a Hencky square (E = 1e4, no yield) squeezed by an initial velocity -600 (x - x_c)
  along x (APIC, C = grad v) at a step that moves it 0.36 cells: J falls to 6e-4 by step 20 at CFL 0.02,
  then the log-strain pressure throws it apart (the failure: a particle leaving the domain at step ~150);
  the kept frames' J range names the collapse;
* ``velocity`` -- one particle of a square at rest thrown at 400 m/s (20 cells per step);
* ``law`` -- fp32, E = 3e38 and nu = 0.45: both parameters fit in float32 (E = 1e39 would not, and is
  refused before the run: ``simulator.check_representable``), but the Lame lambda = E nu / ((1 + nu)(1 - 2 nu))
  = 9.3e38 the law derives in the kernel is inf, and lambda (J - 1) J = inf * 0 at rest; with the dt of CFL 0.3:
  NaN from a quiet state in one step;
* ``domain`` -- a square sliding at 5 m/s off a domain without walls (0.2 cells per step);
* ``cell_crossing`` -- the twisted annulus of ``mpmlab.scenes.large_shear`` at dx = 0.1 (APIC, fp64): J
  rings in grid-aligned modes long before the peak shear; halving dt fails the same way.
"""
import numpy as np
import pytest

import mpmlab
from mpmlab.core import diagnosis as D

BACKENDS = ("jax", "warp")


def square(dt, E=1e4, walls=True, cfl_limit=1e9, gravity=(0.0, -9.8), velocity=None, C=None):
    body = mpmlab.Body(shape={"kind": "box", "lo": [0.35, 0.35], "hi": [0.65, 0.65]}, material="fixed_corotated",
                       params={"E": E, "nu": 0.3}, density=1000.0, particles_per_cell=4, velocity=velocity, C=C)
    return mpmlab.Scene(dim=2, dx=0.05, domain=([0.0, 0.0], [1.0, 1.0]), bodies=[body], gravity=list(gravity),
                        boundaries=[mpmlab.boundaries.Walls()] if walls else [], dt=dt, cfl_limit=cfl_limit)


def with_velocity(st, backend, v):
    s = st.init()
    if backend == "jax":
        import jax.numpy as jnp
        return dict(s, v=jnp.asarray(v, dtype=s["v"].dtype))
    import warp as wp
    s.v.assign(wp.array(np.asarray(v, dtype=s.v.numpy().dtype), dtype=s.v.dtype))
    return s


def diverge(st, state=None, steps=400, every=10):
    with pytest.raises(mpmlab.SimulationDiverged) as err:
        st.rollout(state, steps=steps, every=every)
    e = err.value
    msg = str(e)
    assert e.cause in D.CAUSES and f"step {e.step}" in msg and "cause:" in msg and "\n" not in msg
    assert "CFL number" in msg and e.measures["cfl_prev"] > 0
    return e


@pytest.mark.parametrize("backend", BACKENDS)
def test_cfl(backend):
    st = mpmlab.build_stepper(square(dt=2.5e-2, E=1e5), backend, "pic", "fp64", check_every=5)
    e = diverge(st)
    assert e.cause == "cfl" and e.measures["cfl_wave"] == pytest.approx(5.80, rel=1e-2)
    assert "reduce dt" in str(e)


@pytest.mark.parametrize("backend", BACKENDS)
def test_compression(backend):
    k = 600.0   # APIC keeps each particle's velocity -k (X - 0.5) and C = grad v: J -> 0 within ~20 steps

    def squeeze(x):
        v = np.zeros_like(x)
        v[:, 0] = -k * (x[:, 0] - 0.5)
        return v

    body = mpmlab.Body(shape={"kind": "box", "lo": [0.35, 0.35], "hi": [0.65, 0.65]}, material="hencky_von_mises",
                       params={"E": 1e4, "nu": 0.3, "yield_stress": 1e30}, density=1000.0, particles_per_cell=4,
                       velocity=squeeze, C=[[-k, 0.0], [0.0, 0.0]])
    sc = mpmlab.Scene(dim=2, dx=0.05, domain=([0.0, 0.0], [1.0, 1.0]), bodies=[body], gravity=[0.0, 0.0],
                      boundaries=[], dt=2e-4, cfl_limit=1e9)
    st = mpmlab.build_stepper(sc, backend, "apic", "fp64", check_every=4)
    e = diverge(st, steps=200, every=20)
    m = e.measures
    assert e.cause == "compression", str(e)
    # J collapsed (to ~6e-4 at step 20) at CFL 0.02, long before the Hencky stress threw the body apart
    assert min(m["frames_J_min"]) < 0.01 and m["cfl_wave"] < 0.05 and m["cfl_start"] < 1.0
    assert "J collapse" in str(e) and "reduce dt" not in str(e)


def test_velocity_blow_up():
    st = mpmlab.build_stepper(square(dt=2.5e-3, E=1e3, walls=False, gravity=(0.0, 0.0)), "jax", "pic", "fp64",
                              check_every=5)
    v = np.zeros_like(st.particles.x)
    v[7] = [400.0, 0.0]
    e = diverge(st, with_velocity(st, "jax", v))
    assert e.cause == "velocity", str(e)
    assert e.measures["cfl_start"] < 1.0 and max(e.measures["move_cells_prev"], e.measures["move_cells_fail"]) > 1.0


def test_law_out_of_range_parameter():
    sc = square(dt=1.0, E=1e39, walls=False)
    sc.dt = 0.3 * sc.dx / sc.wave_speed()
    with pytest.raises(mpmlab.ConfigError, match="exceeds fp32's largest value"):
        mpmlab.build_stepper(sc, "jax", "pic", "fp32")       # a parameter fp32 cannot hold: refused up front
    sc = square(dt=1.0, E=3e38, walls=False)                  # representable, but its derived lambda is not
    sc.bodies[0].params["nu"] = 0.45
    sc.dt = 0.3 * sc.dx / sc.wave_speed()
    st = mpmlab.build_stepper(sc, "jax", "pic", "fp32", check_every=1)
    e = diverge(st, steps=3, every=1)
    assert e.cause == "law" and e.step == 1, str(e)
    assert "fixed_corotated" in str(e) and "parameters" in str(e)


def test_cell_crossing_twisted_annulus_is_not_cfl():
    from mpmlab.scenes import large_shear as LS

    runs = [LS.run("annulus", dx=0.1, transfer="apic", frames=22, dt_scale=s) for s in (1.0, 0.5)]
    for r in runs:
        assert r["diverged"] and r["cause"] == "cell_crossing", r["message"]
        m = r["measures"]
        assert m["cfl_wave"] < 0.3 and m["J_min"] < 0.9 and m["J_max"] > 1.1
        assert "shape function" in r["message"] and "reduce dt" not in r["message"]
    # halving dt does not remove it: the failure time moves by less than 25 %
    assert runs[1]["t_diverged"] < 1.25 * runs[0]["t_diverged"] < runs[0]["t_end"]


def test_cpdi_cell_crossing_advises_a_smaller_dt():
    """With CPDI the cell-crossing advice is the measured remedy (a smaller dt: benchmarks/large_shear.md,
    vortex3 on dx 0.0125), not another shape function: the message is built from the failure's numbers,
    so a CPDI stepper's diagnosis of a rippled J field is enough to check it (the twisted annulus at
    dx 0.1, which CPDI + PIC fails on cell-crossing noise at t = 0.53)."""
    from mpmlab.scenes import large_shear as LS

    r = LS.run("annulus", dx=0.1, transfer="pic", shape_function="cpdi", frames=22)
    assert r["diverged"] and r["cause"] == "cell_crossing", r["message"]
    assert "smaller dt" in r["message"] and "a smaller dt does not help" not in r["message"]
    assert "transfer.shape=cpdi" not in r["message"]


def test_domain_edge_at_a_modest_speed():
    """A square sliding at 5 m/s (0.2 cells per step, CFL 0.37) off a wall-less domain: 'domain', not 'cfl'."""
    sc = square(dt=2e-3, E=1e4, walls=False, gravity=(0.0, 0.0), velocity=[5.0, 0.0])
    e = diverge(mpmlab.build_stepper(sc, "jax", "pic", "fp64", check_every=5), steps=100, every=10)
    assert e.cause == "domain" and e.field.startswith("x (outside"), str(e)
    assert e.measures["move_cells_prev"] < 0.5 and "enlarge the domain or add walls" in str(e)


# ---- a law's own note: a learned law outside its training range (benchmarks/nclaw.md, "WATER (c)") -----------
def _nclaw_file(tmp_path, state_range=None, dim=2):
    from mpmlab.laws.nclaw import Law, save_weights
    from mpmlab.nclaw.probe import write_state_range

    law = Law()
    path = tmp_path / "w.safetensors"
    save_weights(str(path), law.initial_weights(dim), law, dim)
    if state_range is not None:
        write_state_range(path, state_range)
    return path


def test_nclaw_note_compares_with_the_recorded_training_range(tmp_path):
    """The note reports the failing particle's deviatoric log-stretch and J, the group's largest and 99th
    percentile, and says whether the states left the recorded training range (or that none is recorded,
    or that the training's own rollout diverged)."""
    from mpmlab.laws.nclaw import Law

    a = 2.0                                   # log-stretch 0.693 at particle 1
    F = np.stack([np.eye(2), np.diag([a, 1 / a]), np.diag([1.1, 1.0]), np.diag([-1.0, 1.0])])
    rng = {"deviatoric_stretch_max": 0.25, "deviatoric_stretch_p99": 0.2, "J_min": 0.5, "J_max": 1.5, "frames": 100}
    note = Law(weights_file=str(_nclaw_file(tmp_path, rng))).divergence_note({"F": F}, 1)
    assert "deviatoric log-stretch 0.693 (J 1)" in note and "1 inverted or non-finite" in note
    assert "reached a deviatoric log-stretch of 0.25" in note and "outside the states it was trained on" in note
    inside = Law(weights_file=str(_nclaw_file(tmp_path, dict(rng, deviatoric_stretch_max=1.0)))).divergence_note(
        {"F": F[:3]}, -1)
    assert "within that range" in inside and "failing particle" not in inside
    none = Law().divergence_note({"F": F}, 0)
    assert "untrained, seed 0" in none and "no training range to compare with" in none
    unrecorded = Law(weights_file=str(_nclaw_file(tmp_path))).divergence_note({"F": F}, 0)
    assert "records no training range" in unrecorded
    bad = Law(weights_file=str(_nclaw_file(tmp_path, {"diverged": True, "step": 40}))).divergence_note({"F": F}, 0)
    assert "diverged at step 40" in bad
    assert Law().divergence_note({}, 0) is None
    unsound = Law(weights_file=str(_nclaw_file(tmp_path, dict(rng, inverted=5)))).divergence_note({"F": F}, 0)
    assert "already inverted 5 particle-frames" in unsound


def test_diagnosis_line_carries_the_law_note(tmp_path):
    """A run of an (untrained) learned law that fails after one particle is thrown at 400 m/s: the
    one-line diagnosis names its cause and adds the law's note on its state (measures["law_notes"]): the
    states left the range its weight file records."""
    body = mpmlab.Body(shape={"kind": "box", "lo": [0.35, 0.35], "hi": [0.65, 0.65]}, material="nclaw",
                       params={}, density=1000.0, particles_per_cell=4,
                       options={"weights_file": str(_nclaw_file(tmp_path, {"deviatoric_stretch_max": 1e-3,
                                                                           "J_min": 0.99, "J_max": 1.01}))})
    sc = mpmlab.Scene(dim=2, dx=0.05, domain=([0.0, 0.0], [1.0, 1.0]), bodies=[body], gravity=[0.0, 0.0],
                      boundaries=[], dt=2.5e-3, cfl_limit=1e9)
    st = mpmlab.build_stepper(sc, "jax", "pic", "fp64", check_every=5)
    v = np.zeros_like(st.particles.x)
    v[7] = [400.0, 0.0]
    e = diverge(st, with_velocity(st, "jax", v))
    assert len(e.measures["law_notes"]) == 1 and e.measures["law_notes"][0] in str(e)
    assert "law 'nclaw' (learned" in str(e) and "outside the states it was trained on" in str(e)
