"""One simulation on several devices (``backend.devices=N``, ``mpmlab.backends.jax.sharding``), issue 20.

The sharded runs need forced host devices, which XLA takes only when JAX starts: they run in one
subprocess (``tests/_sharding_check.py``, 3 host devices, so that material groups of 16 particles are
padded) that compares against the single-device stepper: fp64 trajectories of a six-material scene on
2-cell walls for every transfer (and APIC with the uGIMP shape function), gradients
of an observed-velocity loss, and the CLI. The refusals run
here, in this one-device process.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from mpmlab.cli import EXIT_CONFIG, main
from mpmlab.core.errors import ConfigError

HERE = Path(__file__).resolve().parent
DEVICES = 3
TRAJECTORY_TOL = 1e-12      # issue 20: the sharded run agrees with the single-device one to 1e-12 (fp64)
GRADIENT_TOL = 1e-10        # ... and its gradients to 1e-10


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    out = tmp_path_factory.mktemp("sharding")
    env = dict(os.environ, XLA_FLAGS=f"--xla_force_host_platform_device_count={DEVICES}", JAX_PLATFORMS="cpu")
    env.pop("MPMLAB_DEBUG", None)
    proc = subprocess.run([sys.executable, str(HERE / "_sharding_check.py"), str(out)], cwd=out, env=env,
                          capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-4000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


@pytest.mark.slow
def test_sharded_trajectories_match_one_device(report):
    """Every transfer on 3 devices (MLS on 2 too), 160 steps in which every body lands on the walls:
    x and v within 1e-12 (m, m/s), every carried field (F, C, J, sigma, eps_p) within 1e-12 of its scale."""
    runs = report["trajectories"]
    assert set(runs) == {"pic/3", "flip/3", "apic/3", "mls/3", "tpic/3", "mls/2"}
    for name, r in runs.items():
        assert r["min_y"] < 0.1, (name, r["min_y"])                 # the bodies reach the walls
        assert r["x"] <= TRAJECTORY_TOL and r["v"] <= TRAJECTORY_TOL, (name, r)
        assert r["fields_rel"] and max(r["fields_rel"].values()) <= TRAJECTORY_TOL, (name, r)


@pytest.mark.slow
def test_sharded_shape_functions_match_one_device(report):
    """APIC with uGIMP (its per-particle lp laid out with the particles) on 3 devices, 160 steps."""
    for shape, r in report["shapes"].items():
        assert r["x"] <= TRAJECTORY_TOL and r["v"] <= TRAJECTORY_TOL and r["C_rel"] <= TRAJECTORY_TOL, (shape, r)
    assert set(report["shapes"]) == {"ugimp"}


@pytest.mark.slow
def test_sharded_gradients_match_one_device(report):
    g = report["gradients"]["apic"]
    assert {"['x']", "['v']", "['law'][0]", "['law'][1]", "['mass']", "['gravity']"} <= set(g), g
    assert max(g.values()) <= GRADIENT_TOL, g


def test_cpu_thread_pool_is_sized_before_jax_starts():
    """Forced host devices share XLA's CPU pool; jaxlib's batched SVD can deadlock it (sharding.py):
    before JAX starts, 3 devices x 1 group of >= 256 particles per device ask for 4 threads."""
    code = ("import os; from mpmlab.backends.jax.sharding import check_devices; "
            "check_devices(3, [3000, 10]); print(os.environ.get('PJRT_NPROC'))")
    env = dict(os.environ, XLA_FLAGS=f"--xla_force_host_platform_device_count={DEVICES}", JAX_PLATFORMS="cpu")
    for key in ("PJRT_NPROC", "NPROC"):
        env.pop(key, None)
    proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0 and proc.stdout.split()[-1] == "4", proc.stdout + proc.stderr[-2000:]


def test_threads_needed():
    from mpmlab.backends.jax.sharding import cpu_threads_needed

    assert cpu_threads_needed(2, [62720, 3648]) == 5       # jelly_pool_drop fine: both groups split
    assert cpu_threads_needed(3, [16, 12]) == 1            # small blocks: jaxlib never splits them


@pytest.mark.slow
def test_cli_runs_sharded(report):
    """`mpmlab backend.devices=3` (jelly_pool_drop tiny: dt: auto, two materials, walls) = one device."""
    c = report["cli"]
    assert c["status"] == "ok" and c["summary_devices"] == DEVICES and c["containment"], c
    assert c["x"] <= TRAJECTORY_TOL and c["v"] <= TRAJECTORY_TOL, c


@pytest.mark.parametrize("args, needle", [
    (["backend=warp", "backend.devices=2"], "the warp backend does not shard one simulation"),
    (["backend=jax", "backend.devices={many}"], "XLA_FLAGS=--xla_force_host_platform_device_count={many}"),
    (["backend=jax", "backend.devices=0"], "must be a whole number >= 1"),
    (["task=inverse", "backend.devices=2"], "applies to task=simulate"),
], ids=["warp", "more-than-exist", "zero", "other-task"])
def test_bad_devices_is_one_line(tmp_path, capsys, args, needle):
    import jax

    many = len(jax.devices()) + 1
    run_dir = tmp_path / "run"
    code = main([a.format(many=many) for a in args] + ["steps=5", f"hydra.run.dir={run_dir}"])
    lines = [l for l in capsys.readouterr().err.splitlines() if l.strip()]
    assert code == EXIT_CONFIG, lines
    assert len(lines) == 1 and lines[0].startswith("mpmlab: error: ") and needle.format(many=many) in lines[0], lines
    assert not (run_dir / "config.yaml").exists()           # refused before anything is written


def test_python_api_refusals():
    import jax

    from mpmlab.simulator import build_stepper
    from mpmlab.testing import law_scene

    scene = law_scene(["fixed_corotated"], 2)
    with pytest.raises(ConfigError, match="does not shard one simulation"):
        build_stepper(scene, "warp", "pic", devices=2)
    with pytest.raises(ConfigError, match=f"JAX sees {len(jax.devices())}"):
        build_stepper(scene, "jax", "pic", devices=len(jax.devices()) + 1)
    assert type(build_stepper(scene, "jax", "pic", devices=1)).__name__ == "JaxStepper"   # today's stepper
