"""``task=nclaw_train`` and ``task=nclaw_eval`` from the command line, and a full 2D training (NCLaw,
Ma et al. 2023): the loss falls >= 10x in 30 epochs on each backend, a resumed training repeats the
curve, trained weights run on the other backend, bad datasets are refused in one line, and the
labeled and sys-id baselines reach their targets. Split from ``test_nclaw_train.py`` so the two files
run on different CI workers.
"""
from __future__ import annotations

import dataclasses
import json
import math
from types import SimpleNamespace

import numpy as np
import pytest

from mpmlab.cli import main
from mpmlab.core.errors import ConfigError, TimeStepError
from mpmlab.inverse.teacher import TeacherForcedFit
from mpmlab.laws.nclaw import Law, save_weights

from .test_nclaw_train import GROUPS, NETS, fit20, make_fit, square_scene, truth  # noqa: F401  (truth: a fixture)


def test_training_lowers_the_loss_and_resumes_on_jax(truth, tmp_path):
    """A 2D 200-step training lowers the loss >= 10x within 30 epochs (the release's lrs, clip and
    cosine schedule; period 50); stopped at epoch 12 and resumed from its checkpoint, the curve is the
    uninterrupted one."""
    import shutil

    ck, ck12 = tmp_path / "ck.pkl", tmp_path / "ck12.pkl"
    fit = make_fit("jax", truth, steps=200, epochs=30, period=50.0)
    opt, sch = fit.optimizer(NETS)
    fit.run(30, opt, sch, progress=False, checkpoint=ck, checkpoint_every=1,
            on_checkpoint=lambda raw: shutil.copy(ck, ck12) if fit.epoch == 12 else None)
    losses = [h["loss"] for h in fit.history]
    assert len(losses) == 30 and min(losses[-5:]) <= 0.1 * losses[0], losses
    assert fit.final_loss <= 0.1 * losses[0]
    h = fit.history[0]
    assert h["period"] == 50.0 and h["segments"] == 4 and set(h["grad_norms"]) == {"elastic", "plastic"}
    assert h["lr"] == {"elastic": 1.0, "plastic": 0.1}

    again = make_fit("jax", truth, steps=200, epochs=30, period=50.0)       # a new process would do the same
    opt, sch = again.optimizer(NETS)
    again.run(30, opt, sch, progress=False, checkpoint=ck12, checkpoint_every=1)
    assert len(again.history) == 30
    np.testing.assert_allclose([h["loss"] for h in again.history], losses, rtol=1e-10)


def test_a_resume_on_other_data_or_options_is_refused(truth, tmp_path):
    """The identity kept beside the checkpoint (mpmlab.core.resume): a resume on changed data or with a
    changed option stops in one line naming it; the same identity resumes; a checkpoint without one
    (written before the check) resumes unchecked."""
    from mpmlab.core.resume import array_digest, identity_path

    ck = tmp_path / "ck.pkl"
    same = {"dataset": array_digest(truth["x"], truth["F"]), "nets": NETS}
    fit = make_fit("jax", truth, steps=20, epochs=2, period=5.0)
    opt, sch = fit.optimizer(NETS)
    fit.run(1, opt, sch, progress=False, checkpoint=ck, checkpoint_every=1, identity=same)
    assert fit.epoch == 1 and identity_path(ck).exists()
    other_data = dict(same, dataset=array_digest(truth["x"] + 1e-12, truth["F"]))
    other_lr = dict(same, nets={"elastic": {"lr": 0.5, "clip": 0.1}, "plastic": NETS["plastic"]})
    for changed, key in ((other_data, "dataset"), (other_lr, "nets")):
        with pytest.raises(ConfigError, match=f"was made with {key} = .*this run has .*resume with the same {key}"):
            fit.run(2, opt, sch, progress=False, checkpoint=ck, identity=changed)
    assert fit.epoch == 1                       # refused before any epoch ran
    fit.run(2, opt, sch, progress=False, checkpoint=ck, identity=same)
    assert fit.epoch == 2 and len(fit.history) == 2
    identity_path(ck).unlink()                  # an older checkpoint: no identity recorded
    fit.run(3, opt, sch, progress=False, checkpoint=ck, identity=other_lr)
    assert fit.epoch == 3


