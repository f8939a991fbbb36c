"""The deformation-map ROM's networks (``mpmlab.rom.networks``, ``networks_torch``; Chen et al. JCP
2023 Sec. 4, Tab. 1, App. B): sizes (g's parameter counts and the encoder's conv layers from the
notes, Sec. 2.1), exact Jacobians against central differences (fp64, JAX and torch), JAX = torch from
one file (fp32), the chain rule through the normaliser on an exactly representable g, the file's round
trip and its one-line refusals. Small sizes: the whole file runs in a few seconds."""
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import torch
from safetensors.numpy import save_file

from mpmlab.core.errors import ConfigError
from mpmlab.rom import networks as rn
from mpmlab.rom import networks_torch as rt

jax.config.update("jax_enable_x64", True)   # the fp64 checks; the fp32 ones pass dtypes explicitly


def trained_like(spec, seed=3, scale=2.0):
    """Weights away from the Xavier start (non-zero biases, larger gains), so every ELU is exercised."""
    rng = np.random.default_rng(seed)
    return {k: (scale * a if a.ndim > 1 else 0.3 * rng.standard_normal(a.shape))
            for k, a in rn.init_params(spec, seed).items()}


def norm_like(dim, seed=4):
    """A non-trivial normaliser: a body of a few cm away from the origin, displacements of mm."""
    rng = np.random.default_rng(seed)
    lo = 0.05 + 0.02 * rng.random(dim)
    return {"X_min": lo, "X_max": lo + 0.01 + 0.04 * rng.random(dim),
            "u_mean": 1e-3 * rng.standard_normal(dim), "u_std": 2e-3 * (1.0 + rng.random(dim))}


def points(norm, n, seed=5):
    rng = np.random.default_rng(seed)
    return norm["X_min"] + (norm["X_max"] - norm["X_min"]) * rng.random((n, len(norm["X_min"])))


def rel(a, b):
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    return float(np.linalg.norm(a - b) / np.linalg.norm(b))


# ---- sizes --------------------------------------------------------------------------------------

@pytest.mark.parametrize("latent, count", [(6, 4113), (1, 3963), (7, 4143)])
def test_g_parameter_count_3d(latent, count):
    """Notes 2.1: 4,113 parameters at d_hat = 6, 3,963 at 1, 4,143 at 7 (5 hidden layers of 30)."""
    spec = rn.RomSpec(dim=3, latent=latent)
    assert spec.g_count() == count
    assert sum(a.size for a in rn.init_params(spec).values()) == count
    assert len([k for k in spec.g_shapes() if "_W" in k]) == 6


def test_g_parameter_count_2d():
    assert rn.RomSpec(dim=2, latent=6).g_count() == (8 * 30 + 30) + 4 * (30 * 30 + 30) + (30 * 2 + 2)


