"""The networks of the deformation-map reduced-order model (Chen, Chiaramonte, Grinspun, Carlberg,
JCP 2023, "Model reduction for the material point method via an implicit neural representation of the
deformation map"; seed ``002_*``): the manifold parameterisation g and the encoder e (Sec. 4, Tab. 1,
App. B; ``/work/shared/notes/nclaw-rom.md`` Sec. 2.1, 2.2, 2.8 for what the paper leaves open).

This module holds the one spec both frameworks share (``RomSpec``: shapes, layer counts, Xavier
init), the weight file (``save``/``load``) and the JAX functions (``g_apply``, ``g_jacobians``,
``g_velocity``, ``encode``; each under ``jax.jit``: one compile per shape, not one per primitive as
eager dispatch would). ``mpmlab.rom.networks_torch`` has the torch counterparts; both read the
same dicts. Weights are plain dicts name -> array (JAX pytrees), as the NCLaw law stores its weights
(``mpmlab.laws.nclaw``); equinox is not used (not a dependency).

**g** (Sec. 4, Tab. 1; the release's order of inputs, notes 2.1)::

    in = [x_hat, X~]                      x_hat: latent (d_hat), X~ = (X - X_min) / (X_max - X_min)
    h_1 = ELU(W0 in + b0)                 W0: [30, d_hat + d]
    h_k = ELU(W_{k-1} h_{k-1} + b_{k-1})  k = 2..5, W: [30, 30]     (5 hidden layers of 30)
    u~  = W5 h_5 + b5                     W5: [d, 30], identity output (standardised displacement)
    u   = u~ * u_std + u_mean,  x = X + u (per component)

``g_W0..g_W5``, ``g_b0..g_b5`` in torch ``Linear`` layout ([out, in]). Parameter count for d = 3:
4,113 at d_hat = 6, 3,963 at d_hat = 1, 4,143 at d_hat = 7 (notes 2.1). Tab. 1 lists five rows
(d + d_hat -> 30, three 30 -> 30, 30 -> d: four hidden layers) while its caption and the release say
five hidden layers of 30; mpmlab follows the caption (``depth = 5``). The paper's text says g outputs
the deformed position; App. B standardises "the network's output" and the release predicts the
displacement u with x = X + u (notes 2.1): mpmlab predicts the standardised displacement.

**Encoder e** (Sec. 4.1, Tab. 1; notes 2.1): one snapshot's positions x as ``[d, N]`` (channels = the
d components, length = the particle index; a trajectory frame ``[N, d]`` must be transposed), min-max
normalised with the same X_min / X_max as g's input (App. B min-max normalises "the reference
positions" and says nothing of the encoder's input: an mpmlab choice, recorded as ``encoder_input =
"minmax"`` in the file), then ``n_conv`` times
``Conv1d(d, d, kernel 6, stride 2) + ELU`` (``e_conv{i}_W [d, d, 6]``, ``e_conv{i}_b [d]``), flatten
(``[d * L]``, channel-major like torch), ``Linear(d L, 32) + ELU`` (``e_fc0_*``) and
``Linear(32, d_hat) + ELU`` (``e_fc1_*``). The final ELU on the latent is the release's (notes 2.1);
the paper does not state it; it keeps every component of x_hat above -1 for encoded snapshots (an
online solver's x_hat is free). The number of conv layers: Tab. 1's caption reduces the input "down to
d_conv, which is as low as possible but no smaller than 32", d_conv = d L; i.e. a layer is added while
its output still has d L_out >= 32 (the release's rule, notes 2.1), L_out = (L - 6) // 2 + 1. N = 1,368
-> 6 layers (L = 17, 2,204 encoder parameters at d = 3, d_hat = 6), N = 1,757 -> 6 (L = 23), N = 13,900
-> 9 (L = 23). An N whose first layer would already give d L_out < 32 gets no conv layer (not a case
in the paper). The encoder depends on N and on the particle order; it is used offline only.

**Jacobians** (F = dg/dX in Algs. 3-4 and Eq. 24; dg/dx_hat in Eqs. 21, 23, 24): forward mode
(``jax.jacfwd`` over the d_hat + d inputs of the MLP, ``vmap`` over points), then the chain through the normaliser and the
standardiser, F = dx/dX = I + diag(u_std) (du~/dX~) diag(1 / (X_max - X_min)) and
dx/dx_hat = diag(u_std) (du~/dx_hat): the columns [:d_hat] and [d_hat:] of the MLP's Jacobian (the
release's ``NetGrad`` split, notes 2.1).

**Initialisation** (App. B): Xavier-uniform weights (torch's ``xavier_uniform_``: U(-a, a),
a = sqrt(6 / (fan_in + fan_out)), fan = channels x kernel for a conv) from ``numpy.random.default_rng
(seed)``, drawn in layer order, g first; zero biases (neither the paper nor the notes say how the
biases start; torch's own ``Linear`` default would draw them uniformly: an mpmlab choice).

**File** (``save``/``load``): one safetensors file with the g weights, optionally the encoder's, and
the normaliser ``X_min``, ``X_max``, ``u_mean``, ``u_std`` (each ``[d]``) as arrays; metadata: ``kind``
("rom"), ``parts`` ("g" or "g+encoder"), ``dim``, ``latent``, ``width``, ``depth``, ``n_points`` (with an
encoder), ``encoder_input``, ``seed``. ``load`` refuses, in one line (``ConfigError``), a file whose
kind, dimension, latent size, sizes, array names or shapes, or normaliser do not fit.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..core.errors import ConfigError

#: Tab. 1: every conv layer of the encoder
CONV_KERNEL, CONV_STRIDE = 6, 2
#: Tab. 1: the encoder's first fully connected layer, and the smallest d * L the convs may leave
FC_WIDTH, MIN_CONV_FEATURES = 32, 32
#: Tab. 1 caption: 5 hidden layers of 30 in g
WIDTH, DEPTH = 30, 5
NORM_KEYS = ("X_min", "X_max", "u_mean", "u_std")
ENCODER_INPUT = "minmax"
KIND = "rom"


def conv_lengths(n_points: int, dim: int) -> list[int]:
    """Output lengths of the encoder's conv layers for an input of ``n_points`` (Tab. 1 caption; module
    doc): a layer is added while ``dim * L_out >= 32``."""
    out, L = [], int(n_points)
    while L >= CONV_KERNEL:
        nxt = (L - CONV_KERNEL) // CONV_STRIDE + 1
        if dim * nxt < MIN_CONV_FEATURES:
            break
        out.append(nxt)
        L = nxt
    return out


def _int(value, what, low=1):
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) or int(value) < low:
        raise ConfigError(f"rom networks: {what} = {value!r} must be an integer >= {low}.")
    return int(value)


@dataclass(frozen=True)
class RomSpec:
    """Sizes of the ROM networks: ``dim`` d (2 or 3), ``latent`` d_hat, ``n_points`` N of the encoder's
    snapshots (None: g only), g's ``width`` and ``depth`` (hidden layers; Tab. 1: 30 and 5)."""

    dim: int
    latent: int
    n_points: int | None = None
    width: int = WIDTH
    depth: int = DEPTH

    def __post_init__(self):
        if self.dim not in (2, 3) or isinstance(self.dim, bool):
            raise ConfigError(f"rom networks: dim = {self.dim!r} must be 2 or 3.")
        _int(self.latent, "latent")
        _int(self.width, "width")
        _int(self.depth, "depth")
        if self.n_points is not None:
            _int(self.n_points, "n_points")

    @property
    def parts(self) -> str:
        return "g" if self.n_points is None else "g+encoder"

    def conv_lengths(self) -> list[int]:
        return [] if self.n_points is None else conv_lengths(self.n_points, self.dim)

    def g_shapes(self) -> dict[str, tuple]:
        d, w = self.dim, self.width
        sizes = [self.latent + d] + [w] * self.depth + [d]
        out = {}
        for i, (n_in, n_out) in enumerate(zip(sizes[:-1], sizes[1:])):
            out[f"g_W{i}"], out[f"g_b{i}"] = (n_out, n_in), (n_out,)
        return out

    def encoder_shapes(self) -> dict[str, tuple]:
        if self.n_points is None:
            return {}
        d, out = self.dim, {}
        lengths = self.conv_lengths()
        for i in range(len(lengths)):
            out[f"e_conv{i}_W"], out[f"e_conv{i}_b"] = (d, d, CONV_KERNEL), (d,)
        L = lengths[-1] if lengths else self.n_points
        out.update({"e_fc0_W": (FC_WIDTH, d * L), "e_fc0_b": (FC_WIDTH,),
                    "e_fc1_W": (self.latent, FC_WIDTH), "e_fc1_b": (self.latent,)})
        return out

    def shapes(self) -> dict[str, tuple]:
        """Every network array, g first, in the order the initialisation draws them."""
        return {**self.g_shapes(), **self.encoder_shapes()}

    def norm_shapes(self) -> dict[str, tuple]:
        return {k: (self.dim,) for k in NORM_KEYS}

    def g_count(self) -> int:
        return int(sum(math.prod(s) for s in self.g_shapes().values()))

    def encoder_count(self) -> int:
        return int(sum(math.prod(s) for s in self.encoder_shapes().values()))

    def metadata(self, seed=None) -> dict[str, str]:
        meta = {"kind": KIND, "parts": self.parts, "dim": str(self.dim), "latent": str(self.latent),
                "width": str(self.width), "depth": str(self.depth)}
        if self.n_points is not None:
            meta.update(n_points=str(self.n_points), encoder_input=ENCODER_INPUT)
        if seed is not None:
            meta["seed"] = str(int(seed))
        return meta


