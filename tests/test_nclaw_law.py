"""The ``nclaw`` law (NCLaw, Ma et al. ICML 2023): sizes, rest state, rotation equivariance, the
reference vs JAX vs Warp from one weights file, the file's round trip and refusals, finite gradients
at F = I, ``dt: auto`` from the network's tangent, and the conformance kit.

Small sizes (2 cores): the Warp kernels of the law (2D/3D fp64, 3D fp32) and one fused G2P kernel
(2D, MLS) are the costly part; they are shared with ``tests/test_laws.py`` through Warp's cache.
"""
from functools import partial

import numpy as np
import pytest

import mpmlab
from mpmlab import testing
from mpmlab.core.errors import ConfigError
from mpmlab.laws.nclaw import Law, reference, save_weights
from mpmlab.testing.evaluate import evaluate, warp_eval
from mpmlab.testing.states import deformation_gradients, rotation


def trained_like(law, dim, seed=7, scale=30.0):
    """Weights far from the Xavier start (stresses of ~1e2-1e4 Pa, as after training with lr 1.0)."""
    rng = np.random.default_rng(seed)
    return {k: scale * a * (1.0 + 0.5 * rng.standard_normal(a.shape)) + 0.01 * rng.standard_normal(a.shape)
            for k, a in law.initial_weights(dim).items()}


def states(dim, seed=0):
    Fs = deformation_gradients(dim, np.random.default_rng(seed))
    return [{"F": F} for F in Fs]


def rel(a, b):
    return float(np.max(np.abs(np.asarray(a) - np.asarray(b))) / np.max(np.abs(np.asarray(b))))


def test_weight_counts():
    assert Law().weight_count(3) == 11008 and Law().weight_count(2) == 9600
    shapes = Law().weight_shapes(3)
    assert shapes["e_W1"] == (64, 13) and shapes["e_W2"] == (64, 64) and shapes["p_W3"] == (9, 64)
    assert Law().weight_shapes(2)["e_W1"] == (64, 7)
    assert Law(no_rotation=True).weight_shapes(3)["e_W1"] == (64, 9)
    assert {"e_b1", "e_b3", "p_b2"} <= set(Law(no_undeformed=True).weight_shapes(2))
    w = Law().initial_weights(3)
    a = np.sqrt(6.0 / (64 + 13))                                   # Xavier uniform bound
    assert np.abs(w["e_W1"]).max() <= a and np.abs(w["e_W1"]).max() > 0.9 * a
    assert not np.array_equal(Law(seed=1).initial_weights(3)["e_W1"], w["e_W1"])


@pytest.mark.parametrize("dim", (2, 3))
def test_rotation_equivariance(dim):
    """tau(QF) = Q tau(F) Q^T and update(QF, Q L Q^T) = Q update(F, L), 100 random rotations (fp64)."""
    law = Law()
    w = trained_like(law, dim)
    rng = np.random.default_rng(dim)
    worst = {"tau": 0.0, "F": 0.0}
    for k in range(100):
        F = np.eye(dim) + 0.3 * rng.standard_normal((dim, dim))
        if np.linalg.det(F) < 0:
            F[:, -1] *= -1
        L = rng.standard_normal((dim, dim))
        Q = rotation(dim, rng)
        tau = reference.kirchhoff({"F": F}, {}, w, law=law)
        tau_q = reference.kirchhoff({"F": Q @ F}, {}, w, law=law)
        worst["tau"] = max(worst["tau"], rel(tau_q, Q @ tau @ Q.T))
        Fn = reference.update({"F": F}, L, 1e-2, {}, w, law=law)["F"]
        Fn_q = reference.update({"F": Q @ F}, Q @ L @ Q.T, 1e-2, {}, w, law=law)["F"]
        worst["F"] = max(worst["F"], rel(Fn_q, Q @ Fn))
    assert worst["tau"] <= 1e-12 and worst["F"] <= 1e-12, worst
    # the release's tau = R T F^T is not symmetric (declared: symmetric_stress = False)
    assert not np.allclose(tau, tau.T)
    # the no-rotation ablation is not equivariant (that is the point of it)
    nr = Law(no_rotation=True)
    wn = trained_like(nr, dim)
    assert rel(reference.kirchhoff({"F": Q @ F}, {}, wn, law=nr),
               Q @ reference.kirchhoff({"F": F}, {}, wn, law=nr) @ Q.T) > 1e-3


