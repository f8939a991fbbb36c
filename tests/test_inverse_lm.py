"""Levenberg-Marquardt fits (mpmlab.inverse.lm) on both backends: basal friction segments are recovered
where Adam is path-dependent, the Jacobians of the two backends agree, resume continues exactly, and
misuse is a ConfigError."""
import numpy as np
import pytest

import mpmlab
from mpmlab.boundaries import FrictionWalls, Walls
from mpmlab.core.errors import ConfigError
from mpmlab.inverse.fit import Fit
from mpmlab.inverse.lm import LevenbergMarquardt
from mpmlab.inverse.parameters import FitParameter
from mpmlab.observations import Lagrangian, ObservationSchedule
from mpmlab.simulator import build_stepper

from .test_inverse import make_fit, optimizer

BACKENDS = ("jax", "warp")
TRUE_MU = [0.2, 0.4]


def slide_fit(backend, init=(0.05, 0.05)):
    """A block sliding right across two floor friction segments (edge at x = 0.5), positions observed."""
    floorless = Walls(default="slip", faces={"y-": "none"}, thickness=2)
    fw = FrictionWalls(face="y-", mu=list(TRUE_MU), along="x", thickness=2)
    body = mpmlab.Body(shape={"kind": "box", "lo": [0.3, 0.1], "hi": [0.5, 0.2]}, material="fixed_corotated",
                       params={"E": 5e4, "nu": 0.3}, density=1000.0, particles_per_cell=4, velocity=[2.0, 0.0])
    scene = mpmlab.Scene(dim=2, dx=0.05, domain=([0.0, 0.0], [1.0, 1.0]), bodies=[body], gravity=[0.0, -9.8],
                         boundaries=[floorless, fw], dt=5e-4, name="slide_lm")
    st = build_stepper(scene, backend, "apic", "fp64")
    p = FitParameter(name="mu", target="boundary", boundary="floor", field="mu", form="array", init=list(init),
                     truth=list(TRUE_MU), transform="softplus").bind(scene, st, ["walls", "floor"])
    return Fit(st, scene, [p], Lagrangian(quantity="x"), ObservationSchedule(steps=tuple(range(40, 401, 40))),
               segment=40)


@pytest.mark.parametrize("backend", BACKENDS)
def test_lm_recovers_friction_segments(backend):
    fit = slide_fit(backend)
    raw = fit.run(20, LevenbergMarquardt())
    mu = fit.report(raw)["mu"]["recovered"]
    assert np.allclose(mu, TRUE_MU, rtol=1e-3), mu
    assert fit.history[-1]["loss"] < 1e-8 * fit.history[0]["loss"]
    assert fit.epoch <= 20 and all(np.isfinite(h["damping"]) for h in fit.history)


def test_lm_jacobians_of_the_backends_agree():
    """JAX forward-mode AD and Warp central differences: the same Jacobian of the residuals (fp64)."""
    out = {}
    for backend in BACKENDS:
        fit = slide_fit(backend)
        fit.make_reference()
        lm = LevenbergMarquardt(fd_step=1e-5)
        layout = fit._flat_layout(lm)
        _, jac = fit._residual_functions(lm, lambda v: {n: v[sl].reshape(sh) for n, sh, sl in layout})
        x = np.log(np.expm1(np.array([0.1, 0.3])))
        r, J, bad = jac(x)
        assert not bad
        out[backend] = (r, J)
    np.testing.assert_allclose(out["jax"][0], out["warp"][0], rtol=0, atol=1e-10)
    Jj, Jw = out["jax"][1], out["warp"][1]
    assert np.all(np.abs(Jj).sum(axis=0) > 0)                      # both segments are seen
    assert np.linalg.norm(Jj - Jw) <= 1e-5 * np.linalg.norm(Jj), np.linalg.norm(Jj - Jw) / np.linalg.norm(Jj)


@pytest.mark.parametrize("backend", ("warp",))   # the LM loop and its checkpoint are backend-independent
def test_lm_resume_continues_exactly(backend, tmp_path):
    ck = tmp_path / "ck.pkl"
    full = slide_fit(backend)
    raw_full = full.run(4, LevenbergMarquardt())
    first = slide_fit(backend)
    first.run(2, LevenbergMarquardt(), checkpoint=ck, checkpoint_every=1)
    second = slide_fit(backend)
    raw = second.run(4, LevenbergMarquardt(), checkpoint=ck, checkpoint_every=1)
    assert second.epoch == 4 and [h["epoch"] for h in second.history] == [0, 1, 2, 3]
    np.testing.assert_allclose(second.report(raw)["mu"]["recovered"], full.report(raw_full)["mu"]["recovered"],
                               rtol=1e-9)