def test_data_remade_at_round_off_resumes_with_a_note(truth, tmp_path):
    """Data made again on another machine differ in their last bits (another digest): with fingerprints in
    both identities a resume goes on and records why; a real change of the data is still refused."""
    from mpmlab.core.resume import array_digest, array_fingerprint, read_identity

    def identity(x):
        return {"dataset": array_digest(x, truth["F"]), "dataset_fingerprint": array_fingerprint(x, truth["F"]),
                "nets": NETS}

    ck = tmp_path / "ck.pkl"
    fit = make_fit("jax", truth, steps=20, epochs=3, period=5.0)
    opt, sch = fit.optimizer(NETS)
    fit.run(1, opt, sch, progress=False, checkpoint=ck, checkpoint_every=1, identity=identity(truth["x"]))
    rng = np.random.default_rng(0)
    moved = truth["x"] + 1e-6 * np.abs(truth["x"]).max() * rng.uniform(-1, 1, truth["x"].shape)    # last bits (fp32)
    with pytest.raises(ConfigError, match="was made with dataset = "):
        fit.run(2, opt, sch, progress=False, checkpoint=ck, identity=identity(truth["x"] + 1e-3))   # 1 mm: refused
    fit.run(2, opt, sch, progress=False, checkpoint=ck, identity=identity(moved))
    assert fit.epoch == 2 and len(fit.resume_notes) == 1
    assert "at round-off only" in fit.resume_notes[0] and "resuming" in fit.resume_notes[0]
    assert read_identity(ck)["resume_notes"] == fit.resume_notes          # kept for the resumes after
    fit.run(3, opt, sch, progress=False, checkpoint=ck, identity=identity(moved))
    assert fit.epoch == 3 and len(fit.resume_notes) == 1


# ---- the task, from the command line -------------------------------------------------------------------------
def mpmlab_cli(args, capsys=None, expect=0):
    """`mpmlab ARGS` run in this process: ``mpmlab.cli.main``, the function the console script calls, with
    the exit code it returns and (given ``capsys``) the stdout and stderr it wrote. In-process, the runs
    share this process's imports and compiled programs instead of paying a Python start, the imports and
    every compile again per run; the console script as a real subprocess (exit codes, one-line errors,
    outputs) is tests/test_cli.py's (test_run_writes_outputs_and_one_line_summary and others)."""
    if capsys is not None:
        capsys.readouterr()
    code = main(list(args))
    out = capsys.readouterr() if capsys is not None else None
    got = SimpleNamespace(returncode=code, stdout=out.out if out else "", stderr=out.err if out else "")
    assert got.returncode == expect, got.stdout[-3000:] + got.stderr[-3000:]
    return got


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    d = tmp_path_factory.mktemp("nclaw_data")
    mpmlab_cli(["scene=nclaw_square_2d", "transfer=mls", "precision=fp64", "output.fields=[F,C]",
                "output.recording=false", "output.plots=false", f"hydra.run.dir={d}"])
    return d / "trajectory.h5"


TRAIN = ["task=nclaw_train", "scene=nclaw_square_2d", "material=nclaw", "transfer=mls", "precision=fp64"]


