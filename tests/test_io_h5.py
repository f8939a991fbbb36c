"""HDF5 trajectories (schema mpmlab.trajectory v1), LagrangeBench export and per-frame metrics."""
from __future__ import annotations

import json
import os

import h5py
import numpy as np
import pytest

import mpmlab
from mpmlab.core.errors import ConfigError, SimulationDiverged
from mpmlab.core.state import Trajectory
from mpmlab.io import h5 as mh5
from mpmlab.io.metrics import compute_metrics, frame_metrics

EVERY = 5


def _scene(**kw):
    body = dict(shape={"kind": "box", "lo": [0.4, 0.4], "hi": [0.6, 0.6]}, material="fixed_corotated",
                params={"E": 2.0e4, "nu": 0.3}, velocity=[0.5, 0.0], angular_velocity=3.0, particles_per_cell=4)
    body.update(kw.pop("body", {}))
    args = dict(dim=2, dx=0.05, domain=([0, 0], [1, 1]), bodies=[mpmlab.Body(**body)], gravity=[0, 0],
                boundaries=[mpmlab.boundaries.Walls()], dt=1e-4)
    args.update(kw)
    return mpmlab.Scene(**args)


@pytest.fixture(scope="module")
def stepper():
    return mpmlab.build_stepper(_scene(), backend="jax", transfer="apic", precision="fp64")


@pytest.fixture(scope="module")
def traj(stepper):
    return stepper.rollout(steps=20, every=EVERY, fields=("F", "C"))


def _handmade(T=3, N=7, D=3, dtype=np.float32) -> Trajectory:
    """A 3D two-material trajectory with NaN-padded params and fields over particle subsets."""
    rng = np.random.default_rng(1)
    F = np.eye(D) + 0.05 * rng.standard_normal((T, 4, D, D))
    return Trajectory(
        x=rng.random((T, N, D)).astype(dtype), v=rng.standard_normal((T, N, D)).astype(dtype),
        time=np.arange(T) * 2e-3, step=np.arange(T, dtype=np.int64) * 20,
        mass=rng.random(N), volume=np.full(N, 1e-3), material_id=np.array([0, 0, 0, 0, 1, 1, 1]),
        body_id=np.array([0, 0, 0, 0, 1, 1, 2]),
        materials=[{"law": "fixed_corotated", "param_names": ["E", "nu"], "start": 0, "stop": 4,
                    "provenance": "mpmlab"},
                   {"law": "drucker_prager_jaumann", "param_names": ["E", "nu", "phi"], "start": 4, "stop": 7,
                    "provenance": "mpmlab"}],
        params=np.array([[1e5, 0.3, np.nan]] * 4 + [[2e5, 0.25, 30.0]] * 3),
        meta={"dim": D, "dt": 1e-4, "dx": 0.1, "grid_origin": [0.0] * D, "grid_shape": [11] * D,
              "backend": "warp", "transfer": "mls", "precision": "fp32", "scene": "handmade",
              "gravity": [0.0, 0.0, -9.8], "nested": {"a": [1, 2], "b": None, "c": True}},
        fields={"F": F.astype(dtype), "sigma": rng.standard_normal((T, 3, D, D)).astype(dtype),
                "eps_p": rng.random((T, 3)).astype(dtype), "J": rng.random((T, 3)).astype(dtype)},
        field_particles={"F": np.arange(4), "sigma": np.arange(4, 7), "eps_p": np.arange(4, 7), "J": np.arange(4, 7)},
    )


