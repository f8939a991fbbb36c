"""The ``phase_change`` law (a per-particle, time-dependent switch between two laws: NCLaw Fig. 4b's
melting) and the melting evaluation case."""
from __future__ import annotations

import pickle

import numpy as np
import pytest

from mpmlab import testing
from mpmlab.core.errors import ConfigError
from mpmlab.laws.phase_change import Law

PAIR = {"before": {"law": "hencky_von_mises"}, "after": {"law": "fixed_corotated"}}


def law(**kw):
    return Law.from_config({**PAIR, **kw}, "test")


def test_pair_declares_both_laws_parameters_state_and_round_trips():
    a = law()
    assert type(a).__name__ == "Law_hencky_von_mises_to_fixed_corotated"
    assert a.param_names() == ("before_E", "before_nu", "before_yield_stress", "after_E", "after_nu", "switch_time")
    assert a.state_fields == ("F", "eps_zz", "clock")   # hencky_von_mises carries eps_zz (2D plane strain)
    assert a.plastic and a.symmetric_stress
    b = pickle.loads(pickle.dumps(a))
    assert b == a and hash(b) == hash(a) and type(b) is type(a)
    assert law(switch_axis=1, switch_from=0.1, switch_until=0.2).code_key() == a.code_key()   # no recompile
    assert law(after={"law": "hencky_drucker_prager"}) != a


def test_conformance_kit():
    """Reference vs JAX and Warp (the kit's clocks straddle the switch time: both branches), rest
    state (the clock advances by exactly dt), equivariance, JAX = Warp trajectories, FD gradients."""
    report = testing.check_law(law(), dims=(2,), transfers=("mls",))
    assert not report["failures"]


@pytest.mark.parametrize("bad, msg", [
    ({"after": {"law": "fixed_corotated"}}, "needs option 'before'"),
    ({**PAIR, "switch_at": 1.0}, "has no option(s) switch_at"),
    ({**PAIR, "before": {"law": "phase_change"}}, "cannot switch to another one"),
    ({**PAIR, "before": {"law": "hencky_von_mises", "params": {"E": 1.0}}}, "unknown key(s) params"),
    ({**PAIR, "switch_axis": 3}, "switch_axis = 3"),
    ({**PAIR, "switch_axis": 1, "switch_from": 0.5, "switch_until": 0.1}, "0 <= switch_from <= switch_until"),
    ({**PAIR, "before": {"law": "no_such_law"}}, "no_such_law"),
])
def test_bad_configuration_is_one_clear_line(bad, msg):
    with pytest.raises(Exception) as e:
        Law.from_config(bad, "material")
    assert msg in str(e.value) and "\n" not in str(e.value)


def _scene(material_overrides=(), res="tiny"):
    from mpmlab.config import build_scene, compose

    return build_scene(compose(["scene=nclaw_melting", f"scene.resolution={res}", "precision=fp64",
                                *material_overrides]))


def test_switch_times_rise_with_the_initial_height_over_both_bodies():
    scene = _scene()
    P = scene.particles()
    assert len(P.groups) == 1                                   # ice cream and chocolate: one material
    g = P.groups[0]
    t = g.params[:, g.law.param_names().index("switch_time")]
    y = P.x[g.start:g.stop, 1]
    assert t.min() == pytest.approx(0.25) and t.max() == pytest.approx(0.75)
    assert t[np.argmin(y)] == pytest.approx(0.25) and t[np.argmax(y)] == pytest.approx(0.75)
    np.testing.assert_allclose(t, 0.25 + 0.5 * (y - y.min()) / (y.max() - y.min()), rtol=0, atol=1e-15)


def _run(backend, overrides, steps=40):
    from mpmlab.simulator import build_stepper

    # thrown at the floor with a spin, so the body deforms (and yields) within the 40 steps
    scene = _scene(["scene.bodies.ice_cream.velocity=[0.0,-3.0,0.0]",
                    "scene.bodies.ice_cream.angular_velocity=[0.0,0.0,8.0]", *overrides])
    st = build_stepper(scene, backend, "mls", "fp64")
    return st.rollout(steps=steps, every=steps, fields=("clock",))


SWITCH = ["material.options.switch_from=0.002", "material.options.switch_until=0.016"]   # steps 4-32 of 40


def test_melting_switches_mid_run_on_both_backends_alike():
    """The truth melting scene switched during 40 steps: JAX = Warp (fp64), the clocks at 40 dt, and the
    run differs from one that never switches (the switch acts) and, with the switch after the end,
    equals the PLASTICINE law alone."""
    runs = {b: _run(b, SWITCH) for b in ("jax", "warp")}
    xj, xw = (np.asarray(runs[b].x[-1]) for b in ("jax", "warp"))
    assert np.max(np.abs(xj - xw)) < 1e-11
    assert np.allclose(np.asarray(runs["warp"].fields["clock"][-1]), 40 * 5e-4, rtol=0, atol=1e-15)
    never = _run("warp", ["material.options.switch_from=1.0", "material.options.switch_until=2.0"])
    alone = _run("warp", ["material=plasticine"])
    assert np.max(np.abs(np.asarray(never.x[-1]) - np.asarray(alone.x[-1]))) < 1e-13
    assert np.max(np.abs(np.asarray(never.x[-1]) - xw)) > 1e-6


def test_melting_eval_case_needs_both_materials_weights():
    from mpmlab.nclaw.scenes import eval_cases

    case = {c.name: c for c in eval_cases("plasticine")}["melting"]
    assert case.partners == ("sand",)
    assert case.truth()[0] == "material=plasticine_to_sand"
    got = case.learned("P.safetensors", {"sand": "S.safetensors"})
    assert got[0] == "material=nclaw_plasticine_to_sand"
    assert "material.options.before.options.weights_file=P.safetensors" in got
    assert "material.options.after.options.weights_file=S.safetensors" in got
    assert not any("weights_file" in o for o in case.learned(None))           # ours-init: both untrained
    assert "melting" not in {c.name for c in eval_cases("sand")}