def test_train_task_on_warp_and_reuse_on_jax(dataset, tmp_path, capsys):
    """task=nclaw_train on Warp: the loss falls >= 10x in 30 epochs; summary, recording, weight file;
    the weights drive the law on JAX and Warp to the same 100-step rollout (<= 1e-9 m)."""
    from mpmlab.io.h5 import read_trajectory
    from mpmlab.io.rerun import read_recording_component

    run = tmp_path / "train"
    mpmlab_cli(TRAIN + ["backend=warp", f"task.dataset={dataset}", "task.epochs=30", "task.teacher.start=50",
                        "task.teacher.end=50", f"hydra.run.dir={run}"], capsys)
    s = json.loads((run / "summary.json").read_text())
    losses = [h["loss"] for h in s["history"]]
    assert s["status"] == "ok" and s["epochs"] == 30 and min(losses[-5:]) <= 0.1 * losses[0], losses
    assert s["weights"] == "nclaw_weights.safetensors" and s["law"]["dim"] == "2" and s["seconds_per_epoch"] > 0
    assert {"period", "lr", "grad_norms", "segments"} <= set(s["history"][-1])
    assert (run / "train.png").stat().st_size > 0 and (run / "train_checkpoint.pt").exists()
    rec = run / "recording.rrd"
    for entity in ("metrics/loss", "metrics/period", "metrics/lr/elastic", "metrics/grad_norm/plastic"):
        assert len(read_recording_component(rec, entity, "Scalars:scalars", index="epoch")) == 30, entity
    weights = run / "nclaw_weights.safetensors"
    # the states the trained law visits on its own scene, recorded for the divergence note: the same
    # numbers as a free JAX rollout of the trained weights, every 10th frame
    import mpmlab
    from mpmlab.nclaw.probe import state_range

    rng = s["state_range"]
    assert Law(weights_file=str(weights)).trained_range() == rng
    st = mpmlab.build_stepper(square_scene("nclaw", {}, {"weights_file": str(weights)}), "jax", "mls", "fp64")
    F = st.rollout(steps=s["steps"], every=10, fields=("F",)).fields["F"][1:]
    ref = state_range(F)
    assert ref["frames"] == rng["frames"] == s["steps"] // 10
    for k in ("deviatoric_stretch_max", "deviatoric_stretch_p99", "J_min", "J_max"):
        assert rng[k] == pytest.approx(ref[k], rel=1e-6, abs=1e-9), k
    assert 0 < rng["deviatoric_stretch_max"] and rng["J_min"] < 1 < rng["J_max"]
    xs = {}
    for backend in ("jax", "warp"):
        out = tmp_path / f"reuse_{backend}"
        mpmlab_cli(["scene=nclaw_square_2d", "material=nclaw", f"+material.options.weights_file={weights}",
                    f"backend={backend}", "transfer=mls", "precision=fp64", "scene.steps=100", "output.recording=false",
                    "output.plots=false", f"hydra.run.dir={out}"], capsys)
        xs[backend] = read_trajectory(str(out / "trajectory.h5")).x
    assert float(np.abs(xs["jax"] - xs["warp"]).max()) <= 1e-9


def test_train_task_refuses_bad_datasets(dataset, truth, tmp_path, capsys):
    """One line, exit code 2: no dataset; a dataset kept every 2nd step; one of another scene (CLI). A
    dataset without C and F (API: the same check)."""
    from mpmlab.io.h5 import read_trajectory, write_trajectory
    from mpmlab.tasks.nclaw_train import load_truth

    common = TRAIN + ["task.epochs=1", "output.recording=false", "output.plots=false"]
    p = mpmlab_cli(common + [f"hydra.run.dir={tmp_path / 'a'}"], capsys, expect=2)
    assert "task.dataset" in p.stderr.strip().splitlines()[-1]
    traj = read_trajectory(str(dataset))
    sparse = tmp_path / "sparse.h5"
    write_trajectory(sparse, dataclasses.replace(traj, x=traj.x[::2], v=traj.v[::2], time=traj.time[::2],
                                                 step=traj.step[::2], fields={k: a[::2] for k, a in traj.fields.items()}))
    p = mpmlab_cli(common + [f"task.dataset={sparse}", f"hydra.run.dir={tmp_path / 'c'}"], capsys, expect=2)
    assert "keeps only every 2-th step" in p.stderr.strip().splitlines()[-1]
    p = mpmlab_cli(common + [f"task.dataset={dataset}", "scene.bodies.square.particles_per_cell=4",
                             f"hydra.run.dir={tmp_path / 'd'}"], capsys, expect=2)
    assert "256" in p.stderr and "64 particles" in p.stderr.strip().splitlines()[-1]
    # without C and F: the fit names what is missing
    fit = fit20("jax", truth)
    bare = {"x": truth["x"], "v": truth["v"]}
    with pytest.raises(ConfigError, match="needs C, F at every step"):
        TeacherForcedFit(fit.stepper, fit.scene, fit.parameters, bare, fit.forcing, epochs=1, groups=GROUPS)
    plain = tmp_path / "plain.h5"
    write_trajectory(plain, dataclasses.replace(traj, fields={}, field_particles={}))
    with pytest.raises(ConfigError, match="has no C, F"):
        load_truth(str(plain), fit.stepper, 20)


