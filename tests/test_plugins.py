"""Plugins through the real entry-point path: the example package in examples/ is pip-installed into a
temporary directory (``pip install --target``, nothing changes in this environment), put on PYTHONPATH
of a fresh ``mpmlab`` process, and its law and configs are used from the command line."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import mpmlab
from mpmlab import capabilities

REPO = Path(__file__).resolve().parents[1]
EXAMPLE = REPO / "examples" / "mpmlab-example-plugin"


@pytest.fixture(scope="module")
def plugin_path(tmp_path_factory):
    """The example plugin installed with pip into a temporary target directory."""
    import shutil

    target = tmp_path_factory.mktemp("site")
    build = tmp_path_factory.mktemp("build")
    src = build / EXAMPLE.name  # build a copy: setuptools writes build/ and *.egg-info next to the sources
    shutil.copytree(EXAMPLE, src, ignore=shutil.ignore_patterns("build", "*.egg-info", "__pycache__"))
    proc = subprocess.run(
        [sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--no-build-isolation",
         "--no-cache-dir", "--target", str(target), str(src)],
        capture_output=True, text=True, timeout=300, cwd=build,
        env=dict(os.environ, PIP_DISABLE_PIP_VERSION_CHECK="1"),
    )
    assert proc.returncode == 0, proc.stderr
    assert any(p.name.startswith("mpmlab_example_plugin") and p.suffix == ".dist-info" for p in target.iterdir())
    return target


def with_plugin(target: Path) -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(target)] + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
    env.pop("MPMLAB_DEBUG", None)
    return env


def python(code: str, env: dict, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], env=env, cwd=cwd, capture_output=True, text=True, timeout=300)


def test_entry_points_register_law_and_configs(plugin_path, tmp_path):
    code = (
        "import json, mpmlab\n"
        "from hydra_plugins.mpmlab_searchpath import plugin_config_paths\n"
        "from mpmlab.core import registry\n"
        "law = registry.laws.get('neo_hookean')\n"
        "print(json.dumps({'laws': registry.laws.names(), 'prov': registry.laws.provenance('neo_hookean'),\n"
        "                  'impl': sorted(law.implementations), 'paths': plugin_config_paths()}))\n"
    )
    proc = python(code, with_plugin(plugin_path), tmp_path)
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert "neo_hookean" in out["laws"] and out["prov"] == "mpmlab-example-plugin 0.1.0"
    assert out["impl"] == ["jax", "warp"]
    assert ["mpmlab-plugin:mpmlab_example_plugin", "pkg://mpmlab_example_plugin.conf"] in out["paths"]


def test_search_path_plugin_makes_configs_selectable(plugin_path, tmp_path):
    env = with_plugin(plugin_path)
    info = subprocess.run([sys.executable, "-m", "mpmlab", "--info", "searchpath"], env=env, cwd=tmp_path,
                          capture_output=True, text=True, timeout=120)
    assert info.returncode == 0 and "mpmlab-plugin:mpmlab_example_plugin" in info.stdout
    helptext = subprocess.run([sys.executable, "-m", "mpmlab", "--help"], env=env, cwd=tmp_path,
                              capture_output=True, text=True, timeout=120).stdout
    assert "neo_hookean_rubber" in helptext and "rubber_ball_bounce" in helptext


def test_plugin_law_runs_from_the_cli(plugin_path, tmp_path):
    from mpmlab.io.h5 import read_trajectory

    run_dir = tmp_path / "run"
    proc = subprocess.run([sys.executable, "-m", "mpmlab", "material=neo_hookean_rubber", "steps=20", "frame_every=10",
                           f"hydra.run.dir={run_dir}"], env=with_plugin(plugin_path), cwd=tmp_path,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    s = json.loads((run_dir / "summary.json").read_text())
    assert s["laws"] == ["neo_hookean"] and s["status"] == "ok"
    traj = read_trajectory(run_dir / "trajectory.h5")
    assert traj.materials[0]["law"] == "neo_hookean"
    assert traj.materials[0]["provenance"] == "mpmlab-example-plugin 0.1.0"
    assert (run_dir / "recording.rrd").is_file()


@pytest.mark.parametrize("backend", ["jax", "warp"])
def test_plugin_transfer_runs_from_the_cli(plugin_path, tmp_path, backend):
    """The plugin's RPIC through its entry point and its conf/transfer/rpic.yaml, on each backend."""
    from mpmlab.io.h5 import read_trajectory

    run_dir = tmp_path / "run"
    # the plugin's 2D scene in fp64: the kernels the in-process kit (test_plugin_transfer.py) compiled
    proc = subprocess.run([sys.executable, "-m", "mpmlab", "transfer=rpic", f"backend={backend}", "scene=spinning_block",
                           "precision=fp64", "steps=20",
                           "frame_every=10", "output.recording=false", f"hydra.run.dir={run_dir}"],
                          env=with_plugin(plugin_path), cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert json.loads((run_dir / "summary.json").read_text())["status"] == "ok"
    traj = read_trajectory(run_dir / "trajectory.h5")
    assert traj.meta["transfer"] == "rpic" and "C" in traj.fields
    C = traj.fields["C"][-1]
    assert np.abs(C).max() > 1e-3 and np.abs(C + np.swapaxes(C, 1, 2)).max() < 1e-12   # RPIC's C: skew


@pytest.mark.parametrize("backend", ["jax", "warp"])
def test_plugin_state_law_and_boundary_run_from_the_cli(plugin_path, tmp_path, backend):
    """The plugin's hardening sand (a state field q of its own) on its conveyor belt (a plugin boundary),
    from the CLI on each backend: q is stored in trajectory.h5 and colours the recording."""
    from mpmlab.io.h5 import read_trajectory

    run_dir = tmp_path / "run"
    proc = subprocess.run([sys.executable, "-m", "mpmlab", "scene=conveyor_sand", f"backend={backend}", "steps=60",
                           "frame_every=20", "output.color_by=q", f"hydra.run.dir={run_dir}"],
                          env=with_plugin(plugin_path), cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    s = json.loads((run_dir / "summary.json").read_text())
    assert s["laws"] == ["dp_hardening"] and s["status"] == "ok"
    traj = read_trajectory(run_dir / "trajectory.h5")
    assert "q" in traj.fields and np.all(np.isfinite(traj.fields["q"]))
    assert traj.v[-1][:, 0].mean() > 0.01          # the belt drags the sand along +x
    assert (run_dir / "recording.rrd").is_file()


def test_conformance_kit_passes_on_the_plugin_laws(plugin_path, tmp_path):
    """``mpmlab.testing.check_law`` on the installed plugin's three laws (dp_hardening: a state field q
    of its own), with their own test_params: the
    reference, rest state, equivariance, JAX = Warp trajectories and gradients, 2D, APIC, both backends.
    JAX gradients on ``mlp_elastic`` (its shared weights are the new path), Warp gradients on both:
    neo_hookean's JAX gradient would add one more 10-15 s JAX compile."""
    code = (
        "import json\n"
        "from mpmlab.testing import check_law\n"
        "r = [check_law('neo_hookean', gradients=('warp',)), check_law('mlp_elastic'),\n"
        "     check_law('dp_hardening', gradients=('warp',))]\n"
        "print(json.dumps(r))\n"
    )
    proc = python(code, with_plugin(plugin_path), tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    neo, mlp, dph = json.loads(proc.stdout.strip().splitlines()[-1])
    for r in (neo, mlp, dph):
        assert r["failures"] == []
        assert {"reference[jax,2d]", "reference[warp,2d]", "rest_state[2d]", "equivariance[2d]",
                "backends_agree[apic,2d]", "gradients[warp,apic,2d]"} <= set(r["checks"]), r["checks"].keys()
        assert r["checks"]["backends_agree[apic,2d]"]["moved"] > 1e-3
    assert "gradients[jax,apic,2d]" in mlp["checks"]
    for b in ("jax", "warp"):
        assert set(mlp["checks"][f"gradients[{b},apic,2d]"]) == {"x", "v", "law", "law_weights"}


def test_without_the_plugin_its_names_are_unknown(tmp_path):
    """Control: the same names fail cleanly where the plugin is not installed."""
    from mpmlab.cli import EXIT_CONFIG, main

    if "neo_hookean" in mpmlab.registry.laws.names():
        pytest.skip("the example plugin is installed in this environment")
    assert main(["material=neo_hookean_rubber", f"hydra.run.dir={tmp_path / 'r'}"]) == EXIT_CONFIG
    assert main(["material.law=neo_hookean", f"hydra.run.dir={tmp_path / 'r'}"]) == EXIT_CONFIG


def test_hydra_discovers_the_search_path_plugin():
    from hydra.core.plugins import Plugins
    from hydra.plugins.search_path_plugin import SearchPathPlugin

    names = [c.__module__ for c in Plugins.instance().discover(SearchPathPlugin)]
    assert "hydra_plugins.mpmlab_searchpath" in names


def test_capability_matrix_is_generated_and_readme_is_current():
    table = capabilities.markdown(builtin_only=True)
    for law in ("fixed_corotated", "hencky_drucker_prager", "hencky_von_mises", "weakly_compressible",
                "newtonian_fluid", "drucker_prager_jaumann"):
        assert f"`{law}`" in table
    rows = capabilities.capabilities()
    assert {(r["backend"]) for r in rows} >= {"jax", "warp"}
    assert {r["transfer"] for r in rows} >= {"pic", "flip", "apic", "mls", "tpic"}
    assert capabilities.readme_table(REPO / "README.md") == table, \
        "README capability matrix is stale: run `python -m mpmlab.capabilities --update README.md`"
