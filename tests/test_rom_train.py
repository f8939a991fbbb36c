"""Offline ROM training (Eq. 24, App. B): the loss falls and reconstructs, resuming gives the same
curve, the schedule, the refusals."""
from __future__ import annotations

import logging

import numpy as np
import pytest

from mpmlab.core.errors import ConfigError
from mpmlab.rom.train import PAPER_SCHEDULE, TrainingSet, TrainOptions, fit, reconstruction_error


def bending(R=3, T=6, dt=0.05):
    """A beam bent by y += s(t) X_x^2, s = a sin(3t), per run a: x, v and F in closed form."""
    X = np.stack(np.meshgrid(np.linspace(0, 0.04, 12), np.linspace(0, 0.01, 4), np.linspace(0, 0.01, 4),
                             indexing="ij"), -1).reshape(-1, 3)
    n = len(X)
    x = np.zeros((R, T, n, 3)); v = np.zeros_like(x); F = np.tile(np.eye(3), (R, T, n, 1, 1))
    for r in range(R):
        a = 0.5 + 0.5 * r
        for t in range(T):
            s, sd = a * np.sin(3 * t * dt), 3 * a * np.cos(3 * t * dt)
            x[r, t] = X + np.stack([0 * X[:, 0], s * X[:, 0] ** 2, 0 * X[:, 0]], 1)
            v[r, t, :, 1] = sd * X[:, 0] ** 2
            F[r, t, :, 1, 0] = 2 * s * X[:, 0]
    return TrainingSet(X, x, v, F, dt)


def test_loss_falls_reconstructs_and_resumes_the_same(tmp_path, caplog):
    data = bending()
    opt = TrainOptions(latent=2, batch=2, schedule=((1e-3, 30),), points=64)
    ck = tmp_path / "ckpt.pkl"
    _, first = fit(data, opt, ck, stop_after_epochs=10, progress=False)
    assert len(first) == 10 and ck.exists()
    w, resumed = fit(data, opt, ck, progress=False)
    _, straight = fit(data, opt, None, progress=False)
    assert [h["loss"] for h in resumed] == [h["loss"] for h in straight]      # resume = uninterrupted
    assert straight[-1]["loss"] < straight[0]["loss"] / 3
    err = reconstruction_error(w, data)
    assert err["E"] < 0.02 and err["origin"] == "centroid"
    assert {"u", "F", "v", "lr", "seconds"} <= set(straight[-1])
    # a resume that would change the curve is refused, naming the option
    for changed, name in ((dict(schedule=((3e-3, 30),)), "schedule"), (dict(lambda_F=10.0), "lambda_F"),
                          (dict(batch=4), "batch")):
        other = TrainOptions(**{**dict(latent=2, batch=2, schedule=((1e-3, 30),), points=64), **changed})
        with pytest.raises(ConfigError, match=f"trained with {name} = .* this run asks for"):
            fit(data, other, ck, progress=False)
    # ... and so is one on other snapshots (a scene changed and its snapshots were remade: all moved by 0.1 %)
    moved = bending()
    moved.x[1] *= 1.001
    with pytest.raises(ConfigError, match="trained on other snapshots"):
        fit(moved, opt, ck, progress=False)
    # snapshots remade on another machine (another digest, the same up to round-off) resume, with a warning
    remade = bending()
    remade.x[0, 1, 0, 0] += 1e-9
    with caplog.at_level(logging.WARNING, logger="mpmlab"):
        _, again = fit(remade, opt, ck, progress=False)
    assert "at round-off only" in caplog.text and len(again) == 30


def test_schedule_is_the_papers_and_scales():
    opt = TrainOptions()
    assert opt.epochs() == list(PAPER_SCHEDULE) and opt.total_epochs == 850
    small = TrainOptions(schedule_scale=0.1)
    assert small.epochs() == [(1e-3, 50), (1e-4, 20), (1e-5, 10), (1e-6, 5)]
    assert [small.lr_at(e) for e in (0, 49, 50, 69, 70, 79, 80, 84, 200)] == \
        [1e-3, 1e-3, 1e-4, 1e-4, 1e-5, 1e-5, 1e-6, 1e-6, 1e-6]


