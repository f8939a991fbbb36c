"""Training a neural constitutive law by teacher forcing (NCLaw, Ma et al. 2023, Sec. 3.4, App. D.2;
``mpmlab.inverse.teacher``): the schedule, gradients against finite differences, the unbiased
segment subset, the kinematics-only reset, NaN gradients located, the particle_state observation. The
tasks from the command line are in ``test_nclaw_tasks.py``.

Small sizes (2 cores): the 2D training scene ``nclaw_square_2d`` (64 particles, 200 steps of 5e-4 s,
fixed corotated ground truth), fp64. Each backend compiles its nclaw step once per segment length, so
the trainings here use a constant period (``start = end``): one length.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

import mpmlab
from mpmlab.boundaries import Walls
from mpmlab.core.errors import ConfigError
from mpmlab.inverse.parameters import FitParameter
from mpmlab.inverse.teacher import TeacherForcedFit, TeacherForcing, chosen_segments
from mpmlab.laws.nclaw import Law, save_weights

NAMES = ["e_W1", "e_W2", "e_W3", "p_W1", "p_W2", "p_W3"]
GROUPS = {"elastic": NAMES[:3], "plastic": NAMES[3:]}
NETS = {"elastic": {"lr": 1.0, "clip": 0.1}, "plastic": {"lr": 0.1, "clip": 0.1}}


# ---- the schedule -------------------------------------------------------------------------------------
def test_period_schedule_and_segments():
    tf = TeacherForcing(steps=1000)
    assert tf.period(0, 300) == 25.0 and tf.period(300, 300) == 200.0       # the release's 25 -> 200
    assert 25.0 < tf.period(150, 300) < 200.0
    assert math.isclose(tf.period(150, 300), 112.5)                         # the cosine's midpoint
    for e in (0, 1, 37, 150, 299, 300):
        segs = tf.segments(e, 300)
        assert len(segs) == math.ceil(1000 / tf.period(e, 300) - 1e-9)
        # a partition of the steps into equal segments (lengths differ by at most one)
        covered = np.concatenate([np.arange(s, s + L) for s, L in segs])
        np.testing.assert_array_equal(covered, np.arange(1000))
        lengths = [L for _, L in segs]
        assert max(lengths) - min(lengths) <= 1
    assert len(tf.segments(0, 300)) == 40 and len(tf.segments(300, 300)) == 5
    with pytest.raises(ConfigError, match="reset"):
        TeacherForcing(steps=10, reset=("x",))
    with pytest.raises(ConfigError, match="segment_fraction"):
        chosen_segments(10, 0.0, 0, 0)
    # seeded draws: the same per (seed, epoch), different between epochs
    a, b = chosen_segments(40, 0.25, 3, 7), chosen_segments(40, 0.25, 3, 7)
    np.testing.assert_array_equal(a, b)
    assert len(a) == 10 and not np.array_equal(a, chosen_segments(40, 0.25, 3, 8))
    np.testing.assert_array_equal(chosen_segments(40, 1.0, 3, 7), np.arange(40))


# ---- a tiny 2D problem --------------------------------------------------------------------------------------
def square_scene(material, params, options=None, velocity=(1.0, -1.5), omega=4.0, dt=5e-4):
    body = mpmlab.Body(shape={"kind": "box", "lo": [0.3, 0.3], "hi": [0.7, 0.7]}, material=material, params=params,
                       density=1000.0, velocity=list(velocity), angular_velocity=omega, particles_per_cell=1,
                       options=options or {})
    return mpmlab.Scene(dim=2, dx=0.05, domain=([0.0, 0.0], [1.0, 1.0]), bodies=[body], gravity=[0.0, -9.8],
                        boundaries=[Walls(default="separate", thickness=3)], dt=dt, name="nclaw_square_2d")


@pytest.fixture(scope="module")
def truth():
    """200 steps of the fixed corotated square (JAX, MLS, fp64): x, v, C, F at every step."""
    st = mpmlab.build_stepper(square_scene("fixed_corotated", {"E": 1e5, "nu": 0.2}), "jax", "mls", "fp64")
    traj = st.rollout(steps=200, every=1, fields=("F", "C"))
    return {"x": traj.x, "v": traj.v, "C": traj.fields["C"], "F": traj.fields["F"]}


def make_fit(backend, truth, steps, epochs, period, options=None, **kw):
    st = mpmlab.build_stepper(square_scene("nclaw", {}, options), backend, "mls", "fp64")
    params = [FitParameter(name=n, target="law_weights", field=n, form="array").bind(st.scene, st, []) for n in NAMES]
    tr = {k: a[:steps + 1] for k, a in truth.items()}
    return TeacherForcedFit(st, st.scene, params, tr, TeacherForcing(steps=steps, start=period, end=period),
                            epochs=epochs, groups=GROUPS, **kw)


def trained_like(dim=2, seed=7, scale=10.0):
    """Weights far from the Xavier start (10x; 30x would be too stiff for dt = 5e-4)."""
    law = Law()
    rng = np.random.default_rng(seed)
    return {k: scale * a * (1.0 + 0.5 * rng.standard_normal(a.shape)) for k, a in law.initial_weights(dim).items()}


_FITS = {}


def fit20(backend, truth):
    """A 20-step teacher-forced fit in 4 segments of 5 steps (one compile per backend for the tests)."""
    if backend not in _FITS:
        _FITS[backend] = make_fit(backend, truth, steps=20, epochs=1, period=5.0)
    return _FITS[backend]


def weights(fit, w):
    raw = {n: fit.ops.asarray(w[n]) for n in NAMES}
    return {n: a.clone().requires_grad_(True) for n, a in raw.items()} if fit.backend == "warp" else raw


@pytest.mark.parametrize("backend", ["jax", "warp"])
def test_loss_gradient_matches_central_differences(backend, truth):
    """d loss / d weights through a teacher-forced 20-step fp64 rollout (4 segments of 5) against
    central differences along a random direction of all 9,600 weights, on each backend."""
    fit = fit20(backend, truth)
    ops = fit.ops
    w0 = trained_like()
    raw = weights(fit, w0)
    val, why, g, info = fit.epoch_loss(raw, 0)
    assert why is None and info["segments"] == 4 and val > 0
    g = g if isinstance(g, dict) else dict(zip(NAMES, g))
    rng = np.random.default_rng(1)
    d = {n: rng.standard_normal(w0[n].shape) for n in NAMES}
    ad = sum(float(np.sum(ops.numpy(g[n]) * d[n])) for n in NAMES)

    def loss_at(h):
        r = {n: ops.asarray(w0[n] + h * d[n]) for n in NAMES}
        return fit.epoch_loss(r, 0, grad=False)[0]
    h = 1e-4
    fd = (loss_at(h) - loss_at(-h)) / (2 * h)
    assert abs(ad) > 0
    assert abs(fd - ad) <= 1e-6 * abs(ad), (fd, ad)


@pytest.mark.parametrize("backend", ["jax", "warp"])
def test_segment_fraction_is_an_unbiased_estimate(backend, truth):
    """fraction 1 = the full loss; a fraction that keeps one of n segments, averaged over which one is
    kept, is the full loss and gradient again."""
    fit = fit20(backend, truth)                                             # 4 segments of 5
    raw = weights(fit, trained_like())
    full, _, gfull, _ = fit.epoch_loss(raw, 0, fraction=1.0)
    gfull = gfull if isinstance(gfull, dict) else dict(zip(NAMES, gfull))
    seen, vals, grads = set(), [], []
    for seed in range(40):
        fit.seed = seed
        k = int(chosen_segments(4, 0.25, seed, 0)[0])
        if k in seen:
            continue
        seen.add(k)
        v, _, g, info = fit.epoch_loss(raw, 0, fraction=0.25)
        assert info["segments_backpropagated"] == 1
        vals.append(v)
        grads.append(g if isinstance(g, dict) else dict(zip(NAMES, g)))
    fit.seed = 0
    assert seen == {0, 1, 2, 3}
    assert math.isclose(np.mean(vals), full, rel_tol=1e-12)
    for n in NAMES:
        ref = fit.ops.numpy(gfull[n])
        np.testing.assert_allclose(np.mean([fit.ops.numpy(g[n]) for g in grads], axis=0), ref,
                                   rtol=1e-10, atol=1e-12 * float(np.abs(ref).max()))


def test_kinematics_only_reset_carries_C_and_F(truth, tmp_path):
    """reset [x, v]: each segment restarts from the ground-truth x, v with the C and F the simulation
    reached (not the ground truth's); with one segment it is the whole-state reset's loss."""
    st = mpmlab.build_stepper(square_scene("nclaw", {}), "warp", "mls", "fp64")
    params = [FitParameter(name=n, target="law_weights", field=n, form="array").bind(st.scene, st, []) for n in NAMES]
    tr = {k: a[:21] for k, a in truth.items()}
    kv = TeacherForcedFit(st, st.scene, params, {"x": tr["x"], "v": tr["v"]},
                          TeacherForcing(steps=20, start=10, end=10, reset=("x", "v")), epochs=1, groups=GROUPS)
    w = trained_like()
    raw = weights(kv, w)
    init0 = kv._initial(0, None)
    carry = kv._carry_after(raw, init0, 10)
    # the simulation's own F and C after 10 steps from the scene's initial state, with these weights
    path = tmp_path / "w.safetensors"
    save_weights(str(path), w, Law(), dim=2)
    free = mpmlab.build_stepper(square_scene("nclaw", {}, {"weights_file": str(path)}), "warp", "mls", "fp64")
    traj = free.rollout(steps=10, every=10, fields=("F", "C"))
    np.testing.assert_allclose(kv.ops.numpy(carry["law_state"][0]["F"]), traj.fields["F"][-1], atol=1e-12)
    np.testing.assert_allclose(kv.ops.numpy(carry["C"]), traj.fields["C"][-1], atol=1e-9)
    assert np.abs(traj.fields["F"][-1] - tr["F"][10]).max() > 1e-4        # not the ground truth's F
    val, why, g, info = kv.epoch_loss(raw, 0)
    assert why is None and info["segments"] == 2 and val > 0
    one = TeacherForcedFit(st, st.scene, params, {"x": tr["x"], "v": tr["v"]},
                           TeacherForcing(steps=20, start=20, end=20, reset=("x", "v")), epochs=1, groups=GROUPS)
    full = TeacherForcedFit(st, st.scene, params, tr, TeacherForcing(steps=20, start=20, end=20), epochs=1, groups=GROUPS)
    assert math.isclose(one.epoch_loss(raw, 0)[0], full.epoch_loss(raw, 0)[0], rel_tol=1e-12)


def test_particle_state_observation_on_both_backends():
    """particle_state reads C and F as the rollout stores them (NumPy oracle), JAX = Warp, and its
    gradient w.r.t. the initial velocities agrees between the backends (fp64)."""
    import jax
    import torch

    from mpmlab.observations import ParticleState, apply_numpy

    steps, picked = [0, 3, 10], [0, 5, 63]
    got, grads = {}, {}
    for b in ("jax", "warp"):
        st = mpmlab.build_stepper(square_scene("fixed_corotated", {"E": 1e5, "nu": 0.2}), b, "mls", "fp64")
        traj = st.rollout(steps=10, every=1, fields=("F", "C"))
        c = st.controls()
        for q in ("F", "C"):
            obs = ParticleState(quantity=q, particles=picked)
            y = st.observe(c, obs, steps)
            y = np.asarray(y.detach().numpy() if hasattr(y, "detach") else y)
            for k, s in enumerate(steps):
                oracle = apply_numpy(obs, {"x": traj.x[s], q: traj.fields[q][s]})
                np.testing.assert_allclose(y[k], oracle, rtol=0, atol=1e-12)
            got[b, q] = y
        obs = ParticleState(quantity="F", particles=picked)
        w = np.random.default_rng(0).standard_normal((3, len(picked), 4))
        if b == "jax":
            f = lambda v: (st.observe({**c, "v": v}, obs, steps) * w).sum()
            grads[b] = np.asarray(jax.grad(f)(c["v"]))
        else:
            v = c["v"].clone().requires_grad_(True)
            (st.observe({**c, "v": v}, obs, steps) * torch.as_tensor(w)).sum().backward()
            grads[b] = v.grad.numpy()
    for q in ("F", "C"):
        np.testing.assert_allclose(got["jax", q], got["warp", q], rtol=0, atol=1e-12)
    assert np.abs(grads["jax"]).max() > 0
    np.testing.assert_allclose(grads["warp"], grads["jax"], rtol=1e-9, atol=1e-12 * np.abs(grads["jax"]).max())


@pytest.mark.parametrize("backend", ["jax", "warp"])
def test_a_nan_gradient_is_located_in_its_segment(backend, truth, monkeypatch):
    """A non-finite gradient in a teacher-forced epoch raises GradientError with the trajectory's step
    (segment start + step inside it), never zeroed: here the data loss's derivative is NaN from the
    third segment's (steps 10-15) second step."""
    from mpmlab.core.errors import GradientError

    fit = fit20(backend, truth)
    raw = weights(fit, trained_like())
    fit._bad_segment = (10, 5, fit._initial(10))
    orig = fit.adapter.locate_nan_gradient

    def poisoned(stepper, controls, observation, steps, data_loss, segment=None):
        def bad(y):          # NaN derivative at the segment's second observed step only
            return data_loss(y) + (y[1] * float("nan")).sum()
        return orig(stepper, controls, observation, steps, bad, segment)
    monkeypatch.setattr(fit.adapter, "locate_nan_gradient", poisoned)
    with pytest.raises(GradientError) as err:
        fit._locate(raw)
    assert err.value.step == 12 and "segment starting at step 10" in str(err.value)


def test_jax_tracking_loss_of_fixed_pieces_equals_one_program_per_length(truth):
    """The JAX tracking loss runs any rollout length from four compiled pieces (chunks of ``segment``
    steps and single steps, forward and adjoint). Value and gradient equal the one-program-per-length
    loss (``core.autodiff.tracking_loss``) in fp64, for lengths that are and are not multiples of the
    chunk, with the velocity term on."""
    from mpmlab.core.autodiff import tracking_loss

    fit = make_fit("jax", truth, steps=20, epochs=1, period=10.0, velocity_weight=0.3, segment=3)
    ops, raw = fit.ops, weights(fit, trained_like())
    obs, wts = (fit.observation, fit._obs_v), (1.0, 0.3)
    pieces = fit.adapter.tracking_value_and_grad(fit.stepper, fit._controls, obs, wts, 3)
    whole = tracking_loss(fit.adapter, fit.stepper, fit._controls, obs, wts, 3)
    d = fit._backend_data()
    for s, L in ((0, 7), (13, 2)):
        init = fit._initial(s)
        tg = (d["x"][s + 1:s + L + 1], d["v"][s + 1:s + L + 1])
        a, why_a, ga = pieces(raw, init, tg, ops.asarray(2.5))
        b, why_b, gb = whole(raw, init, tg, ops.asarray(2.5))
        assert why_a is None and why_b is None and a > 0
        assert abs(a - b) <= 1e-12 * abs(b), (L, a, b)
        for n in NAMES:
            x, y = ops.numpy(ga[n]), ops.numpy(gb[n])
            assert np.max(np.abs(x - y)) <= 1e-12 * np.max(np.abs(y)), (L, n)


def test_a_stopped_fit_says_how_far_it_got_and_what_it_kept(truth, tmp_path):
    """A stop signal mid-fit (here raised from on_epoch in the second epoch) carries the epoch reached and
    the checkpoint kept into the CLI's closing line, instead of the 'nothing was written' of a run stopped
    before its first step (seen on a 120-epoch nclaw_train killed by SIGTERM)."""
    from mpmlab.cli import describe_error

    ck = tmp_path / "ck.pkl"
    fit = make_fit("jax", truth, steps=20, epochs=3, period=5.0)
    opt, sch = fit.optimizer(NETS)

    def stop_in_second_epoch(epoch, loss, values):
        if epoch == 1:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt) as info:
        fit.run(3, opt, sch, progress=False, checkpoint=ck, checkpoint_every=1, on_epoch=stop_in_second_epoch)
    assert info.value.mpmlab_detail.startswith("at epoch 2 of 3; ck.pkl keeps the last checkpointed epoch")
    code, line = describe_error(info.value)
    assert code == 130 and "at epoch 2 of 3" in line and "rerun the same command to resume" in line, line
