"""An inverse problem solved in the reduced space, timed beside the same fit through the full-order model
(issue 16, item 7) -> ``benchmarks/rom.md`` (section ``rom-inverse``) and ``benchmarks/results/rom/inverse_<tag>_g<g>_E<factor>.json``.

    python benchmarks/rom_inverse.py --tag beam_tiny_l3_lf1000_s3          # the beam's best recipe (trains it if needed)
    python benchmarks/rom_inverse.py --factor 1.0                          # data at the nominal E: the reduced fit's bias
    python benchmarks/rom_inverse.py --report                              # only rewrite the table

The problem: the 2D beam (``rom_beam_2d``, `tiny`) at a test gravity (g = 3 m/s^2, not a training run)
with a stiffer material than the networks were trained on (E_true = 1.2 x 50 kPa); the positions of 50
of its points every 20 steps over the 0.2 s run, from the full-order model (JAX, PIC, fp64), are the
data. Both fits start from the nominal E = 50 kPa and run the same Levenberg-Marquardt
(``mpmlab.inverse.lm``, forward-mode Jacobians) on the same ``mpmlab.inverse.Fit``: one through the
``ReducedStepper`` (Lagrangian quadrature, linear projection, every point a sample; its ``observe``
runs the reduced rollout), one through the full-order stepper. The reduced fit cannot reach zero
misfit (its manifold is an approximation): its recovered E carries the ROM's model error, which the
table states beside the full-order fit's.
"""
from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

from _harness import RESULTS, ROOT, log, machine_info, md_table, parser, write_readme_section

MD = Path(__file__).resolve().parent / "rom.md"
RES = RESULTS / "rom"

#: the training recipes benchmarks/rom.py is run with when a tag's weights are missing
RECIPES = {"beam_tiny_l3_lf1000_s3": ["--study", "beam_2d", "--resolution", "tiny", "--latent", "3", "--lambda-F", "1000",
                                      "--batch", "2", "--schedule", "[[3e-3,150],[1e-3,100],[1e-4,50]]",
                                      "--samples", "all", "--quadratures", "lagrangian", "--projections", "linear"]}


def weights_of(tag: str) -> Path:
    path = RES / tag / "train" / "rom_weights.safetensors"
    if not path.exists():
        if tag not in RECIPES:
            raise SystemExit(f"no weights for tag {tag} ({path}); train them with benchmarks/rom.py --tag {tag} first")
        log(f"training {tag} (benchmarks/rom.py)")
        rc = subprocess.run([sys.executable, str(Path(__file__).with_name("rom.py")), *RECIPES[tag], "--tag", tag],
                            cwd=ROOT).returncode
        if rc != 0 or not path.exists():
            raise SystemExit(f"benchmarks/rom.py --tag {tag} failed (exit {rc})")
    return path


