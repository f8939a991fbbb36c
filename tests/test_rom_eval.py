"""task=rom_eval (ROM paper Sec. 5): the reduced model of each test run beside its full-order snapshots,
on tiny torsion snapshots and briefly trained networks; the error measures; what it refuses."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from mpmlab.core.errors import ConfigError, SimulationDiverged


def _task(out, *overrides):
    from mpmlab.config import compose
    from mpmlab.tasks import RunContext, run_task

    cfg = compose(["task=rom_eval", "precision=fp64", "task.max_runs=2", *overrides])
    return run_task(cfg, RunContext(output_dir=out, overwrite=True, progress=False))


@pytest.fixture(scope="module")
def torsion(tmp_path_factory):
    """Two training and two test runs of the torsion study at `tiny` (40 points, 2 snapshots) and
    networks fitted to the training runs for a few epochs, recording them."""
    from mpmlab.rom import networks as N
    from mpmlab.rom.snapshots import load_snapshots, run_study, study
    from mpmlab.rom.train import TrainingSet, TrainOptions, fit

    root = tmp_path_factory.mktemp("rom_eval")
    s = study("torsion")
    train, test = list(s.train[:2]), list(s.test[:2])
    run_study(s, root / "data", runs=train + test, overrides=["scene.resolution=tiny", "backend=jax",
                                                                          "precision=fp64"])
    data = TrainingSet.from_snapshots(load_snapshots(root / "data", s, runs=train))
    w, _ = fit(data, TrainOptions(latent=2, batch=2, schedule=((1e-3, 8),)), None, progress=False)
    path = root / "weights.safetensors"
    N.save(path, w.params, w.norm, w.spec, training={"study": "torsion", "params": [s.runs[i].params for i in train]})
    return s, root, path, train, test


def test_rom_eval_task_writes_errors_and_timings(torsion, tmp_path):
    s, root, weights, _, test = torsion
    out = tmp_path / "eval"
    out.mkdir()
    res = _task(out, "task.study=torsion", f"task.data={root / 'data'}", f"task.weights={weights}",
                "task.quadratures=[lagrangian,eulerian]", "task.projections=[nonlinear]", "task.samples=[all]",
                "task.fom_timing_steps=6")
    assert res["status"] == "ok" and res["test_runs"] == [s.runs[i].name for i in test]
    assert [r["scheme"] for r in res["schemes"]] == ["lagrangian+nonlinear, M=all", "eulerian+nonlinear, M=all"]
    for row in res["schemes"]:
        mine = [r for r in res["rows"] if r["scheme"] == row["scheme"]]
        assert len(mine) == 2 and all(r["status"] == "ok" for r in mine)
        pooled = {k: sum(r["sums"][k] for r in mine) for k in mine[0]["sums"]}
        assert row["E"] == pytest.approx(math.sqrt(pooled["x"] / pooled["x_c"]), rel=1e-12)
        assert 0 < row["E"] < 0.5 and row["E_displacement"] > row["E"]     # the body moves less than its size
        assert row["wall_s_per_simulated_s"] > 0 and row["speedup_vs_fom"] > 0
    assert res["fom"]["wall_s_per_simulated_s"] > 0 and res["fom"]["timed_steps"] == [6, 6]
    on_disk = json.loads((out / "summary.json").read_text())
    assert on_disk["schemes"][0]["E"] == res["schemes"][0]["E"]
    assert "| eulerian+nonlinear, M=all |" in (out / "rom_eval.md").read_text()
    assert (out / "rom_eval.png").exists() and (out / "rom_latent.png").exists()
    assert all(0.0 <= r["latent_return"] <= 1.0 for r in res["rows"]) and "x̂ return" in (out / "rom_eval.md").read_text()


def test_rom_eval_refuses_runs_the_weights_were_trained_on(torsion, tmp_path):
    from mpmlab.rom import networks as N

    s, root, weights, train, test = torsion
    w = N.load(weights)
    leaky = tmp_path / "leaky.safetensors"
    N.save(leaky, w.params, w.norm, w.spec, training={"study": "torsion", "params": [s.runs[test[0]].params]})
    with pytest.raises(ConfigError, match=f"test run {s.runs[test[0]].name} .* is one of the weights' training runs"):
        _task(tmp_path, "task.study=torsion", f"task.data={root / 'data'}", f"task.weights={leaky}")


def test_rom_eval_refuses_weights_of_another_dimension_and_missing_inputs(torsion, tmp_path):
    from mpmlab.rom import networks as N

    s, root, weights, _, _ = torsion
    spec = N.RomSpec(dim=2, latent=2)
    flat = tmp_path / "2d.safetensors"
    N.save(flat, N.init_params(spec), N.identity_norm(2), spec)
    with pytest.raises(ConfigError, match="dimension is 2, expected 3"):
        _task(tmp_path, "task.study=torsion", f"task.data={root / 'data'}", f"task.weights={flat}")
    with pytest.raises(ConfigError, match="latent size is 2, expected 5"):
        _task(tmp_path, "task.study=torsion", f"task.data={root / 'data'}", f"task.weights={weights}", "task.latent=5")
    with pytest.raises(ConfigError, match="needs task.study"):
        _task(tmp_path, "task.study=torsion")
    with pytest.raises(ConfigError, match="samples = 100; it must be at least the latent size 2 and at most the 40"):
        _task(tmp_path, "task.study=torsion", f"task.data={root / 'data'}", f"task.weights={weights}",
              "task.samples=[100]", "task.quadratures=[lagrangian]", "task.projections=[linear]", "task.max_runs=1")


@pytest.fixture(scope="module")
def beam(tmp_path_factory):
    """One training run (g = 4) and one test run (g = 3) of the 2D beam study at `tiny` (96 points, 20
    snapshots) and networks fitted to the training run for a few epochs."""
    from mpmlab.rom import networks as N
    from mpmlab.rom.snapshots import load_snapshots, run_study, study
    from mpmlab.rom.train import TrainingSet, TrainOptions, fit

    root = tmp_path_factory.mktemp("rom_eval_beam")
    s = study("beam_2d")
    run_study(s, root / "data", runs=[s.train[1], s.test[0]], overrides=["scene.resolution=tiny", "backend=jax",
                                                                         "precision=fp64"])
    data = TrainingSet.from_snapshots(load_snapshots(root / "data", s, runs=[s.train[1]]))
    w, _ = fit(data, TrainOptions(latent=2, batch=4, schedule=((3e-3, 60),)), None, progress=False)
    path = root / "weights.safetensors"
    N.save(path, w.params, w.norm, w.spec, training={"study": "beam_2d", "params": [s.runs[s.train[1]].params]})
    return root, path


def test_an_unstable_rom_time_step_ends_in_simulation_diverged(beam, tmp_path):
    """dt = the snapshot interval (20 full-order steps, CFL number about 4) with the paper's explicit tangent:
    the reduced beam leaves the domain, and the task says so with SimulationDiverged (the CLI's exit code 3),
    after writing its summary. (With the default tangent, fitted at x_hat_{n+1}, this beam stays bounded at
    that dt, E 17.8 % measured: the explicit tangent's energy gain is what blows it up; there is no larger dt
    the snapshot interval allows.)"""
    root, weights = beam
    with pytest.raises(SimulationDiverged, match="lower task.dt"):
        _task(tmp_path, "task.study=beam_2d", f"task.data={root / 'data'}", f"task.weights={weights}",
              "task.quadratures=[lagrangian]", "task.projections=[linear]", "task.samples=[all]", "task.max_runs=1",
              "task.dt=0.01", "task.tangent=current")
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["status"] == "diverged" and summary["schemes"][0]["diverged"] == 1
    row = summary["rows"][0]
    assert "left the domain or is non-finite" in row["message"]
    # the snapshots kept before the divergence (one per step here) are scored, and said in the table
    at, early = row["diverged_at_step"], row["before_divergence"]
    assert at >= 3 and early["frames"] == at and early["until_s"] == pytest.approx(0.01 * (at - 1))
    assert 0.0 < early["E"] < float("inf") and early["E_F"] > 0.0
    assert "before the divergence" in (tmp_path / "rom_eval.md").read_text()


def test_rom_eval_on_the_warp_reduced_model_matches_jax(beam, tmp_path):
    """task.rom_backend=warp: the same scheme (Lagrangian + linear, every point a sample) gives the JAX
    reduced model's errors."""
    root, weights = beam
    common = ["task.study=beam_2d", f"task.data={root / 'data'}", f"task.weights={weights}",
              "task.quadratures=[lagrangian]", "task.projections=[linear]", "task.samples=[all]", "task.max_runs=1",
              "task.fom_timing_steps=20", "output.plots=false"]
    res = {}
    for backend in ("jax", "warp"):
        out = tmp_path / backend
        out.mkdir()
        res[backend] = _task(out, *common, f"task.rom_backend={backend}", f"task.fom_backend={backend}")
    j, w = res["jax"]["schemes"][0], res["warp"]["schemes"][0]
    assert res["warp"]["fom"]["rom_backend"] == "warp" and w["diverged"] == 0
    for k in ("E", "E_displacement", "E_v", "E_F"):
        assert w[k] == pytest.approx(j[k], rel=1e-8), k
    assert "reduced model on warp" in (tmp_path / "warp" / "rom_eval.md").read_text()


def test_error_measures_of_a_uniform_offset():
    """x_ROM = x_FOM + delta everywhere: E = |delta| sqrt(T N) / sqrt(sum |x - c|^2), and the v and F errors
    of an exact v and F are zero."""
    import jax

    from mpmlab.rom import evaluate as ev
    from mpmlab.rom import networks as N

    jax.config.update("jax_enable_x64", True)
    spec = N.RomSpec(dim=2, latent=2)
    params = N.linear_params(spec, np.zeros((2, 2)), np.eye(2))        # g = X + x_hat
    norm = N.identity_norm(2)
    X = np.random.default_rng(0).uniform(0, 1, (30, 2))
    z = np.array([[0.0, 0.0], [0.1, -0.2]])
    zdot = np.array([[1.0, 0.0], [1.0, 0.0]])
    delta = np.array([0.003, -0.004])
    x = X[None] + z[:, None, :] - delta
    v = np.broadcast_to(zdot[:, None, :], x.shape)
    F = np.broadcast_to(np.eye(2), (2, 30, 2, 2))
    corner = np.array([-0.5, -1.0])
    per_frame, sums = ev._sums(N.to_jax(params), N.to_jax(norm), X, z, zdot, x, v, F, X.mean(0), corner)
    err = ev.errors_of(sums)
    assert err["E"] == pytest.approx(0.005 * math.sqrt(60) / math.sqrt(np.sum((x - X.mean(0)) ** 2)), rel=1e-9)
    # the same error about the domain's corner: a larger denominator (the body sits away from it)
    assert err["E_corner"] == pytest.approx(0.005 * math.sqrt(60) / math.sqrt(np.sum((x - corner) ** 2)), rel=1e-9)
    assert err["E_corner"] < err["E"]
    assert ev.errors_of(ev._sums(N.to_jax(params), N.to_jax(norm), X, z, zdot, x, v, F, X.mean(0))[1])["E_corner"] is None
    assert err["E_v"] == pytest.approx(0.0, abs=1e-12)
    assert err["E_F"] is None                                       # F = I: no deformation to be relative to
    assert per_frame["x"] == pytest.approx([30 * 0.005 ** 2] * 2, rel=1e-9)


def test_error_sums_in_chunks_of_snapshots_are_the_sums_in_one(monkeypatch):
    """``_sums`` evaluates g a few snapshots at a time (the 30 s continual poke in one call needed 17.7 GB):
    one snapshot per chunk gives the one-call sums and per-snapshot lists, on a nonlinear map."""
    import jax

    from mpmlab.rom import evaluate as ev
    from mpmlab.rom import networks as N

    jax.config.update("jax_enable_x64", True)
    spec = N.RomSpec(dim=2, latent=2)
    rng = np.random.default_rng(1)
    X = rng.uniform(0, 1, (30, 2))
    norm = {"X_min": X.min(0), "X_max": X.max(0), "u_mean": np.zeros(2), "u_std": np.full(2, 3e-3)}
    params, nrm = N.to_jax(N.init_params(spec, seed=2)), N.to_jax(norm)
    z, zdot = rng.normal(size=(5, 2)), rng.normal(size=(5, 2))
    x = X[None] + rng.normal(0, 1e-3, (5, 30, 2))
    v = rng.normal(size=(5, 30, 2))
    F = np.eye(2) + rng.normal(0, 1e-2, (5, 30, 2, 2))
    one = ev._sums(params, nrm, X, z, zdot, x, v, F, X.mean(0), np.zeros(2))
    monkeypatch.setattr(ev, "SUM_CHUNK_POINTS", 30)
    chunked = ev._sums(params, nrm, X, z, zdot, x, v, F, X.mean(0), np.zeros(2))
    assert chunked[0] == pytest.approx(one[0], rel=1e-12) and len(chunked[0]["x"]) == 5
    assert chunked[1] == pytest.approx(one[1], rel=1e-12) and one[1]["F"] > 0 and one[1]["v"] > 0


def test_a_study_without_parameters_is_not_taken_for_a_training_run():
    """The continual poke (one run, no parameters) evaluated with weights trained on the poke study is not
    refused; a poke run the weights were trained on is."""
    from types import SimpleNamespace

    from mpmlab.rom.snapshots import study
    from mpmlab.tasks.rom_eval import check_not_trained_on

    w = SimpleNamespace(training={"study": "poke", "params": [{"theta": 0.0}, {"theta": math.pi / 6}]})
    check_not_trained_on(w, study("poke_continual"), [0])
    with pytest.raises(ConfigError, match="one of the weights' training runs"):
        check_not_trained_on(w, study("poke"), [3])


def test_latent_return_and_principal_components():
    """Fig. 14's measures: a latent that goes out and comes back returns 0, one that stays out returns 1;
    its principal components hold the motion (a planar loop in 4 latent dimensions: 2 components, all of it)."""
    from mpmlab.rom import evaluate as ev

    t = np.linspace(0.0, 2.0 * math.pi, 50)
    loop = np.stack([np.sin(t), 1.0 - np.cos(t), 0.0 * t, 0.0 * t], 1) @ np.linalg.qr(np.arange(16.0).reshape(4, 4) + np.eye(4))[0]
    assert ev.latent_return(loop) == pytest.approx(0.0, abs=1e-12)
    assert ev.latent_return(np.linspace(0.0, 1.0, 10)[:, None] * np.ones((1, 3))) == pytest.approx(1.0)
    assert ev.latent_return(np.ones((5, 3))) is None
    proj, share = ev.latent_pca(loop)
    assert proj.shape == (50, 2) and share.sum() == pytest.approx(1.0)
    assert np.linalg.norm(proj[0] - proj[-1]) == pytest.approx(0.0, abs=1e-12)


# ---- Tab. 4's tracer baseline ----------------------------------------------------------------------------
def test_tracers_at_the_material_points_reproduce_the_run(torsion):
    """With the run itself as the truth, the tracers are the coarse points again: massless, they take the
    same G2P as the material points, so the baseline reproduces the run (E ~ 1e-15)."""
    from mpmlab.rom import evaluate as ev
    from mpmlab.rom.snapshots import load_snapshots

    s, root, _, _, test = torsion
    snap = load_snapshots(root / "data", s, runs=test)
    res = ev.tracer_baseline(snap, snap, precision="fp64")
    assert [r["run"] for r in res["runs"]] == list(snap.names) and res["runs"][0]["tracers"] == 40
    assert res["E"] < 1e-12 and res["E_F"] < 1e-10


def test_tracer_baseline_against_a_finer_truth(torsion, tmp_path):
    """A 2x finer truth (tiny at dx 2 mm, its own CFL dt): the tracers are its 720 points, matched by
    position; the baseline's error is finite and small; rom_eval reports it beside the schemes."""
    from mpmlab.rom import evaluate as ev
    from mpmlab.rom.snapshots import load_snapshots, run_study, study

    s, root, weights, _, test = torsion
    test = test[:1]                      # one run: the finer runs and the tracers cost most of this test
    fine = study("torsion_fine")
    idx = [next(j for j, r in enumerate(fine.runs) if r.params == s.runs[i].params) for i in test]
    run_study(fine, tmp_path / "fine", runs=idx, overrides=[
        "scene.resolution=tiny", "scene.resolutions.tiny.dx=0.002", "scene.resolutions.tiny.dt=1.1111111111111112e-04",
        "scene.resolutions.tiny.frame_every=6", "scene.resolutions.tiny.steps=12", "backend=jax", "precision=fp64"])
    truth = load_snapshots(tmp_path / "fine", fine, runs=idx)
    snap = load_snapshots(root / "data", s, runs=test)
    truth.names = snap.names
    res = ev.tracer_baseline(snap, truth, precision="fp64")
    assert res["runs"][0]["tracers"] == 720 and 0 < res["E"] < 0.05, res["E"]
    out = tmp_path / "eval"
    out.mkdir()
    got = _task(out, "task.study=torsion", f"task.data={root / 'data'}", f"task.weights={weights}",
                "task.quadratures=[lagrangian]", "task.projections=[linear]", "task.samples=[all]",
                "task.truth_study=torsion_fine", f"task.truth_data={tmp_path / 'fine'}", "task.tracer_baseline=true",
                "task.fom_timing_steps=6", "task.max_runs=1")
    assert got["tracer_baseline"]["E"] == pytest.approx(res["E"], rel=1e-9)
    assert "tracer baseline" in (out / "rom_eval.md").read_text()
    # a truth whose points are not the coarse points refined: refused in one line
    truth.x = truth.x + 1e-4
    with pytest.raises(ConfigError, match="not the coarse bodies refined 2x"):
        ev.tracer_baseline(snap, truth, precision="fp64")


def test_tracer_baseline_needs_a_truth(torsion, tmp_path):
    s, root, weights, _, _ = torsion
    with pytest.raises(ConfigError, match="needs task.truth_study"):
        _task(tmp_path, "task.study=torsion", f"task.data={root / 'data'}", f"task.weights={weights}",
              "task.tracer_baseline=true")