class RomWeights(NamedTuple):
    """What ``load`` returns: ``params`` (network arrays, the trainable pytree), ``norm`` (X_min,
    X_max, u_mean, u_std, each [d]), ``spec`` and ``seed`` (None when the file has none)."""

    params: dict
    norm: dict
    spec: RomSpec
    seed: int | None = None
    #: what the file records of its training (``save(..., training=)``): study, runs and their parameters
    training: dict | None = None


def init_params(spec: RomSpec, seed: int = 0) -> dict[str, np.ndarray]:
    """Xavier-uniform weights, zero biases, fp64 numpy (module doc, App. B)."""
    rng = np.random.default_rng(int(seed))
    out = {}
    for k, s in spec.shapes().items():
        if len(s) == 1:
            out[k] = np.zeros(s)
        else:
            rf = math.prod(s[2:])                 # torch: fan_in = in * kernel, fan_out = out * kernel
            a = math.sqrt(6.0 / (s[1] * rf + s[0] * rf))
            out[k] = rng.uniform(-a, a, size=s)
    return out


def linear_params(spec: RomSpec, A, B, offset: float = 10.0) -> dict[str, np.ndarray]:
    """Weights of g with u~ = B x_hat + A X~ exactly, while |B x_hat + A X~| stays below ``offset``
    per channel (every pre-activation > 0: ELU is the identity there): W0 copies the inputs into the
    first channels plus ``offset``, the hidden layers are identities, the output layer reads [B | A] and
    removes the offset. ``B = I`` (d_hat = d) with ``identity_norm`` is g(X; x_hat) = X + x_hat, the
    rigid-translation manifold the reduced stepper is checked on. Needs width >= d_hat + d."""
    d, m, w = spec.dim, spec.latent + spec.dim, spec.width
    if w < m:
        raise ConfigError(f"rom networks: linear_params needs width >= latent + dim = {m}; the spec has {w}.")
    p = {k: np.zeros(s) for k, s in spec.g_shapes().items()}
    p["g_W0"][:m, :m] = np.eye(m)
    p["g_b0"][:] = offset
    for i in range(1, spec.depth):
        p[f"g_W{i}"] = np.eye(w)
    last = spec.depth
    p[f"g_W{last}"][:, :m] = np.concatenate([np.asarray(B, float), np.asarray(A, float)], axis=1)
    p[f"g_b{last}"] = -p[f"g_W{last}"] @ np.full(w, offset)
    return p


