"""Issue #12 "Outputs that never lie", items 8, 9, 10 and 13: keys that nothing reads are refused,
bad values end with one line and exit code 2, no false ERROR / driver lines, one float dtype per
precision on both backends."""
from __future__ import annotations

import ctypes
import logging
import os
import subprocess
import sys
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import pytest

from mpmlab.cli import EXIT_CONFIG, main
from mpmlab.config import compose

FAST = ["steps=2", "frame_every=1", "output=minimal"]


def run_cli(tmp_path, capsys, *overrides):
    """``mpmlab <overrides>`` in this process: (exit code, the ``mpmlab: error:`` line or '')."""
    capsys.readouterr()
    code = main([*overrides, f"hydra.run.dir={tmp_path / 'run'}"])
    err = capsys.readouterr().err
    errors = [l for l in err.splitlines() if l.startswith("mpmlab: error: ")]
    return code, (errors[-1][len("mpmlab: error: "):] if errors else "")


def _has_cuda_driver() -> bool:
    for name in ("libcuda.so.1", "libcuda.so"):
        try:
            ctypes.CDLL(name)
            return True
        except OSError:
            pass
    return False


# ---- item 8: keys that no schema reads -------------------------------------------------------------
def test_plus_key_typo_in_a_body_is_refused_with_did_you_mean(tmp_path, capsys):
    code, msg = run_cli(tmp_path, capsys, "+scene.bodies.cube.velocty=[1,2,3]", *FAST)
    assert code == EXIT_CONFIG
    assert msg == ("unknown key 'scene.bodies.cube.velocty' (added with +); did you mean "
                   "'scene.bodies.cube.velocity'? Nothing reads it: fix the name or remove it "
                   "(`mpmlab --cfg job` lists the keys).")
    assert not (tmp_path / "run" / "summary.json").exists()   # refused before anything ran


def test_plus_top_level_key_points_to_the_real_key(tmp_path, capsys):
    code, msg = run_cli(tmp_path, capsys, "+overwrite=True", *FAST)
    assert code == EXIT_CONFIG
    assert msg == ("unknown key 'overwrite' (added with +); did you mean 'output.overwrite'? Nothing reads "
                   "it: fix the name or remove it (`mpmlab --cfg job` lists the keys).")


def test_boundary_options_are_checked_against_the_boundary_kind(tmp_path, capsys):
    code, msg = run_cli(tmp_path, capsys, "+scene.boundaries.walls.thikness=2", *FAST)
    assert code == EXIT_CONFIG
    assert msg.startswith("unknown key 'scene.boundaries.walls.thikness' (added with +); did you mean "
                          "'scene.boundaries.walls.thickness'?")
    code, msg = run_cli(tmp_path, capsys, "+scene.boundaries.walls.extra.thicknes=2", *FAST)
    assert code == EXIT_CONFIG
    assert msg.startswith("unknown key 'scene.boundaries.walls.extra.thicknes' (added with +); did you mean "
                          "'scene.boundaries.walls.extra.thickness'?")


def test_scene_vars_typo_is_refused(tmp_path, capsys):
    """scene.vars are read only by the scene's interpolations: H (for H0) is read by nothing."""
    code, msg = run_cli(tmp_path, capsys, "task=inverse", "experiment=jaxmpm_velocity_constant",
                        "scene.resolution=tiny", "+scene.vars.H=0.3", *FAST)
    assert code == EXIT_CONFIG
    assert msg.startswith("unknown key 'scene.vars.H' (added with +); did you mean 'scene.vars.H0'?")


def test_a_plugin_boundary_keeps_its_own_options():
    """Options a registered boundary class declares are read (they reach its constructor)."""
    from mpmlab.boundaries import Walls
    from mpmlab.config import unknown_keys
    from mpmlab.core import registry
    from mpmlab.core.interfaces import AbstractBoundary

    @dataclass(frozen=True)
    class Spring(AbstractBoundary):
        name: ClassVar[str] = "issue12_spring"
        implementations: ClassVar[dict] = Walls.implementations
        stiffness: float = 1.0

    registry.boundaries.register("issue12_spring", Spring, provenance="test")
    try:
        base = ["scene.boundaries.walls.kind=issue12_spring"]
        assert unknown_keys(compose(base + ["+scene.boundaries.walls.stiffness=2.0"])) == []
        assert unknown_keys(compose(base + ["+scene.boundaries.walls.extra.stiffness=2.0"])) == []
        found = unknown_keys(compose(base + ["+scene.boundaries.walls.stifness=2.0"]))
        assert found == [("scene.boundaries.walls.stifness", ["scene.boundaries.walls.kind",
                                                               "scene.boundaries.walls.enabled",
                                                               "scene.boundaries.walls.stiffness"])]
    finally:
        registry.boundaries._objects.pop("issue12_spring", None)
        registry.boundaries._provenance.pop("issue12_spring", None)