def test_rest_state_exact_with_finite_jax_gradients():
    """At F = I: tau = 0 and F_new = F bit for bit (reference, JAX, Warp), and jax.grad of tau and of
    the update w.r.t. F and the weights is finite there and at repeated singular values."""
    import jax
    import jax.numpy as jnp

    from mpmlab.backends.jax.laws import law_functions

    for dim in (2, 3):
        law = Law()
        w = trained_like(law, dim)
        eye = np.eye(dim)
        for b in ("reference", "jax", "warp"):
            tau = np.asarray(evaluate(law, dim, b, "kirchhoff", [{"F": eye}], {}))[0]
            new = evaluate(law, dim, b, "update", [{"F": eye}], {}, np.zeros((1, dim, dim)), 1e-3)[0]["F"]
            assert np.all(tau == 0.0), (b, dim, tau)
            assert np.array_equal(new, eye), (b, dim, new)
        if dim == 2:
            continue                # the gradients: 3D only (each jit of both networks costs seconds)
        fns = law_functions(law, dim)
        wj = {k: jnp.asarray(a) for k, a in w.items()}
        row = jnp.zeros((0,))
        G = jnp.asarray(np.random.default_rng(0).standard_normal((dim, dim)))
        L = jnp.asarray(np.random.default_rng(1).standard_normal((dim, dim)))

        @jax.jit
        @partial(jax.grad, argnums=(0, 1))
        def grads(F, w):
            s = {"F": F}
            return jnp.sum(G * fns.kirchhoff(s, row, w)) + jnp.sum(G * fns.update(s, L, 1e-2, row, w)["F"])

        rot = np.eye(dim)
        rot[:2, :2] = [[np.cos(0.4), -np.sin(0.4)], [np.sin(0.4), np.cos(0.4)]]
        for F in (eye, 1.01 * rot, np.diag([1.2] * (dim - 1) + [0.9])):   # rest, repeated, partly repeated
            gF, gw = grads(jnp.asarray(F), wj)
            assert np.all(np.isfinite(np.asarray(gF))), F
            assert all(np.all(np.isfinite(np.asarray(g))) for g in gw.values())
            assert float(jnp.abs(gF).max()) > 0


def test_warp_gradient_at_rest_is_finite_and_matches_jax():
    """Warp's adjoint (the MLP's hand-written one, the spectral R and sigma) at F = I and a generic F
    against jax.grad (both take the same derivative of sigma, d s_i = (U^T dF V)_ii)."""
    import jax
    import jax.numpy as jnp
    import warp as wp

    from mpmlab.backends.jax.laws import law_functions
    from mpmlab.backends.warp.kernels import law_kernels

    jax.config.update("jax_enable_x64", True)       # the comparison is fp64 (run alone, no other test sets it)
    dim = 2
    law = Law()
    w = trained_like(law, dim)
    rng = np.random.default_rng(3)
    Fs = np.array([np.eye(dim), np.eye(dim) + 0.2 * rng.standard_normal((dim, dim))])
    G = rng.standard_normal((2, dim, dim))
    K = law_kernels(law, dim, "fp64")
    T = K.types
    Fa = wp.array(Fs, dtype=T.mat, requires_grad=True)
    ws = {k: wp.array(a, dtype=T.scalar, requires_grad=True) for k, a in w.items()}
    tau = wp.zeros(2, dtype=T.mat, requires_grad=True)
    tape = wp.Tape()
    with tape:
        wp.launch(K.stress, dim=2, inputs=[T.state_arrays({"F": Fa}), wp.zeros((2, 0), dtype=T.scalar),
                                           T.weights(ws), 0, tau])
    tape.backward(grads={tau: wp.array(G, dtype=T.mat)})
    fns = law_functions(law, dim)
    wj = {k: jnp.asarray(a) for k, a in w.items()}
    f = lambda F, w: jnp.sum(jnp.asarray(G) * jax.vmap(lambda F: fns.kirchhoff({"F": F}, jnp.zeros((0,)), w))(F))  # noqa: E731
    gF, gw = jax.grad(f, argnums=(0, 1))(jnp.asarray(Fs), wj)
    assert np.all(np.isfinite(Fa.grad.numpy()))
    assert rel(Fa.grad.numpy(), np.asarray(gF)) <= 1e-11
    for k in ("e_W1", "e_W2", "e_W3"):
        assert rel(ws[k].grad.numpy(), np.asarray(gw[k])) <= 1e-11, k


def _agree(law, dims, precisions):
    for dim in dims:
        prm = {}
        for what in ("kirchhoff", "update"):
            sts = states(dim, seed=dim)
            L = 2.0 * np.random.default_rng(5).standard_normal((len(sts), dim, dim))
            ref = evaluate(law, dim, "reference", what, sts, prm, L, 1e-2)
            for b in ("jax", "warp"):
                for prec in precisions:
                    if b == "jax" and prec == "fp32":
                        continue
                    got = (evaluate(law, dim, b, what, sts, prm, L, 1e-2) if prec == "fp64" else
                           warp_eval(law, dim, what, sts, prm, L, 1e-2, precision=prec))
                    if what == "update":
                        got, r = [g["F"] for g in got], [x["F"] for x in ref]
                    else:
                        r = ref
                    e = rel(got, r)
                    tol = 1e-12 if prec == "fp64" else 1e-5
                    assert e <= tol, (dim, what, b, prec, e)


