"""NCLaw's data side: lattice sampling of the training cube, the teacher-forcing datasets of
``experiment=nclaw_datasets`` (x, v, C, F at every step; F = J^(1/d) I for a J-only law, marked in the
file) and ``load_dataset``'s refusals, the evaluation scene set (``eval_cases``, NCLaw's ``sample_vel``)
and the position metric. Small: two 3-step CLI runs on JAX, the rest NumPy."""
from __future__ import annotations

import numpy as np
import pytest

from mpmlab.cli import EXIT_CONFIG, describe_error, main
from mpmlab.config import build_scene, compose
from mpmlab.core.errors import ConfigError
from mpmlab.core.scene import Body, Scene


# ---- lattice sampling ------------------------------------------------------------------------------
def test_nclaw_cube_is_the_linspace_lattice():
    scene = build_scene(compose(["scene=nclaw_jelly"]))
    P = scene.particles()
    axis = np.linspace(0.25, 0.75, 10)                      # NCLaw App. D.1: faces included
    assert P.count == 1000
    for d in range(3):
        assert np.unique(P.x[:, d]) == pytest.approx(axis, abs=1e-12)
    assert axis[1] - axis[0] == pytest.approx(0.5 / 9)        # 0.0556 m, not the cell size 0.05
    assert P.volume == pytest.approx(np.full(1000, 1.25e-4))  # box volume / count
    assert P.mass == pytest.approx(np.full(1000, 0.125))      # 0.125 kg each at 1000 kg/m^3
    # no point on a quadratic B-spline knot (a cell centre, (i + 1/2) dx): the reason for the lattice
    frac = (P.x / scene.dx) % 1.0
    assert np.min(np.abs(frac - 0.5)) > 1e-3


def test_lattice_2d_counts_and_volume():
    body = Body(shape={"kind": "box", "lo": [0.2, 0.3], "hi": [0.5, 0.7]}, material="fixed_corotated",
                sampling="lattice", lattice=[3, 5], name="slab")
    P = Scene(dim=2, dx=0.1, domain=([0.0, 0.0], [1.0, 1.0]), bodies=[body], name="s").particles()
    assert P.count == 15
    assert sorted(set(np.round(P.x[:, 0], 12))) == pytest.approx([0.2, 0.35, 0.5])
    assert sorted(set(np.round(P.x[:, 1], 12))) == pytest.approx([0.3, 0.4, 0.5, 0.6, 0.7])
    assert P.volume == pytest.approx(np.full(15, 0.3 * 0.4 / 15))


@pytest.mark.parametrize("overrides, needle", [
    (["scene.bodies.cube.lattice=null"], "sampling 'lattice' needs scene.bodies.cube.lattice"),
    (["scene.bodies.cube.lattice=[10,10]"], "scene.bodies.cube.lattice = [10, 10] must be 3 integers >= 2"),
    (["scene.bodies.cube.lattice=[1,10,10]"], "must be 3 integers >= 2"),
    (["scene.bodies.cube.sampling=regular"], "is only read by sampling 'lattice'"),
    (["scene.bodies.cube.shape.kind=sphere", "scene.bodies.cube.shape.center=[0.5,0.5,0.5]",
      "scene.bodies.cube.shape.radius=0.2", "scene.bodies.cube.shape.lo=null", "scene.bodies.cube.shape.hi=null"],
     "sampling 'lattice' fills a box, but the shape is 'sphere'"),
])
def test_lattice_config_errors_are_one_line(overrides, needle):
    with pytest.raises(ConfigError) as err:
        build_scene(compose(["scene=nclaw_jelly", *overrides]))
    msg = str(err.value)
    assert needle in msg and "\n" not in msg and msg.startswith("scene 'nclaw_jelly': ")


# ---- NCLaw's sample_vel --------------------------------------------------------------------------
NOTES = {  # notes/nclaw-rom.md 1.5 (omega x of seeds 1 and 7 there are 0.9355 / 0.9005 rounded twice)
    1: ((0.059, -2.233, -1.764), (0.936, 1.270, 2.483)),
    7: ((0.169, -0.537, 0.373), (0.901, 2.621, 0.016)),
    8: ((-0.747, -2.104, -0.783), (2.610, 1.173, 1.314)),
}