def test_packaged_configs_have_no_unread_keys():
    """No false alarm on what ships: every scene, experiment and task composes without unknown keys."""
    from mpmlab.config import CONF_DIR, unknown_keys

    names = [f"scene={p.stem}" for p in sorted((CONF_DIR / "scene").glob("*.yaml"))]
    names += [f"experiment={p.stem}" for p in sorted((CONF_DIR / "experiment").glob("*.yaml"))]
    names += [f"task={p.stem}" for p in sorted((CONF_DIR / "task").glob("*.yaml"))]
    for o in names:
        assert unknown_keys(compose([o])) == [], o


def test_cfg_job_still_prints_the_config(capsys):
    assert main(["--cfg", "job", "+overwrite=True", "scene.dt=0"]) == 0
    out = capsys.readouterr().out
    assert "overwrite: true" in out and "dt: 0" in out


# ---- item 9: values that ended as "internal error" or were read with the wrong type ----------------
def test_dt_zero_is_a_number_and_refused(tmp_path, capsys):
    code, msg = run_cli(tmp_path, capsys, "scene.dt=0", *FAST)
    assert code == EXIT_CONFIG
    assert msg == ("scene 'nclaw_jelly': scene.dt = 0 must be > 0 (seconds) or auto; set scene.dt to a "
                   "positive time step or scene.dt=auto.")


def test_integer_dt_reaches_the_cfl_check(tmp_path, capsys):
    code, msg = run_cli(tmp_path, capsys, "scene.dt=10", *FAST)
    assert code == EXIT_CONFIG
    assert msg.startswith("scene 'nclaw_jelly': dt = 10 s gives CFL number ") and "cfl_limit 0.5" in msg


def test_negative_seed_is_a_config_error(tmp_path, capsys):
    code, msg = run_cli(tmp_path, capsys, "seed=-1", *FAST)
    assert code == EXIT_CONFIG
    assert msg == "seed = -1 must be >= 0; use seed=0 or another non-negative integer."


@pytest.mark.parametrize("value", ["0", "-1000"])
def test_non_positive_density_is_refused(tmp_path, capsys, value):
    code, msg = run_cli(tmp_path, capsys, f"material.density={value}", *FAST)
    assert code == EXIT_CONFIG
    assert msg == (f"scene 'nclaw_jelly', body 'cube': material.density = {float(value)} must be > 0 kg/m^3; "
                   f"set material.density to the material's rest density (water: 1000).")


def test_non_positive_density_of_a_body_material_is_refused(tmp_path, capsys):
    code, msg = run_cli(tmp_path, capsys, "scene=jelly_pool_drop", "scene.resolution=tiny",
                        "scene.bodies.pool.material.density=0", *FAST)
    assert code == EXIT_CONFIG
    assert msg == ("scene 'jelly_pool_drop', body 'pool': scene.bodies.pool.material.density = 0.0 must be "
                   "> 0 kg/m^3; set scene.bodies.pool.material.density to the material's rest density (water: 1000).")


def test_cuda_device_without_gpu_is_a_config_error(tmp_path, capsys):
    import warp as wp

    if wp.get_cuda_device_count() > 0:
        pytest.skip("this machine has a CUDA device")
    code, msg = run_cli(tmp_path, capsys, "backend=warp", "backend.device=cuda:0", *FAST)
    assert code == EXIT_CONFIG
    assert msg.startswith("backend.device='cuda:0' but Warp sees no CUDA device on this machine (devices: cpu")
    assert msg.endswith("); use backend.device=cpu or run on a GPU machine.")
    assert not (tmp_path / "run" / "config.yaml").exists()   # refused before anything was written