def identity_norm(dim: int) -> dict[str, np.ndarray]:
    """X~ = X and u = u~ (X_min = u_mean = 0, X_max = u_std = 1)."""
    z, o = np.zeros(dim), np.ones(dim)
    return {"X_min": z, "X_max": o.copy(), "u_mean": z.copy(), "u_std": o.copy()}


def fit_norm(X, x) -> dict[str, np.ndarray]:
    """The normaliser of App. B from training data: X_min / X_max of the reference positions X
    ``[N, d]`` and the per-component mean and standard deviation of the displacements u = x - X over
    every snapshot and point (x ``[..., N, d]``). A flat axis of X gets range 1; a displacement component
    with no spread gets the largest component's std (not 1: the std is in metres, and a unit scale would
    turn the network's residual output in that component into metres of error), or 1 if none moves."""
    X = np.asarray(X, dtype=np.float64)
    u = (np.asarray(x, dtype=np.float64) - X).reshape(-1, X.shape[-1])
    lo, hi = X.min(0), X.max(0)
    std = u.std(0)
    fallback = float(std.max()) if np.any(std > 0) else 1.0
    return {"X_min": lo, "X_max": np.where(hi > lo, hi, lo + 1.0), "u_mean": u.mean(0),
            "u_std": np.where(std > 0, std, fallback)}


