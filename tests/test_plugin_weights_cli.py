"""The shared-weight demonstrator from the command line (issue #13 item 5), through the installed example
plugin's entry points: a fixed corotated trajectory (experiment=mlp_elastic_data), the MLP law's weights
fitted to it by task=inverse on each backend (experiment=mlp_elastic_fit; the fitted weights go to a
safetensors file) and that file read back as the law's ``weights_file`` option by a plain run."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np

from .test_plugins import plugin_path, with_plugin  # noqa: F401  (the module-scoped install fixture)


def mpmlab_run(args, env, cwd):
    proc = subprocess.run([sys.executable, "-m", "mpmlab", *args], env=env, cwd=cwd, capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    return proc


def test_weights_fitted_from_the_cli_on_both_backends_and_reused(plugin_path, tmp_path):  # noqa: F811
    from mpmlab.io.h5 import read_trajectory

    env = with_plugin(plugin_path)
    mpmlab_run(["experiment=mlp_elastic_data", f"hydra.run.dir={tmp_path / 'data'}"], env, tmp_path)
    data = tmp_path / "data" / "trajectory.h5"
    fitted = {}
    for backend in ("jax", "warp"):
        run = tmp_path / f"fit_{backend}"
        mpmlab_run(["experiment=mlp_elastic_fit", f"input={data}", f"backend={backend}", "task.epochs=6",
                    "output.recording=false", "output.plots=false", f"hydra.run.dir={run}"], env, tmp_path)
        s = json.loads((run / "summary.json").read_text())
        assert s["status"] == "ok" and s["final_loss"] < 0.5 * s["initial_loss"], s["history"]
        fitted[backend] = s
        assert s["weight_files"] == {"mlp_elastic": "law_weights_mlp_elastic.safetensors"}
    # both backends took the same steps
    lj = [h["loss"] for h in fitted["jax"]["history"]]
    lw = [h["loss"] for h in fitted["warp"]["history"]]
    np.testing.assert_allclose(lj, lw, rtol=1e-6)
    # the weight file drives the law on the other backend: closer to the data than the initial weights
    weights = tmp_path / "fit_warp" / "law_weights_mlp_elastic.safetensors"
    common = ["scene=spinning_block", "material=mlp_elastic_small", "precision=fp64", "transfer=apic",
              "output.recording=false", "output.plots=false"]
    mpmlab_run(common + [f"hydra.run.dir={tmp_path / 'initial'}"], env, tmp_path)
    mpmlab_run(common + [f"+material.options.weights_file={weights}", f"hydra.run.dir={tmp_path / 'reuse'}"], env,
               tmp_path)
    x = read_trajectory(str(data)).x[-1]
    err = {r: float(np.abs(read_trajectory(str(tmp_path / r / "trajectory.h5")).x[-1] - x).max())
           for r in ("initial", "reuse")}
    assert err["reuse"] < 0.7 * err["initial"], err
