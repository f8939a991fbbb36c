"""Validation against analytic references (verification note cases 1a/1c, 3a, 3c), small and fast.

The full-size numbers come from ``benchmarks/validation.py`` (table in ``benchmarks/validation.md``);
these tests run reduced versions of the same scenes on both backends:

* vibrating bar, 1D strip, 50 cells, APIC, fp64, 1.5 periods: period within the verification
  note's 1 % bar (the benchmark's 3-period runs give +0.63 % on both backends);
* hydrostatic column at CB-Geo's coarsest dx = 10 mm on a 4-cell-wide slice (roller sides make the
  column one-dimensional, so the width does not change the answer), PIC, fp64: base stress error at
  most CB-Geo's 4.8 % at that dx;
* dam break at dx = 10 mm (10 cells over H0, 2x2 ppc), APIC, fp32, ``newtonian_fluid`` with its
  default tension cut-off p >= 0, in a 1.6 m tank, to t = 0.3 s, heights y = 2dx ... 0.4 H0: the
  surface position within 5 % of the Ritter wave length 2 sqrt(g H0) t at every 0.01 s frame in
  [0.2, 0.3] s (metric C of benchmarks/validation.md; measured <= 3.1 %). The verification note's
  relative metric e = (x_sim - x_R)/(x_R - L0) is NOT met (measured 9 % at y = 2dx, 56 % at 0.4 H0
  where x_R - L0 -> 0.1 sqrt(g H0) t); it is only bounded loosely here as a regression check. This
  is a regression check at one coarse resolution, not a convergence claim: benchmarks/validation.md
  has the 8 / 4 mm numbers on both backends and explains why the note's 5 % bar is not met.

Runtime: about 25-30 s on 2 shared cores once the Warp kernels are in Warp's kernel cache; a cold
cache adds Warp's one-time CPU kernel compilation (tens of seconds per kernel specialisation).
"""
import numpy as np
import pytest

from mpmlab.scenes import validation as V

BACKENDS = ("jax", "warp")


def test_references():
    ref = V.bar_reference()
    assert ref["period"] == pytest.approx(10.0, rel=1e-12)
    assert ref["v_com_amplitude"] == pytest.approx(0.2 / np.pi, rel=1e-12)
    # verification-note checkpoints (g = 9.8)
    assert V.ritter_front(0.02, 0.3) == pytest.approx(1.1955, abs=1e-4)
    assert V.ritter_front(0.02, 0.4) == pytest.approx(1.2607, abs=1e-4)
    assert V.ritter_front(4.0 / 9.0 * 0.1, 0.37) == pytest.approx(1.0, abs=1e-12)   # dam-site depth 4/9 H0
    assert V.hydrostatic_base_stress() == pytest.approx(-1765.8, abs=0.05)


def test_measurements_on_synthetic_data():
    t = np.linspace(0, 30, 3001)
    m = V.measure_period(t, 0.3 * np.cos(2 * np.pi * t / 7.3))
    assert m["period"] == pytest.approx(7.3, rel=1e-4)
    # depth of a uniform layer 0.05 deep sampled like the dam break, front at its end
    dx = 0.01
    xs, ys = np.meshgrid(0.1 + (np.arange(100) + 0.5) * dx / 2, (np.arange(10) + 0.5) * dx / 2, indexing="ij")
    x = np.stack([xs.ravel(), ys.ravel()], 1)
    area = np.full(len(x), (dx / 2) ** 2)
    xi, h = V.column_depth(x, area, dx, 1.0)
    assert np.sum(h) * dx == pytest.approx(area.sum(), rel=1e-12)
    assert np.allclose(h[12:55], 0.05)
    assert V.measure_front(x, area, dx, [0.025], 1.0)[0] == pytest.approx(0.6, abs=dx)
    # base-stress fit of an exact line
    y = np.linspace(0.001, 0.099, 50)
    assert V.fit_base_stress(y, -1765.8 + 17658 * y)["base_stress"] == pytest.approx(-1765.8)


@pytest.mark.parametrize("backend", BACKENDS)
def test_vibrating_bar_period(backend):
    r = V.run_vibrating_bar(backend=backend, transfer="apic", precision="fp64", periods=1.45,
                            frames_per_period=50, cells=50, lateral="strip")
    assert r["cycles"] >= 0.99          # three zero crossings measured
    assert abs(r["period_error"]) <= 0.01, r["period"]
    assert r["amplitude_ratio"] > 0.98   # APIC keeps the mode


@pytest.mark.parametrize("backend", BACKENDS)
def test_hydrostatic_column_base_stress(backend):
    r = V.run_hydrostatic_column(backend=backend, transfer="pic", precision="fp64", settle_periods=40.0,
                                 dx=0.01, width=0.04, law="newtonian_fluid")
    cbgeo = abs(V.CBGEO_HYDROSTATIC[0.01] / V.hydrostatic_base_stress() - 1.0)   # 4.8 %
    assert abs(r["error"]) <= cbgeo, r["base_stress"]
    assert r["residual_speed"] < 0.05    # the column has come to rest


@pytest.mark.parametrize("backend", BACKENDS)
def test_dam_break_front(backend):
    dx = 0.01
    r = V.run_dam_break(backend=backend, transfer="apic", precision="fp32", t_end=0.3, window=(0.2, 0.3),
                        dx=dx, length=1.6)
    assert r["scene"].bodies[0].params["min_pressure"] == 0.0          # the library default: no tension
    ew = r["error_wave"]
    assert np.all(np.isfinite(ew)) and ew.shape[0] >= 10
    assert r["max_abs_error_wave"] <= 0.05, ew                        # metric C (measured 3.1 %)
    assert r["max_abs_error_low"] <= 0.12, r["error"]                 # metric B, y = 2dx (measured 9.3 %)
    # the one-cell tip (not scored) lags Ritter's 2 sqrt(g H0) but has clearly left the dam site
    assert 1.2 < r["tip"][-1] < 1.0 + 2 * np.sqrt(9.8 * 0.1) * 0.3