def test_task_schema_and_options_share_one_set_of_fields():
    """``task=rom_train``'s training options are ``TrainOptions``' fields (written once, in
    ``TrainSettings``), with the same defaults, and ``TrainOptions.from_config`` reads them off the
    composed task (typed; ``points`` may stay None; ``schedule`` from a YAML list of pairs)."""
    import dataclasses

    from mpmlab.config import compose
    from mpmlab.rom.options import TrainSettings
    from mpmlab.tasks.rom_train import RomTrainConfig

    shared = [f.name for f in dataclasses.fields(TrainSettings)]
    assert shared == ["latent", "lambda_F", "lambda_v", "batch", "schedule", "schedule_scale", "points",
                      "frame_stride", "seed"]
    options = {f.name: f.default for f in dataclasses.fields(TrainOptions)}
    schema = {f.name: f.default for f in dataclasses.fields(RomTrainConfig)}
    assert set(options) == set(shared)
    assert {k: schema[k] for k in shared} == {k: options[k] for k in shared}
    assert TrainOptions.from_config(compose(["task=rom_train"]).task) == TrainOptions()
    tc = compose(["task=rom_train", "task.latent=7", "task.lambda_F=0", "task.points=64", "task.seed=3"]).task
    opt = TrainOptions.from_config(tc, schedule=((1e-3, 5),))
    assert opt == TrainOptions(latent=7, lambda_F=0.0, points=64, seed=3, schedule=((1e-3, 5),))
    assert type(opt.lambda_F) is float and type(opt.points) is int
    assert TrainOptions.from_config({"batch": "4"}) == TrainOptions(batch=4)      # a mapping; the rest defaults
    custom = TrainOptions.from_config(compose(["task=rom_train", "task.schedule=[[3e-3,150],[1e-4,50]]"]).task)
    assert custom.epochs() == [(3e-3, 150), (1e-4, 50)] and custom.total_epochs == 200


@pytest.mark.parametrize("bad", [(), ((1e-3, 0),), ((-1.0, 5),), ((1e-3,),), "fast"])
def test_a_malformed_schedule_is_refused_in_one_line(bad):
    with pytest.raises(ConfigError, match="schedule") as e:
        TrainOptions(schedule=bad)
    assert "\n" not in str(e.value)


def test_refusals_are_one_line():
    data = bending(R=1, T=2)
    cases = [
        (TrainingSet(data.X, data.x, data.v, None, data.dt), TrainOptions(), "needs F"),
        (TrainingSet(data.X, data.x, None, data.F, data.dt), TrainOptions(), "needs v"),
        (data, TrainOptions(points=10_000), "points = 10000"),
    ]
    for d, opt, msg in cases:
        with pytest.raises(ConfigError, match=msg) as e:
            fit(d, opt, None, progress=False)
        assert "\n" not in str(e.value)
    with pytest.raises(ConfigError, match="must be"):
        TrainingSet(data.X, data.x, data.v[:, :1], data.F, data.dt)
    with pytest.raises(ConfigError, match="positive"):
        TrainingSet(data.X, data.x, data.v, data.F, 0.0)


def _task(out, *overrides, overwrite=False):
    from mpmlab.config import compose
    from mpmlab.tasks import RunContext, run_task

    cfg = compose(["task=rom_train", "output.plots=false", *overrides])
    return run_task(cfg, RunContext(output_dir=out, overwrite=overwrite, progress=False, job={}))


def test_rom_train_task_on_tiny_torsion_snapshots_resumes(tmp_path):
    """task=rom_train on two training runs and two test runs of the torsion study at `tiny` (Warp FOM):
    a stopped run resumes to the planned epochs; weights, checkpoint, recording and summary are written,
    with the reconstruction error on train and test."""
    import json

    from mpmlab.rom import networks as N
    from mpmlab.rom.snapshots import run_study, study

    s = study("torsion")
    data = tmp_path / "data"
    run_study(s, data, runs=list(s.train[:2]) + list(s.test[:2]), overrides=["scene.resolution=tiny", "backend=warp"])
    out = tmp_path / "train"
    out.mkdir()
    common = ["task.study=torsion", f"task.data={data}", "task.max_runs=2", "task.latent=2",
              "task.schedule_scale=0.01", "task.batch=2"]
    first = _task(out, *common, "task.stop_after_epochs=3")
    assert first["status"] == "stopped" and first["epochs"] == 3
    done = _task(out, *common)
    assert done["status"] == "ok" and done["epochs"] == done["epochs_planned"] == 9
    assert [h["loss"] for h in done["history"][:3]] == [h["loss"] for h in first["history"]]
    assert set(done["reconstruction_error"]) == {"train", "test"}
    for f in ("rom_weights.safetensors", "train_checkpoint.pkl", "recording.rrd", "summary.json"):
        assert (out / f).exists(), f
    w = N.load(out / "rom_weights.safetensors", expect_dim=3, expect_latent=2)
    assert w.spec.n_points == done["points"]
    assert json.loads((out / "summary.json").read_text())["runs"]["train"] == list(s.train[:2])


def test_rom_train_task_refuses_a_test_only_study(tmp_path):
    with pytest.raises(ConfigError, match="no training runs"):
        _task(tmp_path, "task.study=torsion_fine", f"task.data={tmp_path}")
    with pytest.raises(ConfigError, match="needs task.study"):
        _task(tmp_path)