def test_train_task_refuses_to_resume_with_other_options(dataset, tmp_path, capsys):
    """Stopped after one epoch, the same command with another learning rate is refused (exit code 2, one
    line naming task.nets), before a rollout runs; the checkpoint is left as it was."""
    run = tmp_path / "r"
    common = TRAIN + [f"task.dataset={dataset}", "task.epochs=2", "scene.steps=20", "task.teacher.start=20",
                      "task.teacher.end=20", "output.recording=false", "output.plots=false", f"hydra.run.dir={run}"]
    mpmlab_cli(common + ["task.stop_after_epochs=1"], capsys)
    assert json.loads((run / "summary.json").read_text())["status"] == "partial"
    before = (run / "train_checkpoint.pkl").read_bytes()
    p = mpmlab_cli(common + ["task.nets.elastic.lr=0.5"], capsys, expect=2)
    line = p.stderr.strip().splitlines()[-1]
    assert "was made with nets = " in line and "resume with the same nets" in line, line
    assert (run / "train_checkpoint.pkl").read_bytes() == before


def test_train_diverging_gives_fit_diverged(dataset, tmp_path, capsys):
    """A learning rate that blows the law up: FitDiverged, exit code 3, one line (on_divergence=stop; the
    default backoff's step back is tested in tests/test_inverse.py)."""
    p = mpmlab_cli(TRAIN + ["backend=warp", f"task.dataset={dataset}", "task.epochs=3", "task.nets.elastic.lr=1.0e4",
                            "task.on_divergence=stop",
                            "scene.steps=20", "task.teacher.start=20", "task.teacher.end=20", "output.recording=false",
                            "output.plots=false", f"hydra.run.dir={tmp_path / 'x'}"], capsys, expect=3)
    assert "diverged" in p.stderr.strip().splitlines()[-1]


def test_dt_auto_needs_a_wave_speed(tmp_path):
    """A network with zero weights has no stiffness at rest: dt: auto is refused (a fixed dt is required)."""
    law = Law()
    path = tmp_path / "zero.safetensors"
    save_weights(str(path), {k: np.zeros(s) for k, s in law.weight_shapes(2).items()}, law, dim=2)
    scene = square_scene("nclaw", {}, {"weights_file": str(path)}, velocity=(0.0, 0.0), omega=0.0, dt="auto")
    with pytest.raises(TimeStepError, match="nonzero wave speed"):
        scene.resolve_dt()




