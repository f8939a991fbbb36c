"""benchmarks/granular.py: its pure functions (observed order, Richardson extrapolation, power-law
exponent) and its checkpoint/restore of a Warp state (a resumed run continues the uninterrupted one)."""
import importlib.util
import math
from pathlib import Path

import numpy as np
import pytest

_PATH = Path(__file__).resolve().parents[1] / "benchmarks" / "granular.py"


def _module():
    spec = importlib.util.spec_from_file_location("granular_benchmark", _PATH)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


G = _module()


def test_richardson_recovers_order_and_limit():
    f = lambda h: 0.4 + 3.0 * h ** 1.5
    hs = [0.01, 0.005, 0.0025]
    r = G.richardson(hs, [f(h) for h in hs])
    assert r["order"] == pytest.approx(1.5, rel=1e-9)
    assert r["extrapolated"] == pytest.approx(0.4, rel=1e-9)
    # order of the input does not matter; only the three finest are used
    r2 = G.richardson([0.02] + hs[::-1], [f(0.02) + 1.0] + [f(h) for h in hs[::-1]])
    assert r2["order"] == pytest.approx(1.5, rel=1e-9)


def test_richardson_oscillating_has_no_order():
    r = G.richardson([0.01, 0.005, 0.0025], [1.0, 1.1, 1.05])
    assert r["order"] is None and r["extrapolated"] is None
    assert r["change_last"] == pytest.approx(-0.05)


def test_front_at_thickness_interpolates_and_ignores_a_thin_toe():
    """A wedge deposit 0.1 m high at the wall falling linearly to 0 at 0.5 m, plus a 5 mm toe to 0.7 m:
    the 3 cm front is at 0.35 m (linear between bins), the toe only moves fronts thinner than itself."""
    d = np.arange(0.0025, 0.7, 0.005)
    h = np.where(d < 0.5, 0.1 * (1 - d / 0.5), 0.005)
    prof = {"distance": d.tolist(), "height": h.tolist()}
    assert G.front_at_thickness(prof, 0.03) == pytest.approx(0.35, abs=1e-9)
    assert G.front_at_thickness(prof, 0.004) == pytest.approx(d[-1], abs=1e-12)   # the toe counts below 5 mm
    assert G.front_at_thickness(prof, 0.2) is None                                 # thicker than the deposit


def test_power_fit():
    a = [0.5, 1.0, 2.0, 3.0]
    assert G.power_fit(a, [2.0 * x ** 0.7 for x in a]) == pytest.approx(0.7)
    assert G.power_fit([1.0], [1.0]) is None
    assert math.isclose(G.power_fit([0.5, 1.0], [2.05, 3.97]), math.log(3.97 / 2.05) / math.log(2))


def test_deposit_angle_of_a_linear_slope():
    d = np.linspace(0.005, 0.3, 60)
    r = {"profile": {"distance": list(d), "height": list(0.1 - d / 3)}, "H_wall": 0.1}
    assert G.deposit_angle(r) == pytest.approx(math.degrees(math.atan(1 / 3)), rel=1e-6)


def test_checkpoint_restore_continues_the_run(tmp_path):
    pytest.importorskip("warp")
    c = G.cfg(setup="bui", dx=0.02, ppc=1)
    _, st, mon = G.build(c)
    s0 = st.init()
    straight = st.to_numpy(st._advance(s0, 60))
    half = st.to_numpy(st._advance(st.init(), 30))
    mon.update(30 * st.dt, half["x"], half["v"])
    G.save_checkpoint(tmp_path / "ck.npz", half, 30, mon, 1.0)
    _, st2, mon2 = G.build(c)
    d, step, wall = G.load_checkpoint(tmp_path / "ck.npz", mon2)
    assert step == 30 and wall == 1.0 and mon2.fronts == mon.fronts and mon2.settled_index is None
    s = G.restore_warp(st2, d)
    again = st2.to_numpy(s)
    for k in ("x", "v", "sigma", "eps_p", "J"):
        np.testing.assert_array_equal(again[k], half[k])
    resumed = st2.to_numpy(st2._advance(s, 30))
    assert resumed["t"] == pytest.approx(straight["t"])
    # the same run up to the summation order of P2G (particles re-sorted after the restore); fp32
    np.testing.assert_allclose(resumed["x"], straight["x"], atol=1e-5)
    np.testing.assert_allclose(resumed["sigma"], straight["sigma"], atol=1e-2 * np.abs(straight["sigma"]).max())


def test_save_keeps_runs_another_invocation_added(tmp_path, monkeypatch):
    """Two invocations (two parts) write one results file: each save merges over what the file holds,
    so neither loses the other's runs, and the saver's own entries win."""
    monkeypatch.setattr(G, "RESULTS", tmp_path / "granular.json")
    first, second = {"a": {"L_f": 1.0}}, {"b": {"L_f": 2.0}}
    G.save(first)
    G.save(second)                      # loaded before "a" existed
    assert G.load() == {"a": {"L_f": 1.0}, "b": {"L_f": 2.0}} and set(second) == {"a", "b"}
    first["a"] = {"L_f": 3.0}
    G.save(first)
    assert G.load()["a"] == {"L_f": 3.0} and G.load()["b"] == {"L_f": 2.0}
    assert not list(tmp_path.glob("*.tmp"))


def test_dt_scale_scales_only_the_step():
    """Part flip_dt: dt_scale halves dt (and the frame stride keeps 10 ms frames); runs without it keep
    their keys, so the convergence part's runs are reused; a dt_scale run is its own table row."""
    base = G.cfg(setup="bui", dx=0.005)
    half = G.cfg(setup="bui", dx=0.005, dt_scale=0.5)
    ob, oh = G.overrides(base), G.overrides(half)
    dt = lambda ov: float(next(o for o in ov if o.startswith("scene.dt="))[9:])  # noqa: E731
    assert dt(oh) == pytest.approx(0.5 * dt(ob))
    assert [o for o in ob if not o.startswith(("scene.dt=", "scene.frame_every=", "scene.steps="))] == \
        [o for o in oh if not o.startswith(("scene.dt=", "scene.frame_every=", "scene.steps="))]
    assert "dt_scale" not in G.key(base) and G.key(base) in {G.key(c) for c in G.configs("flip_dt", False, 0.0025)}
    res = {G.key(c): {"config": c} for c in (base, half)}
    assert G._rows(res, setup="bui", dx=0.005) == [res[G.key(base)]]
    assert G._rows(res, setup="bui", dx=0.005, dt_scale=0.5) == [res[G.key(half)]]