def _as_numpy(a):
    a = getattr(a, "detach", lambda: a)()
    a = getattr(a, "cpu", lambda: a)()
    return np.asarray(a)


def check(spec: RomSpec, params, norm, where: str) -> None:
    """Refuse (one line) params / norm whose names or shapes do not fit ``spec``, or a normaliser that
    is not finite, has X_max <= X_min or u_std <= 0 in some component."""
    want = spec.shapes()
    got = {k: tuple(np.shape(a)) for k, a in params.items()}
    if got != want:
        diff = [f"{k} missing" for k in want if k not in got] + [f"{k} unexpected" for k in got if k not in want]
        diff += [f"{k} {got[k]} (wants {want[k]})" for k in want if k in got and got[k] != want[k]]
        raise ConfigError(f"{where}: the network arrays do not fit a {spec.dim}D ROM with latent {spec.latent}"
                          f"{'' if spec.n_points is None else f' and an encoder of {spec.n_points} points'}: "
                          f"{', '.join(diff[:4])}{' ...' if len(diff) > 4 else ''}.")
    bad = [k for k, a in params.items() if not np.all(np.isfinite(_as_numpy(a)))]
    if bad:
        raise ConfigError(f"{where}: non-finite values in {', '.join(sorted(bad)[:4])}.")
    missing = [k for k in NORM_KEYS if k not in norm]
    extra = [k for k in norm if k not in NORM_KEYS]
    if missing or extra:
        raise ConfigError(f"{where}: the normaliser needs exactly {', '.join(NORM_KEYS)}; "
                          f"{'missing ' + ', '.join(missing) if missing else 'unexpected ' + ', '.join(extra)}.")
    n = {k: _as_numpy(norm[k]).astype(np.float64) for k in NORM_KEYS}
    wrong = [f"{k} {n[k].shape}" for k in NORM_KEYS if n[k].shape != (spec.dim,)]
    if wrong:
        raise ConfigError(f"{where}: the normaliser arrays must have shape ({spec.dim},): {', '.join(wrong)}.")
    if not all(np.all(np.isfinite(a)) for a in n.values()):
        raise ConfigError(f"{where}: the normaliser has non-finite values.")
    if np.any(n["X_max"] <= n["X_min"]):
        raise ConfigError(f"{where}: the normaliser needs X_max > X_min in every component "
                          f"(X_min = {n['X_min'].tolist()}, X_max = {n['X_max'].tolist()}).")
    if np.any(n["u_std"] <= 0):
        raise ConfigError(f"{where}: the normaliser needs u_std > 0 in every component (u_std = {n['u_std'].tolist()}).")