def test_labeled_baseline_and_eval_task(dataset, tmp_path, capsys):
    """task.method=labeled fits the nets to the dataset's (F, tau) and (F_n, C_n+1 -> F_n+1) pairs; its
    law reproduces the 2D JELL-O trajectory to <= 1e-6 m^2 (NCLaw's target for labeled), and
    task=nclaw_eval's metric is position_mse of the two runs a plain simulate gives."""
    from mpmlab.io.h5 import read_trajectory
    from mpmlab.nclaw.scenes import position_mse

    run = tmp_path / "labeled"
    mpmlab_cli(TRAIN + ["task.method=labeled", f"task.dataset={dataset}", f"hydra.run.dir={run}"], capsys)
    s = json.loads((run / "summary.json").read_text())
    assert s["method"] == "labeled" and s["true_law"] == "fixed_corotated"
    assert s["labeled"]["e"]["loss_final"] < 1e-2 * s["labeled"]["e"]["loss_initial"]
    for net in ("e", "p"):      # each net keeps its best epoch: never worse than it started or ended
        r = s["labeled"][net]
        assert 0 <= r["best_epoch"] <= 30 and r["loss_final"] <= min(r["loss_initial"], r["loss_last_epoch"])
    weights = run / "nclaw_weights.safetensors"
    # its rollout's range is recorded as a teacher-forced training's is (the divergence note reads it)
    assert Law(weights_file=str(weights)).trained_range() == s["state_range"]
    assert s["state_range"]["frames"] == 20 and s["state_range"]["inverted"] == 0
    ev = tmp_path / "eval"
    mpmlab_cli(["task=nclaw_eval", "task.material=jelly", f"task.weights={weights}", "precision=fp64",
                "task.cases=[{name: recon, scene: nclaw_square_2d, steps: 200, tags: [qualitative]}]",
                f"hydra.run.dir={ev}"], capsys)
    e = json.loads((ev / "summary.json").read_text())
    mse = e["cases"]["recon"]["mse"]
    assert e["cases"]["recon"]["status"] == "ok" and mse <= 1e-6, mse
    # the learned law's states every 50 steps (0, 50, ..., 200), inside the range of its training scene
    assert e["cases"]["recon"]["state_range"]["frames"] == 5 and "beyond_training" not in e["cases"]["recon"]
    assert (ev / "eval.md").read_text().count("| recon |") == 2
    assert (ev / "recon_frames.png").stat().st_size > 0     # a qualitative case is shown, truth beside learned
    xs = {}
    for name, extra in (("truth", ["material=jelly"]), ("learned", ["material=nclaw", f"+material.options.weights_file={weights}"])):
        mpmlab_cli(["scene=nclaw_square_2d", *extra, "precision=fp64", "scene.frame_every=5", "output.recording=false",
                    "output.plots=false", f"hydra.run.dir={tmp_path / name}"], capsys)
        xs[name] = read_trajectory(str(tmp_path / name / "trajectory.h5")).x
    assert math.isclose(position_mse(xs["learned"], xs["truth"], every=1), mse, rel_tol=1e-9)


def test_sysid_baseline(dataset, tmp_path, capsys):
    """task.method=sysid: the true family (fixed corotated) from E^0.8 = 1e4 Pa, fitted by the same
    teacher forcing, recovers E within 5 % in 30 epochs; its reconstruction error <= 1e-6 m^2."""
    run = tmp_path / "sysid"
    mpmlab_cli(["task=nclaw_train", "task.method=sysid", "scene=nclaw_square_2d", "material=jelly", "precision=fp64",
                f"task.dataset={dataset}", "task.epochs=30", "task.teacher.start=50", "task.teacher.end=50",
                "task.sysid.lr=0.5", "output.recording=false", f"hydra.run.dir={run}"], capsys)
    s = json.loads((run / "summary.json").read_text())
    E = s["parameters"]["E"]
    assert s["history"][0]["values"]["E"] == pytest.approx(1e4, rel=1e-9)        # NCLaw's start: E^0.8
    assert E["relative_error"] < 0.05, E
    ev = tmp_path / "eval"
    mpmlab_cli(["task=nclaw_eval", "task.material=jelly", f"+task.law_params.E={E['recovered']}", "precision=fp64",
                "task.cases=[{name: recon, scene: nclaw_square_2d, steps: 200, tags: [qualitative]}]",
                f"hydra.run.dir={ev}"], capsys)
    e = json.loads((ev / "summary.json").read_text())
    assert e["label"] == "sys-id" and e["cases"]["recon"]["mse"] <= 1e-6, e["cases"]


def test_eval_rollout_raises_the_cfl_limit_for_the_learned_law():
    """The learned law runs at the case's dt: nclaw_eval's rollout lifts the scene's cfl_limit to
    task.learned_cfl_limit; without the lift the same run is refused."""
    from mpmlab.tasks.nclaw_eval import rollout

    ov = ["scene=nclaw_square_2d", "scene.dt=2.5e-3", "backend=jax", "transfer=pic", "precision=fp64",
          "output.recording=false"]
    with pytest.raises(TimeStepError, match="cfl_limit 0.5"):
        rollout(ov, 4, 4)
    x, _, n = rollout(ov, 4, 4, cfl_floor=1.0)
    assert n == 64 and x.shape[1:] == (64, 2) and np.all(np.isfinite(x))