@pytest.mark.parametrize("seed", sorted(NOTES))
def test_sample_velocity_reproduces_nclaw(seed):
    from mpmlab.nclaw.scenes import sample_velocity

    v, w = sample_velocity(seed)
    v_ref, w_ref = NOTES[seed]
    assert v == pytest.approx(v_ref, abs=6e-4)
    assert w == pytest.approx(w_ref, abs=6e-4)
    assert v[1] <= 0 and np.linalg.norm(v) <= 3 and np.all((0 <= w) & (w <= 3))


def test_sample_velocity_draw_order_matters():
    """Drawing omega before the speed (a plausible wrong order) does not give the notes' numbers."""
    from mpmlab.nclaw.scenes import sample_velocity

    rng = np.random.Generator(np.random.PCG64(1))
    d = rng.uniform(-1, 1, 3)
    wrong_w = rng.uniform(0, 3, 3)
    assert not np.allclose(wrong_w, sample_velocity(1)[1], atol=1e-2)
    assert d[1] > 0 and sample_velocity(1)[0][1] < 0       # seed 1 exercises the y flip


# ---- the datasets ------------------------------------------------------------------------------
def _run(tmp_path, name, *overrides):
    run_dir = tmp_path / name
    code = main(["experiment=nclaw_datasets", "backend=jax", "steps=3", "output.recording=false",
                 "output.plots=false", *overrides, f"hydra.run.dir={run_dir}"])
    assert code == 0
    return run_dir / "trajectory.h5"


@pytest.fixture(scope="module")
def water_dataset(tmp_path_factory):
    return _run(tmp_path_factory.mktemp("nclaw_data"), "water", "scene=nclaw_water")


def test_dataset_has_every_frame_and_f_from_j(water_dataset):
    from mpmlab.io.h5 import read_attrs
    from mpmlab.nclaw.data import load_dataset

    ds = load_dataset(water_dataset)
    assert (ds.scene, ds.n, ds.dim, ds.steps, ds.frame_every) == ("nclaw_water", 1000, 3, 3, 1)
    assert ds.dt == pytest.approx(5e-4) and list(ds.step) == [0, 1, 2, 3]
    assert ds.x.shape == ds.v.shape == (4, 1000, 3)
    assert ds.C.shape == ds.F.shape == (4, 1000, 3, 3)
    assert ds.law_names == ["weakly_compressible"]
    # F = J^(1/3) I: isotropic, det F = J; frame 0 is the identity; it moves with the flow
    F = ds.F.astype(np.float64)
    J = np.linalg.det(F)
    assert F == pytest.approx(np.cbrt(J)[..., None, None] * np.eye(3), abs=1e-6)
    assert F[0] == pytest.approx(np.broadcast_to(np.eye(3), (1000, 3, 3)))
    assert np.abs(J[-1] - 1).max() > 1e-7
    assert np.abs(ds.C[-1]).max() > 0
    # explicit in the metadata: the file says F was made from J
    assert ds.derived["F"]["source"] == "J" and ds.derived["F"]["formula"] == "F = J^(1/3) I"
    assert ds.derived["F"]["particles"] == [[0, 1000]] and ds.derived["F"]["laws"] == ["weakly_compressible"]
    a = read_attrs(water_dataset)
    assert (a["scene"], a["particles"], a["frame_every"], a["steps"], a["backend"]) == ("nclaw_water", 1000, 1, 3, "jax")
    import h5py

    with h5py.File(water_dataset, "r") as f:
        assert f["frames/F"].attrs["derived_from"] == "J"
    ds.check_matches(build_scene(compose(["scene=nclaw_water"])))
    with pytest.raises(ConfigError, match="has scene nclaw_water, but the training scene has nclaw_jelly"):
        ds.check_matches(build_scene(compose(["scene=nclaw_jelly"])))