def test_lm_misuse_is_a_config_error(tmp_path):
    with pytest.raises(ConfigError, match="jacobian = 'hessian' unknown"):
        LevenbergMarquardt(jacobian="hessian")
    with pytest.raises(ConfigError, match="must be > 1"):
        LevenbergMarquardt(increase=0.5)
    with pytest.raises(ConfigError, match="forward-mode AD"):
        LevenbergMarquardt(jacobian="forward").jacobian_kind("warp")
    # an MLP field is for gradient optimisers
    fit = make_fit("jax")
    fit.parameters[0].form = "mlp"
    with pytest.raises(ConfigError, match="scalar and array parameters only"):
        fit.run(1, LevenbergMarquardt())
    with pytest.raises(ConfigError, match="exceeds max_parameters"):
        make_fit("jax").run(1, LevenbergMarquardt(max_parameters=0))
    # a checkpoint of another optimiser is not silently reinterpreted
    ck = tmp_path / "ck.pkl"
    make_fit("jax").run(1, *optimizer("jax", 0.1), checkpoint=ck, checkpoint_every=1)
    with pytest.raises(ConfigError, match="written by another optimiser"):
        make_fit("jax").run(2, LevenbergMarquardt(), checkpoint=ck)


def test_inverse_task_runs_levenberg_marquardt(tmp_path):
    """task=inverse with the optimiser chosen on the command line; the summary names it."""
    import json

    from mpmlab.config import compose
    from mpmlab.tasks import RunContext, get_task

    cfg = compose(["task=inverse", "experiment=jaxmpm_velocity_constant", "scene.resolution=tiny", "steps=120",
                   "task.epochs=6", "task.schedule.frames=10", "task.schedule.every=2",
                   "task.supervision=lagrangian_sparse", "task.optimizer.jax._target_=mpmlab.inverse.lm.LevenbergMarquardt",
                   "+task.optimizer.jax.damping=0.1", "output.recording=false"])
    get_task("inverse")(cfg, RunContext(output_dir=tmp_path))
    s = json.loads((tmp_path / "summary.json").read_text())
    assert s["optimizer"] == "mpmlab.inverse.lm.LevenbergMarquardt"
    assert s["relative_error"]["alpha"] < 1e-3, s["recovered"]
    bad = compose(["task=inverse", "experiment=jaxmpm_velocity_constant", "scene.resolution=tiny", "steps=120",
                   "task.schedule.frames=10", "task.optimizer.jax._target_=mpmlab.inverse.lm.LevenbergMarquardt", "+task.optimizer.jax.lr=0.1"])
    with pytest.raises(ConfigError, match="LevenbergMarquardt"):
        get_task("inverse")(bad, RunContext(output_dir=tmp_path / "bad"))


def test_lm_reverse_mode_jacobians_agree_with_forward_mode_and_differences():
    """jacobian: reverse (adapter: jax.jacrev; Warp one backward pass per residual) is the Jacobian that
    forward mode (JAX) and central differences (Warp) give, on a one-step scene of 24 particles."""
    from .test_autodiff_adapter import tiny_fit

    out = {}
    for backend, modes in (("jax", ("forward", "reverse")), ("warp", ("central", "reverse"))):
        fit = tiny_fit(backend)
        layout = fit._flat_layout(LevenbergMarquardt())
        x = np.array([0.8])
        for mode in modes:
            _, jac = fit._residual_functions(LevenbergMarquardt(jacobian=mode, fd_step=1e-6),
                                             lambda v: {n: v[sl].reshape(sh) for n, sh, sl in layout})
            r, J, bad = jac(x)
            assert not bad and J.shape == (r.size, 1) and np.abs(J).sum() > 0
            out[backend, mode] = (r, J)
    np.testing.assert_allclose(out["jax", "reverse"][1], out["jax", "forward"][1], rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(out["warp", "reverse"][1], out["warp", "central"][1], rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(out["warp", "reverse"][1], out["jax", "forward"][1], rtol=1e-9, atol=1e-14)
    np.testing.assert_array_equal(out["warp", "reverse"][0], fit._residual_functions(
        LevenbergMarquardt(jacobian="central"), lambda v: {n: v[sl].reshape(sh) for n, sh, sl in layout})[0](x))
