"""Torch counterparts of ``mpmlab.rom.networks`` (the ROM's g and encoder; Chen et al. 2023 Sec. 4,
Tab. 1, App. B): the same dicts of arrays (torch ``Linear`` / ``Conv1d`` layouts), the same file, the
same spec; for the Warp side, whose online stage evaluates g in batched torch (notes 2.8).

Jacobians by forward mode (the tangent carried through the layers, batched over points), chained
through the normaliser and standardiser as in ``networks.g_jacobians``.
"""
from __future__ import annotations

import torch
import torch.nn.functional as tF
from torch.func import jvp

from . import networks as _spec
from .networks import CONV_STRIDE, RomWeights


def to_torch(tree, dtype=torch.float32, device="cpu"):
    """A dict of arrays (numpy, as ``networks.load`` returns them) as torch tensors."""
    return {k: torch.as_tensor(_spec._as_numpy(a), dtype=dtype, device=device) for k, a in tree.items()}


def load(path, expect_dim=None, expect_latent=None, expect_n_points=None, dtype=torch.float32,
         device="cpu") -> RomWeights:
    """``networks.load`` (same checks, same one-line refusals), params and norm as torch tensors."""
    w = _spec.load(path, expect_dim=expect_dim, expect_latent=expect_latent, expect_n_points=expect_n_points)
    return RomWeights(to_torch(w.params, dtype, device), to_torch(w.norm, dtype, device), w.spec, w.seed)


def g_mlp(params, inp):
    """The MLP of g on ``[..., d_hat + d]`` = [x_hat, X~] -> u~ ``[..., d]``."""
    n = _spec._n_layers(params, "g_W")
    h = inp
    for i in range(n - 1):
        h = tF.elu(tF.linear(h, params[f"g_W{i}"], params[f"g_b{i}"]))
    return tF.linear(h, params[f"g_W{n - 1}"], params[f"g_b{n - 1}"])


def _inputs(norm, X, z):
    lead = torch.broadcast_shapes(X.shape[:-1], z.shape[:-1])
    X = X.expand(lead + X.shape[-1:])
    z = z.expand(lead + z.shape[-1:])
    Xn = (X - norm["X_min"]) / (norm["X_max"] - norm["X_min"])
    return X, torch.cat([z, Xn], dim=-1)


def g_apply(params, norm, X, z):
    """x = g(X; x_hat), shapes and broadcasting as ``networks.g_apply``."""
    X, inp = _inputs(norm, X, z)
    return X + g_mlp(params, inp) * norm["u_std"] + norm["u_mean"]


def _carry(params, h, T0=None):
    """The MLP on points ``h`` [P, m] and its derivative along the input tangents ``T0`` [m, t] (None: the
    identity, the whole Jacobian), carried forward layer by layer (tangent ``[P, width, t]``, ELU' = 1
    above 0 and exp below): the same forward mode as ``jacfwd``, written out because ``vmap(jacfwd)``'s
    eager dispatch costs ten times the arithmetic at the reduced model's sizes. Returns (u~ [P, d],
    du~ [P, d, t])."""
    n = _spec._n_layers(params, "g_W")
    J = None
    for i in range(n):
        W = params[f"g_W{i}"]
        pre = tF.linear(h, W, params[f"g_b{i}"])
        if J is None:
            Jp = (W if T0 is None else W @ T0).expand(h.shape[0], -1, -1)
        else:
            Jp = torch.matmul(W, J)
        if i == n - 1:
            return pre, Jp
        h = tF.elu(pre)
        J = torch.where(pre > 0, 1.0, torch.exp(torch.clamp(pre, max=0.0)))[..., None] * Jp


def g_jacobians(params, norm, X, z):
    """(x, F ``[..., d, d]``, dx/dx_hat ``[..., d, d_hat]``) as ``networks.g_jacobians``."""
    X, inp = _inputs(norm, X, z)
    lead, m, d = inp.shape[:-1], inp.shape[-1], X.shape[-1]
    ut, J = _carry(params, inp.reshape(-1, m))
    J, ut = J.reshape(lead + (d, m)), ut.reshape(lead + (d,))
    s = norm["u_std"][:, None]
    x = X + ut * norm["u_std"] + norm["u_mean"]
    F = torch.eye(d, dtype=J.dtype, device=J.device) + s * J[..., m - d:] / (norm["X_max"] - norm["X_min"])
    return x, F, s * J[..., : m - d]


def _forward(params, norm, X, z, zdot=None):
    """(x, F[, v]) as ``networks._forward``: the tangents of X's d directions (and (zdot, 0)) only."""
    X, inp = _inputs(norm, X, z)
    lead, m, d = inp.shape[:-1], inp.shape[-1], X.shape[-1]
    k = m - d
    T0 = torch.eye(m, dtype=inp.dtype, device=inp.device)[:, k:]
    if zdot is not None:
        T0 = torch.cat([T0, torch.cat([zdot.reshape(k, 1).to(inp.dtype),
                                       torch.zeros(d, 1, dtype=inp.dtype, device=inp.device)])], dim=1)
    ut, J = _carry(params, inp.reshape(-1, m), T0)
    ut, J = ut.reshape(lead + (d,)), J.reshape(lead + J.shape[-2:])
    x = X + ut * norm["u_std"] + norm["u_mean"]
    s = norm["u_std"][:, None]
    F = torch.eye(d, dtype=J.dtype, device=J.device) + s * J[..., :d] / (norm["X_max"] - norm["X_min"])
    if zdot is None:
        return x, F
    return x, F, J[..., d] * norm["u_std"]


def g_F(params, norm, X, z):
    """(x, F) as ``networks.g_F``."""
    return _forward(params, norm, X, z)


def g_state(params, norm, X, z, zdot):
    """(x, F, v) as ``networks.g_state``, for one latent velocity ``zdot`` [d_hat]."""
    return _forward(params, norm, X, z, zdot)


def g_velocity(params, norm, X, z, zdot):
    """(x, v = (dx/dx_hat) zdot) by one ``torch.func.jvp``, as ``networks.g_velocity``."""
    X, inp = _inputs(norm, X, z)
    tangent = torch.cat([zdot.expand(inp.shape[:-1] + zdot.shape[-1:]), torch.zeros_like(X)], dim=-1)
    ut, dut = jvp(lambda v: g_mlp(params, v), (inp,), (tangent,))
    return X + ut * norm["u_std"] + norm["u_mean"], dut * norm["u_std"]


def encode(params, norm, x):
    """x_hat = e(x): ``[d, N]`` (or ``[B, d, N]``) -> ``[d_hat]`` (or ``[B, d_hat]``), as ``networks.encode``."""
    single = x.dim() == 2
    h = x[None] if single else x
    n_conv = _spec._check_snapshot(params, h.shape[1], h.shape[2])
    h = (h - norm["X_min"][:, None]) / (norm["X_max"] - norm["X_min"])[:, None]
    for i in range(n_conv):
        h = tF.elu(tF.conv1d(h, params[f"e_conv{i}_W"], params[f"e_conv{i}_b"], stride=CONV_STRIDE))
    h = tF.elu(tF.linear(h.flatten(1), params["e_fc0_W"], params["e_fc0_b"]))
    z = tF.elu(tF.linear(h, params["e_fc1_W"], params["e_fc1_b"]))   # the release's ELU on the latent
    return z[0] if single else z