def test_derived_f_merges_with_a_law_that_carries_f(tmp_path):
    """jelly_pool_drop: the ball's law carries F, the pool's only J; the file's F covers both, in order."""
    from mpmlab.nclaw.data import load_dataset

    ds = load_dataset(_run(tmp_path, "pool", "scene=jelly_pool_drop", "scene.resolution=tiny", "scene.dt=5e-4",
                           "scene.bodies.ball.angular_velocity=[0,0,20]"))   # spun: the ball's F rotates
    (pool,) = [m for m in ds.laws if m["law"] == "weakly_compressible"]
    (ball,) = [m for m in ds.laws if m["law"] == "fixed_corotated"]
    F = ds.F[-1].astype(np.float64)
    Fw = F[pool["start"]:pool["stop"]]
    assert Fw == pytest.approx(np.cbrt(np.linalg.det(Fw))[:, None, None] * np.eye(3), abs=1e-6)
    Fb = F[ball["start"]:ball["stop"]]
    off = Fb - np.eye(3) * np.diagonal(Fb, axis1=1, axis2=2)[:, :, None]
    assert np.abs(off).max() > 1e-2                         # the ball's own F (a rotation), not synthesised
    assert ds.derived["F"]["particles"] == [[pool["start"], pool["stop"]]]


def test_apply_derived_2d():
    from mpmlab.io.derived import apply_derived, plan_derived
    from mpmlab.core import registry

    class G:
        def __init__(self, law, a, b):
            self.law, self.start, self.stop = registry.laws.get(law), a, b

    plans = plan_derived(["F", "C"], [G("fixed_corotated", 0, 2), G("weakly_compressible", 2, 4)])
    assert list(plans) == ["F"]
    st = {"F": np.stack([np.eye(2) * 2, np.eye(2) * 3]), "F_particles": np.array([0, 1]),
          "J": np.array([4.0, 9.0]), "J_particles": np.array([2, 3])}
    out = apply_derived(st, plans, 2)
    assert list(out["F_particles"]) == [0, 1, 2, 3]
    assert out["F"][2] == pytest.approx(2 * np.eye(2)) and out["F"][3] == pytest.approx(3 * np.eye(2))
    assert "F" in st and len(st["F"]) == 2                   # the input is not changed
    assert plan_derived(["all"], [G("weakly_compressible", 0, 4)]) == {}


def test_load_dataset_refusals(water_dataset, tmp_path):
    from mpmlab.io.h5 import read_trajectory, write_trajectory
    from mpmlab.nclaw.data import load_dataset

    def expect(path, needle):
        with pytest.raises(ConfigError) as err:
            load_dataset(path)
        msg = str(err.value)
        assert needle in msg and "\n" not in msg, msg
        assert describe_error(err.value)[0] == EXIT_CONFIG      # the CLI's exit code 2
        return msg

    expect(tmp_path / "nope.h5", "does not exist")
    traj = read_trajectory(water_dataset)
    for drop in ("C", "F"):
        t = read_trajectory(water_dataset)
        del t.fields[drop]
        path = write_trajectory(tmp_path / f"no_{drop}.h5", t)
        msg = expect(path, f"has no {drop}")
        assert "under teacher forcing the dataset must hold x, v, C, F at every step; rerun " \
               "experiment=nclaw_datasets" in msg
    t = read_trajectory(water_dataset)
    keep = [0, 2]                                             # every 2nd step: frame_every = 2
    t.x, t.v, t.time, t.step = t.x[keep], t.v[keep], t.time[keep], t.step[keep]
    t.fields = {k: a[keep] for k, a in t.fields.items()}
    path = write_trajectory(tmp_path / "every2.h5", t)
    msg = expect(path, "keeps only every 2-th step (frame_every = 2)")
    assert "rerun experiment=nclaw_datasets" in msg
    assert traj.x.shape[0] == 4