def save(path, params, norm, spec: RomSpec, seed: int | None = None, training: dict | None = None) -> None:
    """Write params and normaliser (numpy, JAX or torch arrays) as one safetensors file, fp64, with
    ``spec.metadata(seed)`` (module doc) and ``training`` (a JSON-able dict: the study, its training runs
    and their parameters, which ``task=rom_eval`` keeps out of the test set). Refuses, like ``load``,
    what does not fit ``spec``."""
    import json

    from safetensors.numpy import save_file

    where = f"rom.networks.save('{path}')"
    check(spec, params, norm, where)
    arrays = {k: np.ascontiguousarray(_as_numpy(a), dtype=np.float64) for k, a in {**params, **norm}.items()}
    meta = spec.metadata(seed)
    if training is not None:
        meta["training"] = json.dumps(training)
    save_file(arrays, str(path), metadata=meta)


def load(path, expect_dim: int | None = None, expect_latent: int | None = None,
         expect_n_points: int | None = None) -> RomWeights:
    """Read a file of ``save`` as fp64 numpy (``to_jax`` / ``networks_torch.to_torch`` convert it).

    Refuses in one line (``ConfigError``): an unreadable file, another kind, a dimension / latent size /
    encoder size other than ``expect_*``, inconsistent metadata, arrays whose names or shapes do not fit
    the metadata, and a bad normaliser (``check``)."""
    from safetensors import SafetensorError, safe_open

    where = f"rom weights file '{path}'"
    try:
        with safe_open(str(path), framework="numpy") as f:
            meta = dict(f.metadata() or {})
            arrays = {k: np.asarray(f.get_tensor(k), dtype=np.float64) for k in f.keys()}
    except (OSError, ValueError, RuntimeError, SafetensorError) as e:  # SafetensorError is a bare Exception (0.8)
        first = str(e).splitlines()[0] if str(e) else ""
        raise ConfigError(f"{where}: cannot read it ({type(e).__name__}: {first}).") from None
    if meta.get("kind") != KIND:
        raise ConfigError(f"{where}: it is not a ROM network file (metadata kind = {meta.get('kind')!r}, wants '{KIND}').")

    def num(key, required=True):
        if key not in meta:
            if required:
                raise ConfigError(f"{where}: its metadata has no '{key}'.")
            return None
        try:
            return int(meta[key])
        except ValueError:
            raise ConfigError(f"{where}: metadata {key} = {meta[key]!r} is not an integer.") from None

    dim, latent = num("dim"), num("latent")
    for key, have, want, what in (("dim", dim, expect_dim, "dimension"), ("latent", latent, expect_latent, "latent size"),
                                  ("n_points", num("n_points", False), expect_n_points, "encoder's number of points")):
        if want is not None and have != int(want):
            raise ConfigError(f"{where}: the file's {what} is {have}, expected {int(want)}.")
    parts = meta.get("parts", "g")
    if parts not in ("g", "g+encoder") or (parts == "g+encoder") != ("n_points" in meta):
        raise ConfigError(f"{where}: metadata parts = {parts!r} and n_points = {meta.get('n_points')!r} do not "
                          "agree (parts 'g' without n_points, 'g+encoder' with it).")
    if parts == "g+encoder" and meta.get("encoder_input", ENCODER_INPUT) != ENCODER_INPUT:
        raise ConfigError(f"{where}: encoder_input = {meta['encoder_input']!r}; this version feeds the encoder "
                          f"'{ENCODER_INPUT}'-normalised positions only.")
    spec = RomSpec(dim=dim, latent=latent, n_points=num("n_points", False),
                   width=num("width", False) or WIDTH, depth=num("depth", False) or DEPTH) \
        if dim in (2, 3) and latent >= 1 else None
    if spec is None:
        raise ConfigError(f"{where}: metadata dim = {dim}, latent = {latent} (dim must be 2 or 3, latent >= 1).")
    norm = {k: arrays.pop(k) for k in NORM_KEYS if k in arrays}
    check(spec, arrays, norm, where)
    training = None
    if "training" in meta:
        import json

        try:
            training = json.loads(meta["training"])
        except ValueError:
            raise ConfigError(f"{where}: its metadata 'training' is not JSON.") from None
    return RomWeights(arrays, norm, spec, num("seed", False), training)