def assert_same(a: Trajectory, b: Trajectory):
    for name in ("x", "v", "time", "step", "mass", "volume", "params"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype, name
        np.testing.assert_array_equal(x, y, err_msg=name)  # NaN == NaN here
    for name in ("material_id", "body_id"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert a.materials == b.materials
    assert a.meta == b.meta
    assert set(a.fields) == set(b.fields)
    for k in a.fields:
        assert a.fields[k].dtype == b.fields[k].dtype, k
        np.testing.assert_array_equal(a.fields[k], b.fields[k], err_msg=k)
        np.testing.assert_array_equal(a.field_particles[k], b.field_particles[k])


# ---- round trips ---------------------------------------------------------------------------------
def test_roundtrip_simulated_exact(traj, tmp_path):
    p = mh5.write_trajectory(tmp_path / "t.h5", traj, config_yaml="law: fixed_corotated\n", extra_attrs={"seed": 3})
    back = mh5.read_trajectory(p)
    assert_same(traj, back)
    assert back.material_id.dtype == np.int64
    attrs = mh5.read_attrs(p)
    assert attrs["schema"] == "mpmlab.trajectory" and attrs["schema_version"] == 1
    assert attrs["complete"] is True and attrs["frame_count"] == traj.frame_count
    assert attrs["dim"] == 2 and attrs["dt"] == traj.meta["dt"] and attrs["substeps_per_frame"] == EVERY
    assert (attrs["backend"], attrs["transfer"], attrs["precision"]) == ("jax", "apic", "fp64")
    assert attrs["mpmlab_version"] == mpmlab.__version__ and attrs["config_yaml"] == "law: fixed_corotated\n"
    assert attrs["seed"] == 3
    with h5py.File(p, "r") as f:
        assert f["frames/x"].chunks == (1, traj.particle_count, 2)
        assert f["frames/x"].compression == "lzf" and f["frames/x"].shuffle
        assert f["frames/F"].shape == traj.fields["F"].shape
        assert f["particles/material_id"].dtype == np.int32 and f["particles/body_id"].dtype == np.int32
        assert list(f["grid"].attrs["shape"]) == traj.meta["grid_shape"] and f["grid"].attrs["dx"] == traj.meta["dx"]
        laws = json.loads(f["materials"].attrs["laws_json"])
        assert laws[0]["law"] == "fixed_corotated" and laws[0]["provenance"] == "mpmlab"
        assert json.loads(f["particles/params"].attrs["names_json"]) == [["E", "nu"]]


@pytest.mark.parametrize("compression", ["lzf", "gzip", None])
def test_roundtrip_handmade_all_fields(tmp_path, compression):
    t = _handmade()
    p = mh5.write_trajectory(tmp_path / "h.h5", t, compression=compression)
    back = mh5.read_trajectory(p)
    assert_same(t, back)
    assert back.x.dtype == np.float32 and np.isnan(back.params[0, 2])
    with h5py.File(p, "r") as f:
        assert f["frames/sigma"].compression == compression


def test_empty_and_bad_compression(tmp_path):
    t = _handmade().truncated(0)
    back = mh5.read_trajectory(mh5.write_trajectory(tmp_path / "e.h5", t))
    assert back.x.shape == (0, 7, 3) and back.fields["F"].shape == (0, 4, 3, 3)
    with pytest.raises(ConfigError, match="compression 'zstd' unknown"):
        mh5.write_trajectory(tmp_path / "z.h5", t, compression="zstd")


# ---- atomic writes -----------------------------------------------------------------------------
def test_atomic_write_refuses_overwrite_and_leaves_no_temp(tmp_path):
    t = _handmade()
    p = tmp_path / "sub" / "t.h5"
    mh5.write_trajectory(p, t)
    assert os.listdir(p.parent) == ["t.h5"]
    before = p.read_bytes()
    with pytest.raises(ConfigError) as e:
        mh5.write_trajectory(p, _handmade(T=2))
    msg = str(e.value)
    assert "already exists" in msg and "overwrite=True" in msg and "\n" not in msg
    assert p.read_bytes() == before and os.listdir(p.parent) == ["t.h5"]
    mh5.write_trajectory(p, _handmade(T=2), overwrite=True)
    assert mh5.read_trajectory(p).frame_count == 2 and os.listdir(p.parent) == ["t.h5"]


def test_failed_write_leaves_nothing(tmp_path):
    with pytest.raises(ConfigError, match="reserved"):
        mh5.write_trajectory(tmp_path / "t.h5", _handmade(), extra_attrs={"complete": True})
    assert os.listdir(tmp_path) == []
    bad = _handmade()
    bad.fields["F"] = bad.fields["F"][:2]
    with pytest.raises(ConfigError, match="frames"):
        mh5.write_trajectory(tmp_path / "t.h5", bad)
    assert os.listdir(tmp_path) == []


# ---- reading errors ------------------------------------------------------------------------------
def _one_sentence(msg: str) -> bool:
    return "\n" not in msg and msg.endswith(".") and ". " not in msg


def test_read_errors_are_one_sentence(tmp_path):
    cases = {}
    with pytest.raises(ConfigError) as e:
        mh5.read_trajectory(tmp_path / "missing.h5")
    cases["missing"] = str(e.value)
    assert "does not exist" in cases["missing"]

    (tmp_path / "notes.txt").write_text("not hdf5")
    with pytest.raises(ConfigError) as e:
        mh5.read_trajectory(tmp_path / "notes.txt")
    cases["text"] = str(e.value)
    assert "not an HDF5 file" in cases["text"]

    with h5py.File(tmp_path / "foreign.h5", "w") as f:
        f.create_dataset("position", data=np.zeros((2, 3)))
    with pytest.raises(ConfigError) as e:
        mh5.read_trajectory(tmp_path / "foreign.h5")
    cases["foreign"] = str(e.value)
    assert "no 'schema' attribute" in cases["foreign"] and "position" in cases["foreign"]

    with h5py.File(tmp_path / "other.h5", "w") as f:
        f.attrs["schema"] = "other.format"
    with pytest.raises(ConfigError) as e:
        mh5.read_trajectory(tmp_path / "other.h5")
    cases["other"] = str(e.value)
    assert "schema 'other.format'" in cases["other"]

    p = mh5.write_trajectory(tmp_path / "v2.h5", _handmade())
    with h5py.File(p, "r+") as f:
        f.attrs["schema_version"] = 2
    with pytest.raises(ConfigError) as e:
        mh5.read_trajectory(p)
    cases["version"] = str(e.value)
    assert "version 2" in cases["version"] and "version 1" in cases["version"]
    for name, msg in cases.items():
        assert _one_sentence(msg), (name, msg)


# ---- streaming ---------------------------------------------------------------------------------
def test_streaming_writer_equals_rollout(stepper, traj, tmp_path):
    p = tmp_path / "s.h5"
    with mh5.TrajectoryWriter(p, stepper=stepper, fields=("F", "C"), every=EVERY) as w:
        assert not p.exists()  # frames go to a temporary file until the end
        out = stepper.rollout(steps=20, every=EVERY, fields=("F", "C"), on_frame=w)
    assert_same(out, traj)
    assert_same(mh5.read_trajectory(p), traj)
    assert mh5.read_attrs(p)["complete"] is True and os.listdir(tmp_path) == ["s.h5"]


def test_streaming_without_every_uses_state_time(stepper, traj, tmp_path):
    p = tmp_path / "s.h5"
    with mh5.TrajectoryWriter(p, traj) as w:
        stepper.rollout(steps=10, every=EVERY, on_frame=w)
    back = mh5.read_trajectory(p)
    np.testing.assert_array_equal(back.step, [0, 5, 10])
    np.testing.assert_array_equal(back.x, traj.x[:3])
    assert back.fields == {}


def test_streaming_keeps_frames_before_divergence(stepper, tmp_path):
    """A body thrown at 100 m/s into a wall is crushed (J <= 0); the frames produced before are kept."""
    state = stepper.init()
    state["v"] = state["v"] + np.array([100.0, 0.0])
    p = tmp_path / "d.h5"
    with pytest.raises(SimulationDiverged) as e:
        with mh5.TrajectoryWriter(p, stepper=stepper, fields=("F",), every=10) as w:
            stepper.rollout(state=state, steps=1000, every=10, fields=("F",), on_frame=w)
    kept = e.value.trajectory
    assert 1 < kept.frame_count < 101
    attrs = mh5.read_attrs(p)
    assert attrs["complete"] is False and attrs["diverged"] is True
    assert attrs["diverged_step"] == e.value.step and "diverged" in attrs["diverged_message"]
    with pytest.warns(UserWarning, match="incomplete"):
        back = mh5.read_trajectory(p)
    assert_same(back, kept)
    with pytest.raises(ConfigError, match="incomplete"):
        mh5.read_trajectory(p, require_complete=True)
    assert os.listdir(tmp_path) == ["d.h5"]


def test_streaming_exception_without_frames_writes_nothing(traj, tmp_path):
    with pytest.raises(RuntimeError):
        with mh5.TrajectoryWriter(tmp_path / "n.h5", traj):
            raise RuntimeError("boom")
    assert os.listdir(tmp_path) == []
    with pytest.raises(RuntimeError):
        with mh5.TrajectoryWriter(tmp_path / "n.h5", traj) as w:
            w.add_frame(traj.x[0], traj.v[0], 0.0, 0)
            raise RuntimeError("boom")
    assert mh5.read_attrs(tmp_path / "n.h5")["error"] == "RuntimeError: boom"
    with pytest.raises(ConfigError, match="already exists"):
        mh5.TrajectoryWriter(tmp_path / "n.h5", traj)


def test_streaming_missing_field_is_named(traj, tmp_path):
    with pytest.raises(ConfigError, match=r"no field \['sigma'\]"):
        with mh5.TrajectoryWriter(tmp_path / "m.h5", traj, fields=("sigma",)) as w:
            w(0, {"x": traj.x[0], "v": traj.v[0], "t": 0.0, "F": traj.fields["F"][0]})


# ---- LagrangeBench -----------------------------------------------------------------------------
def test_export_lagrangebench_layout(traj, tmp_path):
    src = mh5.write_trajectory(tmp_path / "t.h5", traj)
    out = tmp_path / "lb"
    p = mh5.export_lagrangebench(src, out)
    assert p == out / "train.h5" and sorted(os.listdir(out)) == ["metadata.json", "train.h5"]
    with h5py.File(p, "r") as f:
        assert list(f) == ["00000"]
        pos, ptype = f["00000/position"][()], f["00000/particle_type"][()]
    assert pos.dtype == np.float32 and pos.shape == traj.x.shape
    np.testing.assert_array_equal(pos, traj.x.astype(np.float32))
    np.testing.assert_array_equal(ptype, traj.material_id)
    md = json.loads((out / "metadata.json").read_text())
    for key in ("dim", "dt", "dx", "bounds", "sequence_length", "num_particles_max", "solver", "case",
                "vel_mean", "vel_std", "acc_mean", "acc_std", "periodic_boundary_conditions",
                "default_connectivity_radius", "write_every"):
        assert key in md, key
    assert md["dim"] == 2 and md["dt"] == traj.meta["dt"] and md["dx"] == traj.meta["dx"]
    assert md["sequence_length"] == traj.frame_count - 1 and md["num_particles_max"] == traj.particle_count
    assert md["bounds"] == [[0.0, 1.0], [0.0, 1.0]] and md["write_every"] == EVERY
    vel = np.diff(traj.x.astype(np.float32).astype(np.float64), axis=0).reshape(-1, 2)
    np.testing.assert_allclose(md["vel_mean"], vel.mean(0), rtol=1e-10, atol=1e-15)
    assert len(md["acc_std"]) == 2 and all(s > 0 for s in md["acc_std"])
    # a second split updates the metadata; the existing split is not clobbered
    mh5.export_lagrangebench([traj, traj], out, split="valid")
    md2 = json.loads((out / "metadata.json").read_text())
    assert md2["num_trajs_valid"] == 2 and md2["vel_mean"] == md["vel_mean"]
    with h5py.File(out / "valid.h5", "r") as f:
        assert list(f) == ["00000", "00001"]
    with pytest.raises(ConfigError, match="already exists"):
        mh5.export_lagrangebench(traj, out)


# ---- metrics -----------------------------------------------------------------------------------
def _p2g_angular_momentum(x, v, m, C, dx):
    """Grid angular momentum sum_i x_i x m_i v_i after an APIC P2G with quadratic B-splines."""
    D = x.shape[1]
    L = np.zeros(() if D == 2 else 3)
    for p in range(len(x)):
        base = np.floor(x[p] / dx - 0.5).astype(int)
        fx = x[p] / dx - base
        w = np.stack([0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2])
        for off in np.ndindex(*([3] * D)):
            weight = np.prod([w[off[d], d] for d in range(D)])
            xi = (base + np.array(off)) * dx
            mv = weight * m[p] * (v[p] + C[p] @ (xi - x[p]))
            L = L + (xi[0] * mv[1] - xi[1] * mv[0] if D == 2 else np.cross(xi, mv))
    return L


@pytest.mark.parametrize("D", [2, 3])
def test_angular_momentum_spin_term_equals_grid(D):
    rng = np.random.default_rng(D)
    n, dx = 5, 0.1
    x = 0.3 + 0.4 * rng.random((n, D))
    v, C, m = rng.standard_normal((n, D)), rng.standard_normal((n, D, D)), rng.random(n) + 0.5
    got = frame_metrics(x[None], v[None], m, dx=dx, C=C[None])["angular_momentum"][0]
    np.testing.assert_allclose(got, _p2g_angular_momentum(x, v, m, C, dx), rtol=1e-12, atol=1e-12)
    no_spin = frame_metrics(x[None], v[None], m)["angular_momentum"][0]
    assert not np.allclose(no_spin, got)


def test_metrics_of_free_rotating_body(traj):
    m = compute_metrics(traj)
    assert set(m) == {"mass", "linear_momentum", "kinetic_energy", "angular_momentum",
                      "gravity_potential_energy", "elastic_energy"}
    T = traj.frame_count
    assert m["linear_momentum"].shape == (T, 2) and m["angular_momentum"].shape == (T,)
    np.testing.assert_allclose(m["mass"], traj.mass.sum())
    np.testing.assert_allclose(m["linear_momentum"], np.tile(m["linear_momentum"][0], (T, 1)), rtol=1e-12, atol=1e-12)
    # APIC conserves angular momentum exactly once the spin term is included (zero gravity, no contact)
    np.testing.assert_allclose(m["angular_momentum"], m["angular_momentum"][0], rtol=1e-10)
    assert m["elastic_energy"][0] == 0.0 and np.all(m["elastic_energy"][1:] > 0)
    np.testing.assert_allclose(m["kinetic_energy"][0], 0.5 * np.sum(traj.mass[:, None] * traj.v[0] ** 2))


def test_elastic_energy_only_where_defined():
    t = _handmade(dtype=np.float64)
    m = compute_metrics(t)
    assert m["angular_momentum"].shape == (3, 3)
    # only the fixed corotated group (particles 0..3) has an energy; it is summed over its particles
    from mpmlab.laws.fixed_corotated.reference import energy
    want = [sum(t.volume[p] * energy(t.fields["F"][k, p], t.params[p, :2]) for p in range(4)) for k in range(3)]
    np.testing.assert_allclose(m["elastic_energy"], want, rtol=1e-12)
    no_F = Trajectory(**{**t.__dict__, "fields": {}, "field_particles": {}})
    assert "elastic_energy" not in compute_metrics(no_F)
    unknown = Trajectory(**{**t.__dict__, "materials": [{**t.materials[0], "law": "no_such_law"}, t.materials[1]]})
    assert "elastic_energy" not in compute_metrics(unknown)


@pytest.mark.parametrize("D", [2, 3])
def test_fixed_corotated_energy_derivative_is_first_piola(D):
    from mpmlab.laws.fixed_corotated.reference import energy, first_piola
    rng = np.random.default_rng(7)
    prm = np.array([1e5, 0.3])
    for flip in (False, True):
        F = np.eye(D) + 0.3 * rng.standard_normal((D, D))
        if flip:
            F[:, 0] *= -1.0  # inverted element: the signed singular value keeps psi differentiable
        h, G = 1e-6, np.zeros((D, D))
        for i in range(D):
            for j in range(D):
                E = np.zeros((D, D)); E[i, j] = h
                G[i, j] = (energy(F + E, prm) - energy(F - E, prm)) / (2 * h)
        np.testing.assert_allclose(G, first_piola(F, prm), rtol=1e-6, atol=1e-6 * np.abs(G).max())
    assert energy(np.stack([np.eye(D)] * 4), prm).shape == (4,)
    np.testing.assert_allclose(energy(np.stack([np.eye(D)] * 4), prm), 0.0)