# ---- evaluation cases and the metric -------------------------------------------------------------
def test_eval_cases_names_and_steps():
    from mpmlab.nclaw.scenes import eval_cases

    common = ["reconstruction", "time", "velocity_seed1", "velocity_seed7", "velocity_seed8", "geometry"]
    got = {m: {c.name: c for c in eval_cases(m)} for m in ("jelly", "sand", "plasticine", "water")}
    assert list(got["jelly"]) == common + ["contact", "pool"]
    assert list(got["sand"]) == common
    assert list(got["plasticine"]) == common + ["melting"]
    assert got["plasticine"]["melting"].scene == "nclaw_melting" and got["plasticine"]["melting"].steps == 2000
    assert list(got["water"]) == common + ["incline"]
    for m, cases in got.items():
        assert cases["reconstruction"].steps == 1000 and cases["reconstruction"].scene == f"nclaw_{m}"
        assert cases["time"].steps == (5000 if m == "water" else 2000)
        assert cases["geometry"].steps == 2000 and cases["geometry"].scene == f"nclaw_geometry_{m}"
        assert cases["velocity_seed7"].steps == 1000
    assert got["water"]["incline"].steps == 1500 and got["jelly"]["contact"].steps == 1000
    assert got["jelly"]["pool"].scene == "jelly_pool_drop" and got["jelly"]["pool"].steps == 3000
    with pytest.raises(ConfigError, match="unknown material 'rubber'"):
        eval_cases("rubber")


def test_eval_case_overrides_compose_for_truth_and_learned():
    from mpmlab.nclaw.scenes import eval_cases, sample_velocity

    cases = {c.name: c for c in eval_cases("water")}
    vel = cases["velocity_seed8"]
    truth, learned = compose(vel.truth()), compose(vel.learned("w.safetensors"))
    assert truth.material.law == "weakly_compressible" and learned.material.law == "nclaw"
    assert learned.material.options.weights_file == "w.safetensors"
    v, w = sample_velocity(8)
    for cfg in (truth, learned):
        assert cfg.scene.name == "nclaw_water" and cfg.steps == 1000 and cfg.frame_every == 5
        assert list(cfg.scene.bodies.cube.velocity) == pytest.approx(v)
        assert list(cfg.scene.bodies.cube.angular_velocity) == pytest.approx(w)
    inc_t, inc_l = compose(cases["incline"].truth()), compose(cases["incline"].learned())
    assert inc_t.material.density == inc_l.material.density == 5000.0   # rho 5e3 for both runs
    assert list(inc_t.scene.gravity) == pytest.approx([0.0, -1.0, 0.866])
    geo = build_scene(compose(cases["geometry"].truth() + ["scene.resolution=tiny"]))
    assert geo.cells == (32, 32, 32) and geo.particles().count == 500
    assert compose(cases["geometry"].truth()).scene.bodies.body.count == 30000


def test_position_mse_by_hand():
    from mpmlab.nclaw.scenes import EvalCase, position_mse

    T, N = 11, 2
    x_true = np.zeros((T, N, 3))
    x_pred = np.zeros((T, N, 3))
    x_pred[:, 0, 0] = np.arange(T) * 0.1     # particle 0 drifts along x by 0.1 m per frame
    x_pred[3, 1, 2] = 100.0                  # an error on a frame the metric skips (3 % 5 != 0)
    # frames 0, 5, 10: squared errors 0, 0.25, 1.0 on one of 6 coordinates -> (0 + 0.25/6 + 1/6) / 3
    assert position_mse(x_pred, x_true) == pytest.approx((0.25 + 1.0) / 6 / 3)
    assert position_mse(x_pred, x_true, every=1) > 100
    case = EvalCase("c", "s", (), 10, "", "jelly", frame_every=5)
    assert case.mse(x_pred[::5], x_true[::5]) == pytest.approx(position_mse(x_pred, x_true))
    with pytest.raises(ConfigError, match="one shape"):
        position_mse(x_pred, x_true[:5])