# ---- JAX ------------------------------------------------------------------------------------------

def to_jax(tree, dtype=None):
    """A dict (or ``RomWeights``' params / norm) of arrays as JAX arrays of ``dtype`` (default: as is)."""
    return {k: jnp.asarray(_as_numpy(a), dtype=dtype) for k, a in tree.items()}


def _n_layers(params, prefix):
    n = 0
    while f"{prefix}{n}" + ("_W" if prefix == "e_conv" else "") in params:
        n += 1
    return n


def _elu(x):
    return jax.nn.elu(x)


def g_mlp(params, inp):
    """The MLP of g on its raw inputs ``[..., d_hat + d]`` = [x_hat, X~] -> u~ ``[..., d]``."""
    n = _n_layers(params, "g_W")
    h = inp
    for i in range(n - 1):
        h = _elu(h @ params[f"g_W{i}"].T + params[f"g_b{i}"])
    return h @ params[f"g_W{n - 1}"].T + params[f"g_b{n - 1}"]


def _inputs(params, norm, X, z):
    X, z = jnp.asarray(X), jnp.asarray(z)
    lead = jnp.broadcast_shapes(X.shape[:-1], z.shape[:-1])
    X = jnp.broadcast_to(X, lead + X.shape[-1:])
    z = jnp.broadcast_to(z, lead + z.shape[-1:])
    Xn = (X - norm["X_min"]) / (norm["X_max"] - norm["X_min"])
    return X, jnp.concatenate([z, Xn], axis=-1)


@jax.jit
def g_apply(params, norm, X, z):
    """x = g(X; x_hat): reference positions X ``[..., d]`` and latents z ``[..., d_hat]`` (leading axes
    broadcast: one latent ``[d_hat]`` for ``[N, d]`` points, or ``[B, 1, d_hat]`` with ``[N, d]``) ->
    deformed positions ``[..., d]`` (module doc)."""
    X, inp = _inputs(params, norm, X, z)
    return X + g_mlp(params, inp) * norm["u_std"] + norm["u_mean"]


@jax.jit
def g_jacobians(params, norm, X, z):
    """(x, F, dx/dx_hat): positions ``[..., d]``, F = dx/dX ``[..., d, d]`` and dx/dx_hat
    ``[..., d, d_hat]``, exact, by forward mode (``jax.jacfwd`` over the MLP's d_hat + d inputs,
    ``vmap`` over points) and the chain through normaliser and standardiser (module doc)."""
    X, inp = _inputs(params, norm, X, z)
    lead, m, d = inp.shape[:-1], inp.shape[-1], X.shape[-1]
    jac = jax.vmap(jax.jacfwd(lambda v: (g_mlp(params, v),) * 2, has_aux=True))
    J, ut = jac(inp.reshape(-1, m))                                   # [P, d, d_hat + d], [P, d]
    J, ut = J.reshape(lead + (d, m)), ut.reshape(lead + (d,))
    s = norm["u_std"][:, None]
    x = X + ut * norm["u_std"] + norm["u_mean"]
    F = jnp.eye(d, dtype=J.dtype) + s * J[..., m - d:] / (norm["X_max"] - norm["X_min"])
    return x, F, s * J[..., : m - d]