def run(a) -> dict:
    import jax

    jax.config.update("jax_enable_x64", True)
    import numpy as np

    from mpmlab.build import build_scene
    from mpmlab.config import compose
    from mpmlab.inverse.fit import Fit
    from mpmlab.inverse.lm import LevenbergMarquardt
    from mpmlab.inverse.parameters import FitParameter
    from mpmlab.observations import Lagrangian, ObservationSchedule
    from mpmlab.rom import networks as N
    from mpmlab.rom.stepper import ReducedStepper
    from mpmlab.simulator import build_stepper

    w = N.load(weights_of(a.tag))
    over = ["scene=rom_beam_2d", f"scene.resolution={a.resolution}", f"scene.gravity=[0.0,{-a.g}]"]
    cfg = compose(over)
    scene, n_steps = build_scene(cfg), int(cfg.scene.steps)
    E0 = float(scene.bodies[0].params["E"])
    E_true = a.factor * E0
    truth_scene = build_scene(compose(over + [f"material.params.E={E_true}"]))
    steps = tuple(range(a.every, n_steps + 1, a.every))
    obs = Lagrangian(quantity="x", particles=a.points)
    ref_stepper = build_stepper(truth_scene, "jax", "pic", "fp64")
    reference = np.asarray(ref_stepper.observe(ref_stepper.controls(), obs, steps))
    fom = build_stepper(scene, "jax", "pic", "fp64")
    out = {"problem": {"scene": "rom_beam_2d", "resolution": a.resolution, "g": a.g, "E_nominal": E0, "E_true": E_true,
                       "points": a.points, "observed_steps": len(steps), "every": a.every, "steps": n_steps,
                       "weights": a.tag, "latent": w.spec.latent, "tangent": a.tangent},
           "fits": []}
    models = {"reduced": ReducedStepper(fom, w, samples=fom.particles.count, quadrature="lagrangian",
                                        projection="linear", tangent=a.tangent),
              "full-order": fom}
    for name, st in models.items():
        p = FitParameter(name="E", target="law", param="E", init=E0, truth=E_true, transform="exp").bind(scene, st, ["walls"])
        fit = Fit(st, scene, [p], obs, ObservationSchedule(steps=steps), reference=reference)
        t0 = time.perf_counter()
        raw = fit.run(a.iterations, LevenbergMarquardt())
        wall = time.perf_counter() - t0
        rep = fit.report(raw)["E"]
        times = [h["time_s"] for h in fit.history if "time_s" in h]
        out["fits"].append({"model": name, "E": rep["recovered"], "relative_error": rep["relative_error"],
                            "iterations": fit.epoch, "initial_loss": fit.history[0]["loss"],
                            "final_loss": fit.history[-1]["loss"], "wall_s": wall,
                            "s_per_iteration_after_first": (float(np.mean(np.diff(times))) if len(times) > 2 else None),
                            "stop": fit.lm_stop})
        log(f"{name}: E = {rep['recovered']:.6g} (truth {E_true:.6g}, error {rep['relative_error']:.2%}), "
            f"{fit.epoch} iterations, {wall:.1f} s")
    out["machine"] = machine_info(load=True)
    RES.mkdir(parents=True, exist_ok=True)
    (RES / f"inverse_{a.tag}_g{a.g:g}_E{a.factor:g}{'' if a.tangent == 'next' else '_current'}.json").write_text(json.dumps(out, indent=1))
    return out


def report() -> None:
    rows = []
    for f in sorted(RES.glob("inverse_*.json")) if RES.exists() else []:
        r = json.loads(f.read_text())
        pr = r["problem"]
        for x in r["fits"]:
            spi = x["s_per_iteration_after_first"]
            model = x["model"] + (f", tangent {pr.get('tangent', 'current')}" if x["model"] == "reduced" else "")
            rows.append([pr["weights"], f"g {pr['g']}, E_true {pr['E_true'] / 1e3:.0f} kPa, {pr['points']} points x "
                         f"{pr['observed_steps']} times", model, f"{x['E'] / 1e3:.3f}",
                         f"{100 * x['relative_error']:.2f}", x["iterations"], f"{x['initial_loss']:.3g} -> {x['final_loss']:.3g}",
                         f"{x['wall_s']:.1f}", "–" if spi is None else f"{spi:.2f}"])
    body = ["The beam's Young's modulus recovered from full-order observations by the same Levenberg-Marquardt fit "
            "through the reduced model and through the full-order model (`benchmarks/rom_inverse.py`; problem in its "
            "docstring). Wall time includes compilation.", "",
            *md_table(["weights", "problem", "model", "E [kPa]", "error %", "iterations", "loss", "wall s",
                       "s / iteration"], rows), ""]
    write_readme_section(MD, "rom-inverse", "An inverse problem in the reduced space", "\n".join(body))
    log(f"wrote {MD}")


def main():
    ap = parser(__doc__.splitlines()[0])
    ap.add_argument("--tag", default="beam_tiny_l3_lf1000_s3", help="the ROM weights (benchmarks/rom.py --tag)")
    ap.add_argument("--resolution", default="tiny")
    ap.add_argument("--g", type=float, default=3.0, help="gravity of the observed run [m/s^2] (a test value)")
    ap.add_argument("--factor", type=float, default=1.2, help="E_true / E_nominal")
    ap.add_argument("--points", type=int, default=50)
    ap.add_argument("--every", type=int, default=20, help="observe every this many steps")
    ap.add_argument("--iterations", type=int, default=15)
    ap.add_argument("--report", action="store_true")
    ap.add_argument("--tangent", default="next", choices=("next", "current"),
                    help="the reduced model's velocity-fit tangent (mpmlab.rom.stepper)")
    a = ap.parse_args()
    if not a.report:
        run(a)
    report()


if __name__ == "__main__":
    main()