def test_mesh_parity_inside_test_matches_trimesh():
    import trimesh

    from mpmlab.core.geometry import contains_parity

    m = trimesh.load(str(__import__("pathlib").Path(__import__("mpmlab").__file__).parent / "assets" / "spot.obj"),
                     force="mesh")
    rng = np.random.default_rng(3)
    x = m.bounds[0] + (m.bounds[1] - m.bounds[0]) * rng.random((600, 3))
    inside = contains_parity(m.vertices, m.faces, x)
    assert 0.1 < inside.mean() < 0.5
    assert np.array_equal(inside, m.contains(x))


# ---- the probes of a learned law (mpmlab.nclaw.probe) --------------------------------------------------------
def _rotation(rng, d):
    q, r = np.linalg.qr(rng.standard_normal((d, d)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


@pytest.mark.parametrize("dim", [2, 3])
def test_deviatoric_stretch_closed_form(dim):
    """Q s diag(a, a^(-1/(D-1)), ...) R: the isochoric log-stretch is log a and J = s^D, whatever the
    rotations; an inverted or non-finite F has an infinite stretch."""
    from mpmlab.nclaw.probe import deviatoric_stretch

    rng = np.random.default_rng(3)
    a = np.array([1.0, 1.3, 0.6, 2.5])
    s = np.array([1.0, 0.8, 1.1, 0.5])
    F = np.stack([_rotation(rng, dim) @ (si * np.diag([ai] + [ai ** (-1 / (dim - 1))] * (dim - 1)))
                  @ _rotation(rng, dim) for ai, si in zip(a, s)])
    dev, J = deviatoric_stretch(F)
    expect = np.maximum(np.abs(np.log(a)), np.abs(np.log(a)) / (dim - 1))
    np.testing.assert_allclose(dev, expect, atol=1e-12)
    np.testing.assert_allclose(J, s ** dim, rtol=1e-12)
    bad = np.stack([np.diag([-1.0] + [1.0] * (dim - 1)), np.full((dim, dim), np.nan)])
    dev, J = deviatoric_stretch(bad)
    assert np.all(np.isinf(dev)) and J[0] == pytest.approx(-1.0)


def _zeroed(net_outputs: str):
    """nclaw weights whose named networks' last layer is zero: that network's output T is 0."""
    from mpmlab.laws.nclaw import Law

    w = Law().initial_weights(3)
    for net in net_outputs:
        w[f"{net}_W3"] = np.zeros_like(w[f"{net}_W3"])
    return w


def test_constitutive_errors_identities(water_dataset):
    """NCLaw Tab. 5's two errors: with a zero plastic net F^e,new is F_trial, so its MSE equals the
    no-return-map column exactly; with a zero elastic net P = 0, so its MSE is the mean square of the
    true P (whose RMS the result also gives)."""
    from mpmlab.laws.nclaw import Law
    from mpmlab.nclaw.data import load_dataset
    from mpmlab.nclaw.probe import constitutive_errors

    ds = load_dataset(water_dataset)
    r = constitutive_errors(Law(), _zeroed("ep"), ds, n=200, seed=1)
    assert r["pairs"] == 200
    assert r["F_new"] == pytest.approx(r["F_new_without_return_map"], rel=1e-12)
    assert r["F_new_without_return_map"] > 0          # the flow sheared F_trial away from J^(1/3) I
    assert 0 < r["F_new_floor"] < r["F_new_without_return_map"]   # the kept rotation: a floor above 0
    assert r["P"] == pytest.approx(r["P_true_rms"] ** 2, rel=1e-12) and r["P"] > 0
    # a learned (non-zero) plastic net changes F^e,new
    r2 = constitutive_errors(Law(), _zeroed("e"), ds, n=200, seed=1)
    assert r2["F_new"] != pytest.approx(r2["F_new_without_return_map"], rel=1e-6)


def test_return_map_reach_without_a_return_map():
    """A zero plastic net leaves every isochoric stretch where it started (not returned); its report
    rows are the steps asked for."""
    from mpmlab.laws.nclaw import Law
    from mpmlab.nclaw.probe import return_map_reach

    rows = return_map_reach(Law(), _zeroed("p"), 3, [1.2, 2.0], steps=20, report=(1, 10))
    assert [(r["kind"], r["stretch"]) for r in rows] == [("uniaxial", 1.2), ("uniaxial", 2.0), ("shear", 1.2),
                                                         ("shear", 2.0)]
    for r in rows:
        assert sorted(r["after"]) == [1, 10, 20] and not r["returned"]
        for k, v in r["after"].items():
            assert v["deviatoric_stretch"] == pytest.approx(np.log(r["stretch"]), abs=1e-12)
            assert v["J"] == pytest.approx(1.0, abs=1e-12)


def test_return_map_reach_from_a_dilation():
    """kind 'dilation' starts at F = a I: a zero plastic net keeps J = a^3 and no deviatoric part (returned:
    J finite and positive); an unknown kind is refused by name."""
    from mpmlab.laws.nclaw import Law
    from mpmlab.nclaw.probe import return_map_reach

    rows = return_map_reach(Law(), _zeroed("p"), 3, [0.8, 1.1], kinds=("dilation",), steps=5, report=(5,))
    for r in rows:
        assert r["kind"] == "dilation" and r["returned"]
        assert after_5(r)["J"] == pytest.approx(r["stretch"] ** 3, rel=1e-12)
        assert after_5(r)["deviatoric_stretch"] == pytest.approx(0.0, abs=1e-12)
    with pytest.raises(ValueError, match="dilation"):
        return_map_reach(Law(), _zeroed("p"), 3, [1.1], kinds=("twist",), steps=1)


def test_acoustic_minimum_closed_form():
    """Fixed corotated elasticity at F = I: one step's acoustic tensor is Q = (lambda + mu) n n^T + mu I, so
    the smallest eigenvalue over directions is mu and the largest lambda + 2 mu, at any rotation R (the
    response is objective); stretched in 2D as in 3D; a J-only law (WATER's truth, no shear stiffness) gives
    0 and its bulk modulus. A law keeping another state is refused."""
    from mpmlab.core import registry
    from mpmlab.nclaw.probe import acoustic_minimum, sphere_directions

    E, nu = 1.0e5, 0.2
    lam, mu = E * nu / ((1 + nu) * (1 - 2 * nu)), E / (2 * (1 + nu))
    law = registry.laws.get("fixed_corotated")()
    row = [E, nu]
    th = 0.7
    Rz = np.array([[np.cos(th), -np.sin(th), 0.0], [np.sin(th), np.cos(th), 0.0], [0.0, 0.0, 1.0]])
    F = np.stack([np.eye(3), Rz])
    assert acoustic_minimum(law, {}, 3, F, row=row) == pytest.approx([mu, mu], rel=1e-9)
    assert acoustic_minimum(law, {}, 3, F, row=row, largest=True) == pytest.approx([lam + 2 * mu] * 2, rel=1e-9)
    assert acoustic_minimum(law, {}, 2, np.eye(2)[None], row=row, directions=64) == pytest.approx([mu], rel=1e-9)
    n = sphere_directions(200)
    assert np.allclose(np.linalg.norm(n, axis=1), 1.0)
    water = registry.laws.get("weakly_compressible")()             # tau = -p J I: bulk stiffness only
    K = 2.0e6
    assert abs(acoustic_minimum(water, {}, 3, np.eye(3)[None], row=[K])[0]) <= 1e-9 * K
    assert acoustic_minimum(water, {}, 3, np.eye(3)[None], row=[K], largest=True) == pytest.approx([K], rel=1e-9)
    with pytest.raises(ValueError, match="F- or J-state"):
        acoustic_minimum(registry.laws.get("drucker_prager_jaumann")(), {}, 3, np.eye(3)[None], row=[1.0] * 6)


def test_range_tracker_and_beyond_training():
    """RangeTracker over frames equals state_range of the frames it samples; beyond_training names each
    bound the rollout passed (J above / below, stretch, inverted) and nothing inside the range."""
    from mpmlab.nclaw.probe import RangeTracker, beyond_training, state_range

    rng = np.random.default_rng(3)
    frames = np.eye(3) + 0.1 * rng.standard_normal((6, 40, 3, 3))
    tr = RangeTracker(every=2)
    for f in frames:
        tr.update(f)
    ref = state_range(frames[::2])
    assert tr.range["frames"] == 3
    for k in ref:
        assert tr.range[k] == pytest.approx(ref[k], rel=1e-12), k
    assert beyond_training(ref, ref) == [] and beyond_training(ref, None) == []
    wide = dict(ref, J_max=ref["J_max"] * 3, J_min=ref["J_min"] / 3, deviatoric_stretch_max=2.0, inverted=4)
    got = beyond_training(wide, ref)
    assert [c.split(" (")[0].split(" up")[0].split(" down")[0] for c in got] == [
        "J", "J", "deviatoric log-stretch", "4 inverted or non-finite particle-frames"], got


def after_5(row):
    return row["after"][5]


def test_best_in_rotation_is_the_closest_rotated_symmetric():
    """best_in_rotation: exact when the target is R S (S symmetric, R the polar rotation of F_trial);
    otherwise closer to the target than F_trial itself and than random R S'."""
    from mpmlab.laws._linalg_np import polar_rotation
    from mpmlab.nclaw.probe import best_in_rotation

    rng = np.random.default_rng(5)
    Ft = np.eye(3) + 0.2 * rng.standard_normal((20, 3, 3))
    R = np.stack([polar_rotation(f) for f in Ft])
    S = rng.standard_normal((20, 3, 3))
    S = S + S.transpose(0, 2, 1)
    np.testing.assert_allclose(best_in_rotation(Ft, R @ S), R @ S, atol=1e-12)
    G = np.broadcast_to(np.eye(3), Ft.shape)                # WATER's target at J = 1: the rotation dropped
    best = best_in_rotation(Ft, G)
    err = np.sum((best - G) ** 2, axis=(1, 2))
    assert np.all(err <= np.sum((Ft - G) ** 2, axis=(1, 2)) + 1e-15)
    for _ in range(5):
        D = 0.05 * rng.standard_normal((20, 3, 3))
        other = R @ (R.transpose(0, 2, 1) @ best + D + D.transpose(0, 2, 1))
        assert np.all(err <= np.sum((other - G) ** 2, axis=(1, 2)) + 1e-15)


def test_write_state_range_keeps_the_file(tmp_path):
    """write_state_range adds the record to a weight file's metadata and keeps its arrays and its other
    metadata; the law reads it back (trained_range)."""
    from safetensors import safe_open
    from safetensors.numpy import load_file

    from mpmlab.laws.nclaw import Law, save_weights
    from mpmlab.nclaw.probe import write_state_range

    law = Law()
    w = law.initial_weights(3)
    path = tmp_path / "w.safetensors"
    save_weights(str(path), w, law, 3)
    rng = {"deviatoric_stretch_max": 0.25, "deviatoric_stretch_p99": 0.2, "J_min": 0.5, "J_max": 1.5, "frames": 100}
    write_state_range(path, rng)
    back = load_file(str(path))
    assert set(back) == set(w) and all(np.array_equal(back[k], w[k]) for k in w)
    with safe_open(str(path), framework="numpy") as f:
        meta = f.metadata()
    assert {k: meta[k] for k in law.weights_metadata(3)} == law.weights_metadata(3)
    assert Law(weights_file=str(path)).trained_range() == rng
    assert not list(tmp_path.glob("*.tmp*"))


def test_state_range_counts_inverted_particles_apart():
    """state_range: the stretch range over sound particles, J's range, inverted particle-frames counted."""
    from mpmlab.nclaw.probe import state_range

    frame = np.stack([np.eye(3), np.diag([2.0, 0.5, 1.0]), np.diag([-1.0, 1.0, 1.0])])
    r = state_range(np.stack([frame, frame]))
    assert r["deviatoric_stretch_max"] == pytest.approx(np.log(2.0))
    assert (r["J_min"], r["J_max"], r["inverted"], r["frames"]) == (-1.0, 1.0, 2, 2)