def _forward(params, norm, X, z, zdot=None):
    """(x, F[, v]) by forward mode over the tangents they need, the d directions of X (and (zdot, 0)):
    d (+ 1) tangents instead of g_jacobians' d + d_hat (``vmap`` of ``jax.jvp`` over them, as ``jacfwd``)."""
    X, inp = _inputs(params, norm, X, z)
    lead, m, d = inp.shape[:-1], inp.shape[-1], X.shape[-1]
    k = m - d
    flat = inp.reshape(-1, m)
    P = flat.shape[0]
    T = jnp.broadcast_to(jnp.eye(m, dtype=flat.dtype)[k:, None, :], (d, P, m))
    if zdot is not None:
        zd = jnp.broadcast_to(jnp.asarray(zdot, flat.dtype), lead + (k,)).reshape(P, k)
        T = jnp.concatenate([T, jnp.concatenate([zd, jnp.zeros((P, d), flat.dtype)], axis=-1)[None]], axis=0)
    ut, dT = jax.vmap(lambda t: jax.jvp(lambda v: g_mlp(params, v), (flat,), (t,)), out_axes=(None, 0))(T)
    s = norm["u_std"]
    x = X + ut.reshape(lead + (d,)) * s + norm["u_mean"]
    JX = jnp.moveaxis(dT[:d], 0, -1).reshape(lead + (d, d))           # [..., out i, in j]
    F = jnp.eye(d, dtype=JX.dtype) + s[:, None] * JX / (norm["X_max"] - norm["X_min"])
    if zdot is None:
        return x, F
    return x, F, dT[d].reshape(lead + (d,)) * s


@jax.jit
def g_F(params, norm, X, z):
    """(x, F): positions and F = dx/dX, as ``g_jacobians`` without dx/dx_hat (d tangents, not d + d_hat:
    the inverse map's Newton matrix)."""
    return _forward(params, norm, X, z)


@jax.jit
def g_state(params, norm, X, z, zdot):
    """(x, F, v): positions, F = dx/dX and the velocity v = (dx/dx_hat) zdot of a latent velocity ``zdot``
    (broadcast like z), in one forward pass of d + 1 tangents: what a reduced step and Eq. 24 need of g,
    without the [.., d, d_hat] Jacobian (``g_jacobians``' d + d_hat tangents)."""
    return _forward(params, norm, X, z, zdot)


@jax.jit
def g_velocity(params, norm, X, z, zdot):
    """(x, v): positions and the velocity v = (dx/dx_hat) zdot of a latent velocity zdot (Eq. 24's
    velocity term, Eqs. 21/23), by one ``jax.jvp``; shapes as in ``g_apply``."""
    X, inp = _inputs(params, norm, X, z)
    tangent = jnp.concatenate([jnp.broadcast_to(zdot, inp.shape[:-1] + zdot.shape[-1:]),
                               jnp.zeros_like(X)], axis=-1)
    ut, dut = jax.jvp(lambda v: g_mlp(params, v), (inp,), (tangent,))
    return X + ut * norm["u_std"] + norm["u_mean"], dut * norm["u_std"]


def _check_snapshot(params, dim, n):
    n_conv = _n_layers(params, "e_conv")
    L = n
    for _ in range(n_conv):
        L = (L - CONV_KERNEL) // CONV_STRIDE + 1
    if params["e_fc0_W"].shape[1] != dim * L:
        raise ConfigError(f"rom encoder: a snapshot of {n} points leaves {dim} x {L} features, the encoder "
                          f"takes {params['e_fc0_W'].shape[1]} (it was built for another number of points).")
    return n_conv


@jax.jit
def encode(params, norm, x):
    """x_hat = e(x): a snapshot's positions ``[d, N]`` (or a batch ``[B, d, N]``) -> ``[d_hat]`` (or
    ``[B, d_hat]``), module doc; convs by ``jax.lax.conv_general_dilated`` in torch's NCH / OIH layout."""
    x = jnp.asarray(x)
    single = x.ndim == 2
    h = x[None] if single else x
    d = h.shape[1]
    n_conv = _check_snapshot(params, d, h.shape[2])
    h = (h - norm["X_min"][:, None]) / (norm["X_max"] - norm["X_min"])[:, None]
    for i in range(n_conv):
        h = jax.lax.conv_general_dilated(h, params[f"e_conv{i}_W"], (CONV_STRIDE,), "VALID",
                                         dimension_numbers=("NCH", "OIH", "NCH"))
        h = _elu(h + params[f"e_conv{i}_b"][:, None])
    h = h.reshape(h.shape[0], -1)
    h = _elu(h @ params["e_fc0_W"].T + params["e_fc0_b"])
    z = _elu(h @ params["e_fc1_W"].T + params["e_fc1_b"])          # the release's ELU on the latent
    return z[0] if single else z