# ---- item 10: no ERROR line when nothing is wrong; no CUDA driver line on a CPU machine --------------
def test_optax_function_target_logs_no_error(caplog):
    from omegaconf import OmegaConf

    from mpmlab.inverse.lm import LevenbergMarquardt
    from mpmlab.tasks.inverse import _levenberg_marquardt_class

    with caplog.at_level(logging.DEBUG):
        assert _levenberg_marquardt_class(OmegaConf.create({"_target_": "optax.adam"})) is None
        assert _levenberg_marquardt_class(OmegaConf.create({"_target_": "optax.adm"})) is None
    assert [r for r in caplog.records if r.levelno >= logging.ERROR] == []
    lm = OmegaConf.create({"_target_": "mpmlab.inverse.lm.LevenbergMarquardt"})
    assert _levenberg_marquardt_class(lm) is LevenbergMarquardt


@pytest.fixture(scope="module")
def warp_cli_run(tmp_path_factory):
    """One real ``mpmlab backend=warp`` process (the driver line is printed once per process)."""
    run = tmp_path_factory.mktemp("warp_cli") / "run"
    env = dict(os.environ)
    env.pop("MPMLAB_DEBUG", None)
    env.pop("MPMLAB_WARP_DEVICE", None)
    proc = subprocess.run([sys.executable, "-m", "mpmlab", "backend=warp", *FAST, "output.trajectory=true",
                           "output.fields=[F,C]", f"hydra.run.dir={run}"],
                          capture_output=True, text=True, timeout=600, env=env)
    return proc, run


def test_warp_on_a_cpu_machine_prints_no_driver_line(warp_cli_run):
    proc, _ = warp_cli_run
    assert proc.returncode == 0, proc.stderr[-2000:]
    if _has_cuda_driver():
        pytest.skip("this machine has a CUDA driver: Warp prints no driver line anyway")
    assert "CUDA driver" not in proc.stderr + proc.stdout


# ---- item 13: one float dtype per precision on both backends ---------------------------------------
def test_warp_fp32_trajectory_file_is_float32(warp_cli_run):
    import h5py

    proc, run = warp_cli_run
    assert proc.returncode == 0, proc.stderr[-2000:]
    with h5py.File(run / "trajectory.h5", "r") as f:
        fr = f["frames"]
        assert {k: fr[k].dtype for k in ("x", "v", "F", "C")} == {k: np.dtype(np.float32) for k in ("x", "v", "F", "C")}
        assert fr["step"].dtype == np.int64


@pytest.mark.parametrize("backend", ["jax", "warp"])
@pytest.mark.parametrize("precision", ["fp32", "fp64"])
def test_rollout_and_to_numpy_dtype_follow_the_precision(backend, precision):
    sys.path.insert(0, os.path.dirname(__file__))
    from scenes import all_laws_scene

    from mpmlab.simulator import build_stepper
    from mpmlab.transfers import make_transfer

    want = np.dtype(np.float32 if precision == "fp32" else np.float64)
    # hencky_drucker_prager carries F and eps_p, weakly_compressible J, drucker_prager_jaumann sigma
    scene = all_laws_scene(2, laws=["hencky_drucker_prager", "weakly_compressible", "drucker_prager_jaumann"])
    st = build_stepper(scene, backend, make_transfer("apic"), precision)
    traj = st.rollout(steps=2, every=1, fields=("F", "C", "J", "sigma", "eps_p"))
    assert sorted(traj.fields) == ["C", "F", "J", "eps_p", "sigma"]
    got = {"x": traj.x.dtype, "v": traj.v.dtype, **{k: a.dtype for k, a in traj.fields.items()}}
    assert got == {k: want for k in got}
    assert traj.step.dtype == np.int64
    npstate = st.to_numpy(st.init())
    floats = {k: np.asarray(a).dtype for k, a in npstate.items() if k != "t" and not k.endswith("_particles")}
    assert floats == {k: want for k in floats} and {"x", "v", "C", "F", "J", "sigma", "eps_p"} <= set(floats)
    assert all(np.asarray(npstate[k]).dtype == np.int64 for k in npstate if k.endswith("_particles"))