def test_reference_jax_warp_agree_from_one_weights_file(tmp_path, monkeypatch):
    """One safetensors file, three implementations: fp64 within 1e-12, Warp fp32 within 1e-5 (relative),
    on the kit's hard deformation gradients (random, rotated, near-singular, stretch 3)."""
    # a relative file name: the law instance (and so its Warp kernels' cache key) is the same every run
    monkeypatch.chdir(tmp_path)
    for dim in (2, 3):
        path = f"nclaw_{dim}d.safetensors"
        save_weights(path, trained_like(Law(), dim), Law(), dim)
        law = Law(weights_file=path)
        _agree(law, (dim,), ("fp64",) + (("fp32",) if dim == 3 else ()))


def test_weights_file_round_trip_and_refusals(tmp_path):
    law = Law()
    w = trained_like(law, 3)
    path = tmp_path / "w.safetensors"
    save_weights(path, w, law, 3)
    got = Law(weights_file=str(path)).initial_weights(3)
    assert set(got) == set(w) and all(np.array_equal(got[k], w[k]) for k in w)
    from safetensors import safe_open

    with safe_open(str(path), framework="numpy") as f:
        meta = f.metadata()
    assert meta == {"law": "nclaw", "dim": "3", "variant": "invariant", "width": "64", "alpha": "0.001", "seed": "0"}

    def refused(law, dim, *words):
        with pytest.raises(ConfigError) as e:
            law.initial_weights(dim)
        msg = str(e.value)
        assert "\n" not in msg and all(wd in msg for wd in words), msg

    refused(Law(weights_file=str(path)), 2, "dimension 3", "dimension 2")
    refused(Law(weights_file=str(path), no_rotation=True), 3, "variant invariant", "no_rotation")
    refused(Law(weights_file=str(path), alpha=0.01), 3, "alpha")
    refused(Law(weights_file=str(path), width=32), 3, "width 64")
    # a file without metadata (e.g. written by hand) is checked by its arrays' names and shapes
    from safetensors.numpy import save_file

    bare = tmp_path / "bare.safetensors"
    save_file({k: np.ascontiguousarray(a) for k, a in w.items()}, str(bare))
    assert np.array_equal(Law(weights_file=str(bare)).initial_weights(3)["p_W2"], w["p_W2"])
    refused(Law(weights_file=str(bare)), 2, "2D", "e_W1")
    refused(Law(weights_file=str(bare), no_undeformed=True), 3, "e_b1")
    refused(Law(weights_file=str(tmp_path / "missing.safetensors")), 3, "cannot read")
    junk = tmp_path / "junk.safetensors"
    junk.write_bytes(b"junk")                   # safetensors' SafetensorError is a bare Exception
    refused(Law(weights_file=str(junk)), 3, "cannot read")


def test_dt_auto_uses_the_networks_rest_tangent(tmp_path):
    """The wave speed comes from the elastic network's tangent at F = I: scaling the output layer by k
    scales it by sqrt(k); a scene with dt: auto sees the weights file's stiffness."""
    law = Law()
    w = law.initial_weights(2)
    c1 = law.instance_wave_speed({}, 1000.0, 2, w)
    w4 = dict(w, e_W3=4.0 * w["e_W3"])
    assert c1 > 0 and abs(law.instance_wave_speed({}, 1000.0, 2, w4) / c1 - 2.0) < 1e-12
    # the tangent matches a one-sided difference of the reference along a diagonal dF with sorted,
    # distinct stretches (there d sigma = diag(dF), the backends' convention at U = V = I; the singular
    # values are not differentiable at F = I: a central difference averages two orderings)
    C = reference.rest_tangent(w, 2, law)
    dF = np.array([[0.3, 0.0], [0.0, -0.4]])
    h = 1e-7
    fd = reference.kirchhoff({"F": np.eye(2) + h * dF}, {}, w) / h
    assert rel(np.einsum("ijkl,kl->ij", C, dF), fd) < 1e-5
    path = tmp_path / "stiff.safetensors"
    save_weights(path, dict(w, e_W3=1e6 * w["e_W3"]), law, 2)
    scene = mpmlab.Scene(dim=2, dx=0.05, domain=([0, 0], [1, 1]), dt="auto", name="nclaw_dt",
                         bodies=[mpmlab.Body(shape={"kind": "box", "lo": [0.4, 0.4], "hi": [0.5, 0.5]},
                                             material="nclaw", options={"weights_file": str(path)})])
    assert abs(scene.wave_speed() / (1e3 * c1) - 1.0) < 1e-9
    assert scene.resolve_dt() == pytest.approx(0.3 * 0.05 / scene.wave_speed(), rel=1e-9)


def test_conformance_kit():
    """check_law: reference (JAX, Warp), rest state, equivariance, JAX vs Warp trajectories (2D, MLS)
    and gradients w.r.t. x, v and the shared weights (JAX and Warp, central differences, 1e-6)."""
    report = testing.check_law("nclaw", dims=(2,), transfers=("mls",))
    assert not report["failures"]
    assert report["checks"]["equivariance[2d]"]["symmetry"] > 1e-3      # measured, not required
    assert set(report["checks"]["gradients[warp,mls,2d]"]) == {"x", "v", "law_weights"}