@pytest.mark.parametrize("n_points, n_conv, length", [(1368, 6, 17), (1757, 6, 23), (13900, 9, 23)])
def test_encoder_layers(n_points, n_conv, length):
    """Notes 2.1: N = 1,368 -> 6 conv layers (L = 17), 1,757 -> 6 (L = 23), 13,900 -> 9; d L >= 32 after
    the last, < 32 after one more (Tab. 1 caption: d_conv "as low as possible but no smaller than 32")."""
    spec = rn.RomSpec(dim=3, latent=6, n_points=n_points)
    lengths = spec.conv_lengths()
    assert len(lengths) == n_conv and lengths[-1] == length
    assert 3 * length >= 32 and 3 * ((length - 6) // 2 + 1) < 32
    shapes = spec.encoder_shapes()
    assert shapes["e_fc0_W"] == (32, 3 * length) and shapes["e_fc1_W"] == (6, 32)
    assert len([k for k in shapes if k.startswith("e_conv") and k.endswith("_W")]) == n_conv


def test_encoder_parameter_count():
    """Notes 2.1: 2,204 encoder parameters at N = 1,368, d_hat = 6 (6 x 57 + 51 x 32 + 32 + 32 x 6 + 6)."""
    assert rn.RomSpec(dim=3, latent=6, n_points=1368).encoder_count() == 2204
    # the same rule, not stated in the notes: 6 x 57 + (69 x 32 + 32) + 198 and 9 x 57 + 2,272 + 198
    assert rn.RomSpec(dim=3, latent=6, n_points=1757).encoder_count() == 2780
    assert rn.RomSpec(dim=3, latent=6, n_points=13900).encoder_count() == 2951


def test_init_is_xavier_uniform_with_zero_biases():
    spec = rn.RomSpec(dim=3, latent=6, n_points=1368)
    p, q = rn.init_params(spec, seed=1), rn.init_params(spec, seed=1)
    assert all(np.array_equal(p[k], q[k]) for k in p)
    assert not np.array_equal(p["g_W0"], rn.init_params(spec, seed=2)["g_W0"])
    for k, a in p.items():
        if a.ndim == 1:
            assert not a.any()
        else:
            rf = math.prod(a.shape[2:])
            bound = math.sqrt(6.0 / (rf * (a.shape[0] + a.shape[1])))
            assert np.abs(a).max() <= bound and np.abs(a).max() > 0.8 * bound


# ---- Jacobians ----------------------------------------------------------------------------------

def central_differences(fn, X, z, h_X, h_z):
    """dx/dX [P, d, d] and dx/dz [P, d, d_hat] of a point-wise fn(X [P, d], z [P, d_hat]) -> [P, d]."""
    d, m = X.shape[1], z.shape[1]
    FX = np.stack([(fn(X + h_X * np.eye(d)[j], z) - fn(X - h_X * np.eye(d)[j], z)) / (2 * h_X) for j in range(d)], -1)
    Fz = np.stack([(fn(X, z + h_z * np.eye(m)[j]) - fn(X, z - h_z * np.eye(m)[j])) / (2 * h_z) for j in range(m)], -1)
    return FX, Fz


def _fd_case(dim):
    spec = rn.RomSpec(dim=dim, latent=5)
    params, norm = trained_like(spec), norm_like(dim)
    X = points(norm, 6)
    z = np.random.default_rng(8).standard_normal((6, spec.latent))
    return params, norm, X, z


@pytest.mark.parametrize("dim", [2, 3])
def test_jacobians_vs_central_differences_jax(dim):
    params, norm, X, z = _fd_case(dim)
    p, n = rn.to_jax(params, jnp.float64), rn.to_jax(norm, jnp.float64)
    x, F, Fz = (np.asarray(a) for a in rn.g_jacobians(p, n, X, z))
    assert np.allclose(x, np.asarray(rn.g_apply(p, n, X, z)), rtol=0, atol=1e-15)
    FX_fd, Fz_fd = central_differences(lambda a, b: np.asarray(rn.g_apply(p, n, a, b)), X, z, 1e-6, 1e-5)
    assert rel(F, FX_fd) < 1e-7 and rel(F - np.eye(dim), FX_fd - np.eye(dim)) < 1e-7
    assert rel(Fz, Fz_fd) < 1e-7


@pytest.mark.parametrize("dim", [2, 3])
def test_jacobians_vs_central_differences_torch(dim):
    params, norm, X, z = _fd_case(dim)
    p, n = rt.to_torch(params, torch.float64), rt.to_torch(norm, torch.float64)
    T = lambda a: torch.as_tensor(a, dtype=torch.float64)   # noqa: E731
    x, F, Fz = (a.numpy() for a in rt.g_jacobians(p, n, T(X), T(z)))
    assert np.allclose(x, rt.g_apply(p, n, T(X), T(z)).numpy(), rtol=0, atol=1e-15)
    FX_fd, Fz_fd = central_differences(lambda a, b: rt.g_apply(p, n, T(a), T(b)).numpy(), X, z, 1e-6, 1e-5)
    assert rel(F, FX_fd) < 1e-7 and rel(F - np.eye(dim), FX_fd - np.eye(dim)) < 1e-7
    assert rel(Fz, Fz_fd) < 1e-7


def test_velocity_is_the_latent_jacobian_times_zdot():
    params, norm, X, z = _fd_case(3)
    zdot = np.random.default_rng(9).standard_normal(z.shape[1])
    p, n = rn.to_jax(params, jnp.float64), rn.to_jax(norm, jnp.float64)
    _, _, Fz = rn.g_jacobians(p, n, X, z)
    x, v = rn.g_velocity(p, n, X, z, zdot)
    assert rel(v, np.einsum("pij,j->pi", np.asarray(Fz), zdot)) < 1e-13
    assert rel(x, rn.g_apply(p, n, X, z)) < 1e-15
    pt, nt = rt.to_torch(params, torch.float64), rt.to_torch(norm, torch.float64)
    xt, vt = rt.g_velocity(pt, nt, torch.as_tensor(X), torch.as_tensor(z), torch.as_tensor(zdot))
    assert rel(vt.numpy(), v) < 1e-13 and rel(xt.numpy(), x) < 1e-15


@pytest.mark.parametrize("dim", [2, 3])
def test_g_state_is_g_jacobians_on_fewer_tangents(dim):
    """g_F / g_state (d and d + 1 forward tangents) give g_jacobians' x and F and its dx/dz zdot, on JAX
    (one latent for all points, and a batch of latents and latent velocities) and on torch."""
    params, norm, X, z = _fd_case(dim)
    zdot = np.random.default_rng(10).standard_normal(z.shape[1])
    p, n = rn.to_jax(params, jnp.float64), rn.to_jax(norm, jnp.float64)
    x, F, Fz = (np.asarray(a) for a in rn.g_jacobians(p, n, X, z[:1]))
    v = np.einsum("pij,j->pi", Fz, zdot)
    xs, Fs, vs = (np.asarray(a) for a in rn.g_state(p, n, X, z[:1], zdot[None]))
    xf, Ff = (np.asarray(a) for a in rn.g_F(p, n, X, z[:1]))
    assert rel(xs, x) < 1e-15 and rel(Fs, F) < 1e-15 and rel(vs, v) < 1e-14 and rel(xf, x) < 1e-15 and rel(Ff, F) < 1e-15
    zb, zdb = z[:3, None, :], np.stack([zdot, -2 * zdot, 0 * zdot])[:, None, :]
    _, Fb, Fzb = (np.asarray(a) for a in rn.g_jacobians(p, n, X, zb))
    _, Fsb, vsb = (np.asarray(a) for a in rn.g_state(p, n, X, zb, zdb))
    assert vsb.shape == (3, 6, dim) and rel(Fsb, Fb) < 1e-15
    assert rel(vsb, np.einsum("bpij,bj->bpi", Fzb, zdb[:, 0])) < 1e-14
    pt, nt = rt.to_torch(params, torch.float64), rt.to_torch(norm, torch.float64)
    xt, Ft, vt = (a.numpy() for a in rt.g_state(pt, nt, torch.as_tensor(X), torch.as_tensor(z[:1]), torch.as_tensor(zdot)))
    xtf, Ftf = (a.numpy() for a in rt.g_F(pt, nt, torch.as_tensor(X), torch.as_tensor(z[:1])))
    assert rel(xt, x) < 1e-14 and rel(Ft, F) < 1e-13 and rel(vt, v) < 1e-13 and rel(xtf, x) < 1e-14 and rel(Ftf, F) < 1e-13


def test_broadcast_one_latent_per_snapshot():
    """z [B, 1, d_hat] with X [N, d] -> [B, N, ...], the same as one snapshot at a time."""
    params, norm, X, z = _fd_case(3)
    p, n = rn.to_jax(params), rn.to_jax(norm)
    zb = z[:3, None, :]
    x, F, Fz = rn.g_jacobians(p, n, X, zb)
    assert x.shape == (3, 6, 3) and F.shape == (3, 6, 3, 3) and Fz.shape == (3, 6, 3, 5)
    for b in range(3):
        xb, Fb, Fzb = rn.g_jacobians(p, n, X, z[b])
        assert rel(F[b], Fb) < 1e-15 and rel(Fz[b], Fzb) < 1e-15 and rel(x[b], xb) < 1e-15
    xt, Ft, _ = rt.g_jacobians(rt.to_torch(params, torch.float64), rt.to_torch(norm, torch.float64),
                               torch.as_tensor(X), torch.as_tensor(zb))
    assert rel(Ft.numpy(), F) < 1e-13 and rel(xt.numpy(), x) < 1e-14


def linear_g(spec, A, B, c=10.0):
    """u~ = B x_hat + A X~ exactly (``networks.linear_params``)."""
    return rn.linear_params(spec, A, B, c)


@pytest.mark.parametrize("dim", [2, 3])
def test_identity_and_linear_maps_through_the_normaliser(dim):
    """g(X; x_hat) = X + u_std * x_hat[:d] + u_mean gives F = I exactly and dx/dx_hat = [diag(u_std), 0];
    with u~ = A X~ + B x_hat, F = I + diag(u_std) A diag(1 / (X_max - X_min)): the chain rule through the
    min-max normaliser and the standardiser."""
    spec = rn.RomSpec(dim=dim, latent=4)
    norm = norm_like(dim)
    X = points(norm, 5)
    z = 0.5 * np.random.default_rng(1).standard_normal((5, 4))
    pad = np.eye(dim, 4)                                           # x_hat[:d], padded with zeros
    ident = linear_g(spec, np.zeros((dim, dim)), pad)
    M = 0.3 * np.random.default_rng(2).standard_normal((dim, dim))  # the F - I to recover
    A = (M * (norm["X_max"] - norm["X_min"])) / norm["u_std"][:, None]
    lin = linear_g(spec, A, pad)
    T = lambda a: torch.as_tensor(a, dtype=torch.float64)          # noqa: E731
    for name, apply in (("jax", lambda p: rn.g_jacobians(rn.to_jax(p), rn.to_jax(norm), X, z)),
                        ("torch", lambda p: rt.g_jacobians(rt.to_torch(p, torch.float64),
                                                           rt.to_torch(norm, torch.float64), T(X), T(z)))):
        x, F, Fz = (np.asarray(a) for a in apply(ident))
        assert np.array_equal(F, np.broadcast_to(np.eye(dim), F.shape)), name
        np.testing.assert_allclose(x, X + norm["u_std"] * z[:, :dim] + norm["u_mean"], rtol=0, atol=1e-16)
        np.testing.assert_allclose(Fz, np.broadcast_to(norm["u_std"][:, None] * pad, Fz.shape), rtol=0, atol=1e-18)
        x, F, Fz = (np.asarray(a) for a in apply(lin))
        np.testing.assert_allclose(F, np.broadcast_to(np.eye(dim) + M, F.shape), rtol=0, atol=1e-12)
        Xn = (X - norm["X_min"]) / (norm["X_max"] - norm["X_min"])
        np.testing.assert_allclose(x, X + norm["u_std"] * (z[:, :dim] + Xn @ A.T) + norm["u_mean"], rtol=0, atol=1e-15)


# ---- JAX = torch from one file ------------------------------------------------------------------

def test_jax_equals_torch_from_one_file_fp32(tmp_path):
    spec = rn.RomSpec(dim=3, latent=6, n_points=1368)
    norm = norm_like(3)
    path = tmp_path / "rom.safetensors"
    rn.save(path, trained_like(spec, scale=1.0), norm, spec, seed=3)
    wj, wt = rn.load(path, expect_dim=3, expect_latent=6), rt.load(path, dtype=torch.float32)
    p, n = rn.to_jax(wj.params, jnp.float32), rn.to_jax(wj.norm, jnp.float32)
    X = points(norm, 64).astype(np.float32)
    z = np.random.default_rng(6).standard_normal((64, 6)).astype(np.float32)
    a = rn.g_jacobians(p, n, X, z)
    b = rt.g_jacobians(wt.params, wt.norm, torch.from_numpy(X), torch.from_numpy(z))
    assert all(u.dtype == jnp.float32 for u in a) and all(v.dtype == torch.float32 for v in b)
    assert rel(a[0], b[0].numpy()) < 1e-6
    assert rel(a[1], b[1].numpy()) < 1e-6 and rel(a[2], b[2].numpy()) < 1e-6
    assert rel(rn.g_apply(p, n, X, z), rt.g_apply(wt.params, wt.norm, torch.from_numpy(X), torch.from_numpy(z))) < 1e-6
    # the standardised displacement u~ itself (x - X loses digits to X's fp32 rounding: u ~ X / 20 here)
    inp = np.concatenate([z, (X - norm["X_min"]) / (norm["X_max"] - norm["X_min"])], 1).astype(np.float32)
    assert rel(rn.g_mlp(p, inp), rt.g_mlp(wt.params, torch.from_numpy(inp)).numpy()) < 1e-6
    snaps = (points(norm, 1368, seed=7).T[None] + 0.002 * np.random.default_rng(8).standard_normal((2, 3, 1368)))
    snaps = snaps.astype(np.float32)
    ej, et = rn.encode(p, n, snaps), rt.encode(wt.params, wt.norm, torch.from_numpy(snaps))
    assert ej.shape == (2, 6) and ej.dtype == jnp.float32
    assert rel(ej, et.numpy()) < 1e-6
    assert rel(rn.encode(p, n, snaps[1]), ej[1]) < 1e-6 and np.all(np.asarray(ej) > -1.0)


def test_encoder_refuses_another_number_of_points():
    spec = rn.RomSpec(dim=3, latent=6, n_points=1368)
    p, n = rn.init_params(spec), norm_like(3)
    with pytest.raises(ConfigError) as e:
        rn.encode(rn.to_jax(p), rn.to_jax(n), np.zeros((3, 1757)))
    assert "\n" not in str(e.value) and "1757 points" in str(e.value)
    with pytest.raises(ConfigError):
        rt.encode(rt.to_torch(p), rt.to_torch(n), torch.zeros(3, 1757))


# ---- the file -----------------------------------------------------------------------------------

@pytest.mark.parametrize("n_points", [None, 1368])
def test_file_round_trip(tmp_path, n_points):
    spec = rn.RomSpec(dim=3, latent=7, n_points=n_points)
    params, norm = trained_like(spec), norm_like(3)
    path = tmp_path / "rom.safetensors"
    rn.save(path, rn.to_jax(params), rt.to_torch(norm, torch.float64), spec, seed=11)   # JAX / torch arrays
    w = rn.load(path, expect_dim=3, expect_latent=7, expect_n_points=n_points)
    assert w.spec == spec and w.seed == 11
    assert set(w.params) == set(params) and all(np.array_equal(w.params[k], params[k]) for k in params)
    assert all(np.array_equal(w.norm[k], norm[k]) for k in rn.NORM_KEYS)
    from safetensors import safe_open
    with safe_open(str(path), framework="numpy") as f:
        meta = f.metadata()
    assert meta["kind"] == "rom" and meta["parts"] == ("g" if n_points is None else "g+encoder")
    assert meta["dim"] == "3" and meta["latent"] == "7" and meta["seed"] == "11"
    assert meta.get("n_points") == (None if n_points is None else "1368")


def _write(path, arrays, meta):
    save_file({k: np.ascontiguousarray(v, dtype=np.float64) for k, v in arrays.items()}, str(path), metadata=meta)
    return path


def _good(n_points=None):
    spec = rn.RomSpec(dim=3, latent=6, n_points=n_points)
    return spec, rn.init_params(spec), norm_like(3)


def _refusals():
    spec, p, n = _good()
    meta = spec.metadata(0)
    cases = {
        "wrong dim": ({**p, **n}, meta, dict(expect_dim=2), "dimension is 3, expected 2"),
        "wrong latent": ({**p, **n}, meta, dict(expect_latent=7), "latent size is 6, expected 7"),
        "wrong n_points": ({**p, **n}, meta, dict(expect_n_points=1368), "number of points is None"),
        "wrong shape": ({**p, "g_W2": np.zeros((30, 31)), **n}, meta, {}, "g_W2 (30, 31) (wants (30, 30))"),
        "missing array": ({k: v for k, v in p.items() if k != "g_b5"} | n, meta, {}, "g_b5 missing"),
        "extra array": ({**p, "g_W6": np.zeros((3, 30)), **n}, meta, {}, "g_W6 unexpected"),
        "latent vs shapes": ({**rn.init_params(rn.RomSpec(3, 5)), **n}, meta, {}, "g_W0 (30, 8) (wants (30, 9))"),
        "dim vs shapes": ({**p, **n}, {**meta, "dim": "2"}, {}, "fit a 2D ROM"),
        "non-finite weight": ({**p, "g_b1": np.full(30, np.nan), **n}, meta, {}, "non-finite values in g_b1"),
        "normaliser shape": ({**p, **n, "X_min": np.zeros(2)}, meta, {}, "X_min (2,)"),
        "normaliser missing": ({**p, **{k: v for k, v in n.items() if k != "u_std"}}, meta, {}, "missing u_std"),
        "normaliser range": ({**p, **n, "X_max": n["X_min"] - 1.0}, meta, {}, "X_max > X_min"),
        "normaliser std": ({**p, **n, "u_std": np.array([1.0, 0.0, 1.0])}, meta, {}, "u_std > 0"),
        "normaliser nan": ({**p, **n, "u_mean": np.array([0.0, np.inf, 0.0])}, meta, {}, "non-finite"),
        "another kind": ({**p, **n}, {**meta, "kind": "nclaw"}, {}, "not a ROM network file"),
        "no dim": ({**p, **n}, {k: v for k, v in meta.items() if k != "dim"}, {}, "no 'dim'"),
        "bad dim": ({**p, **n}, {**meta, "dim": "4"}, {}, "dim must be 2 or 3"),
        "parts vs n_points": ({**p, **n}, {**meta, "parts": "g+encoder"}, {}, "do not agree"),
    }
    es, ep, en = _good(1368)
    emeta = es.metadata(0)
    cases["encoder shapes"] = ({**ep, "e_fc0_W": np.zeros((32, 60)), **en}, emeta, {}, "e_fc0_W (32, 60) (wants (32, 51))")
    cases["encoder n_points"] = ({**ep, **en}, {**emeta, "n_points": "1757"}, {}, "e_fc0_W (32, 51) (wants (32, 69))")
    cases["encoder missing"] = ({**p, **n}, emeta, {}, "e_conv0_W missing")
    return cases


@pytest.mark.parametrize("case", sorted(_refusals()))
def test_load_refusals_are_one_line(tmp_path, case):
    arrays, meta, kwargs, text = _refusals()[case]
    path = _write(tmp_path / "w.safetensors", arrays, meta)
    with pytest.raises(ConfigError) as e:
        rn.load(path, **kwargs)
    msg = str(e.value)
    assert "\n" not in msg and text in msg and str(path) in msg, msg
    with pytest.raises(ConfigError) as e2:                         # the torch loader says the same
        rt.load(path, **kwargs)
    assert str(e2.value) == msg


def test_unreadable_file_is_one_line(tmp_path):
    path = tmp_path / "junk.safetensors"
    path.write_bytes(b"not a safetensors file")
    for p in (path, tmp_path / "absent.safetensors"):
        with pytest.raises(ConfigError) as e:
            rn.load(p)
        assert "\n" not in str(e.value) and "cannot read it" in str(e.value)


def test_save_refuses_what_load_would(tmp_path):
    spec, p, n = _good()
    path = tmp_path / "w.safetensors"
    for bad_p, bad_n, text in (({**p, "g_W0": np.zeros((30, 8))}, n, "g_W0 (30, 8)"),
                               (p, {**n, "u_std": -n["u_std"]}, "u_std > 0"),
                               (p, {**n, "X_max": np.ones(3)[:2]}, "X_max (2,)")):
        with pytest.raises(ConfigError) as e:
            rn.save(path, bad_p, bad_n, spec)
        assert "\n" not in str(e.value) and text in str(e.value)
    assert not path.exists()


@pytest.mark.parametrize("kwargs, text", [(dict(dim=1, latent=6), "dim = 1"), (dict(dim=3, latent=0), "latent = 0"),
                                          (dict(dim=3, latent=6, n_points=0), "n_points = 0"),
                                          (dict(dim=3, latent=2.5), "latent = 2.5")])
def test_spec_refusals(kwargs, text):
    with pytest.raises(ConfigError) as e:
        rn.RomSpec(**kwargs)
    assert "\n" not in str(e.value) and text in str(e.value)


def test_fit_norm():
    rng = np.random.default_rng(0)
    X = rng.random((50, 3))
    x = X + 0.01 * rng.standard_normal((4, 50, 3)) + np.array([0.0, -0.02, 0.0])
    n = rn.fit_norm(X, x)
    u = (x - X).reshape(-1, 3)
    assert np.allclose(n["X_min"], X.min(0)) and np.allclose(n["X_max"], X.max(0))
    assert np.allclose(n["u_mean"], u.mean(0)) and np.allclose(n["u_std"], u.std(0))
    flat = rn.fit_norm(np.zeros((5, 2)), np.zeros((2, 5, 2)))     # no spread: range and std 1, valid
    rn.check(rn.RomSpec(2, 1), rn.init_params(rn.RomSpec(2, 1)), flat, "test")


def test_loss_gradients_through_the_jacobians_jax_equals_torch():
    """An Eq. 24-shaped loss (positions, lambda_F |F - F*|^2, lambda_v |dx/dx_hat zdot - v*|^2, with
    x_hat = e(x*)) differentiates through the forward-mode Jacobians and the encoder: JAX's reverse
    mode over jacfwd equals torch's autograd over torch.func.jacfwd (fp64)."""
    spec = rn.RomSpec(dim=3, latent=4, n_points=40)
    norm, params = norm_like(3), trained_like(spec, scale=1.0)
    X = points(norm, 40)
    rng = np.random.default_rng(12)
    xs, Fs, vs = X + 1e-3 * rng.standard_normal((40, 3)), np.eye(3) + 0.1 * rng.standard_normal((40, 3, 3)), rng.standard_normal((40, 3))
    zdot = rng.standard_normal(4)

    def loss(m, p, n, Xa, xa, Fa, va, zd):
        z = m.encode(p, n, xa.T)
        x, F, Fz = m.g_jacobians(p, n, Xa, z)
        v = (Fz * zd).sum(-1)
        return ((x - xa) ** 2).mean() + 100.0 * ((F - Fa) ** 2).mean() + 0.01 * ((v - va) ** 2).mean()

    gj = jax.jit(jax.grad(lambda p: loss(rn, p, rn.to_jax(norm), X, xs, Fs, vs, zdot)))(rn.to_jax(params))
    pt = {k: v.requires_grad_(True) for k, v in rt.to_torch(params, torch.float64).items()}
    T = lambda a: torch.as_tensor(a, dtype=torch.float64)          # noqa: E731
    loss(rt, pt, rt.to_torch(norm, torch.float64), T(X), T(xs), T(Fs), T(vs), T(zdot)).backward()
    for k in params:
        assert rel(gj[k], pt[k].grad.numpy()) < 1e-10, k
    assert np.linalg.norm(gj["e_conv0_W"]) > 0 and np.linalg.norm(gj["g_W0"]) > 0
