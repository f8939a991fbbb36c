"""NCLaw, neural constitutive laws (Ma et al., ICML 2023): an elastic and a plastic network with
shared (group-level) weights, rotation-equivariant and exactly at rest at F = I.

Architecture (paper Sec. 3.3 and App. C, Alg. 4; the release ``nclaw/material/meta.py``,
``InvariantFullMeta{Elasticity,Plasticity}``; ``/work/shared/notes/nclaw-rom.md`` Sec. 1.1):

* each network is a bias-free MLP  D + D^2 + 1 -> width -> width -> D^2  (3 linear layers, exact erf
  GELU after both hidden ones), Xavier-uniform initial weights (``seed``);
* inputs (rotation invariants, App. C.2 Eqs. 22-30), shifted so they vanish at rest (Sec. 3.3
  "undeformed state equilibrium"): sigma - 1 (singular values of F), vec(F^T F - I), det F - 1;
* output: T1 (D x D, row-major), T = (T1 + T1^T)/2, R = U V^T from the polar decomposition
  (Alg. 4 lines 1-5; App. C.3 Eqs. 31-33 prove Y = R T equivariant);
* elastic (Alg. 4 line 6): P = R T; the stepper's Kirchhoff stress is tau = P F^T (the release
  returns P F^T; NCLaw Alg. 2 line 1). tau is NOT symmetric in general (T need not commute with
  S = V Sigma V^T), as in the release: ``symmetric_stress = False``;
* plastic (Alg. 2 line 3, Alg. 4 line 9, App. C.3 Eqs. 34-37): F_trial = (I + dt grad_v) F, then
  F <- F_trial + alpha R T with R, T of the plastic network at F_trial, alpha = 1e-3 (App. C.1).

At F = I every input is 0, GELU(0) = 0 and there is no bias, so tau = 0 and F_new = F_trial exactly.
Derivatives are finite at F = I and at repeated singular values: R's derivative is the spectral one
(``backends.*.linalg.polar``), sigma's is ds_i = (U^T dF V)_ii (``singular_values``), where the SVD's
own derivative divides by s_i^2 - s_j^2. (The release zeroes NaN gradients with ``nan_to_num_``; mpmlab
does not.)

Ablations (paper Sec. 4.5): ``no_rotation`` feeds vec(F - I) (D^2 inputs) and uses the raw output as
P (elastic: tau = P F^T; plastic: F_trial + alpha P), no R, no symmetrisation (the release's
``PlainMeta*``); ``no_undeformed`` feeds the raw invariants sigma, vec(F^T F), det F (or vec F) and
adds biases (initially zero) to every layer. Note: the release's ``InvariantFullMetaPlasticity``
ignores ``normalize_input``, so there "no-undeformed" changes only the elastic network; mpmlab applies
it to both, as the paper describes.

Shared weights (``weight_shapes``): ``e_W1 [width, n_in]``, ``e_W2 [width, width]``, ``e_W3 [D^2,
width]`` for the elastic net and ``p_W*`` for the plastic one (torch ``Linear`` layout: [out, in]),
plus ``e_b*`` / ``p_b*`` with ``no_undeformed``: 11,008 numbers in 3D, 9,600 in 2D at width 64.
No per-particle parameters: stresses come out in Pa directly (the release has no output scaling).

``weights_file``: a safetensors file with those arrays; its metadata records law, dim, variant,
width, alpha and seed (``save_weights``). A file whose dim, variant or shapes do not fit the law
instance, or whose alpha differs from the instance's, is refused in one line. The same file serves
the reference, JAX and Warp.

Time step: ``dt: auto`` takes the wave speed from the elastic network's tangent at F = I (the largest
acoustic-tensor eigenvalue over directions, ``instance_wave_speed``); an untrained network is very
soft, so give a fixed dt for training runs.

Speed (``benchmarks/nclaw.md`` "Speed", ``benchmarks/README.md`` "NCLaw on Warp"): on Warp the
networks run inside the fused G2P + law kernel on 64-wide Warp vectors (``weight_views``: column and
row copies of the matrices), with a vectorised rational erf in fp32 (libm's exact erf in fp64). That
was measured against batched torch evaluation between kernels (slower at 1,000 particles on the CPU
even before the kernel split it needs) and kept. 1000 steps at 1,000 particles on one shared CPU
core: 2.8-3.3 s vs 1.1-1.25 s for fixed_corotated (2.49-2.67x, load average 2-4); JAX 1.88-1.95x.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from ...core.errors import ConfigError
from ...core.interfaces import AbstractConstitutiveLaw
from .._common import DEFORMATION_GRADIENT, builtin_implementations
from . import reference as _reference

NETS = ("e", "p")     # elastic, plastic


@dataclass(frozen=True)
class Law(AbstractConstitutiveLaw):
    """NCLaw (Ma et al. 2023): tau = R T(F) F^T and F <- F_trial + alpha R T_p(F_trial) (module doc)."""

    name: ClassVar[str] = "nclaw"
    params = ()
    #: F is guarded for finiteness only, not det F > 0: the networks are defined for any F (the release
    #: has no guard), and an untrained law ("ours-init", NCLaw Tab. 1) inverts elements while its
    #: positions stay finite: its error is a number, not a divergence
    state = (dataclasses.replace(DEFORMATION_GRADIENT, check=None),)
    plastic = True
    reference = _reference
    #: tau = R T F^T is not symmetric in general (the release does not symmetrise it)
    symmetric_stress: ClassVar[bool] = False
    implementations: ClassVar[dict] = builtin_implementations("nclaw")
    #: the exhaustive suites (every law x transfer x dimension: tests/test_conformance.py,
    #: tests/test_grad_warp.py) leave this law out: each fused Warp kernel with its two 64-wide networks
    #: compiles in ~10 s. tests/test_nclaw_law.py runs the kit on it (2D, MLS, NCLaw's transfer)
    test_transfers: ClassVar[tuple] = ()

    #: hidden width of both networks
    width: int = 64
    #: plastic step size alpha (F <- F_trial + alpha R T; NCLaw App. C.1)
    alpha: float = 1.0e-3
    #: seed of the Xavier-uniform initial weights (ignored with ``weights_file``)
    seed: int = 0
    #: ablation "no-rotation": input vec(F - I), output P used as is (no R, no symmetrisation)
    no_rotation: bool = False
    #: ablation "no-undeformed": raw inputs (sigma, F^T F, det F; or F) and biases in every layer
    no_undeformed: bool = False
    #: a safetensors file of the weights (``save_weights``); overrides ``seed``
    weights_file: str = ""

    def __post_init__(self):
        if not (isinstance(self.width, (int, np.integer)) and int(self.width) >= 1):
            raise ConfigError(f"law '{self.name}': width = {self.width!r} must be an integer >= 1.")
        if not (isinstance(self.alpha, (int, float)) and math.isfinite(float(self.alpha))):
            raise ConfigError(f"law '{self.name}': alpha = {self.alpha!r} must be a finite number.")

    # ---- configuration -----------------------------------------------------------------------
    def code_key(self):
        """The kernels depend on the architecture and alpha, not on where the weights come from."""
        return tuple((k, v) for k, v in self._config_key() if k not in ("weights_file", "seed"))

    @property
    def variant(self) -> str:
        """``invariant`` (the paper's method), ``no_rotation``, ``no_undeformed`` or both."""
        parts = [n for n in ("no_rotation", "no_undeformed") if getattr(self, n)]
        return "+".join(parts) or "invariant"

    def n_inputs(self, dim: int) -> int:
        return dim * dim if self.no_rotation else dim + dim * dim + 1

    def weight_shapes(self, dim):
        w, n, o = int(self.width), self.n_inputs(dim), dim * dim
        out = {}
        for net in NETS:
            out.update({f"{net}_W1": (w, n), f"{net}_W2": (w, w), f"{net}_W3": (o, w)})
            if self.no_undeformed:
                out.update({f"{net}_b1": (w,), f"{net}_b2": (w,), f"{net}_b3": (o,)})
        return out

    def weight_views(self, dim):
        """The Warp form's vector copies (``warp.py``): each W as columns (the forward's a += W[:, j] x_j)
        and as rows (the adjoint's g += W[i, :] g_i), each bias as one vector; and each W's gradient as
        rows (the adjoint's dW[i, :] += g_i x, a vector add per row)."""
        out = {}
        for net in NETS:
            for k in ("W1", "W2", "W3"):
                out.update({f"{net}_{k}c": (f"{net}_{k}", "cols"), f"{net}_{k}r": (f"{net}_{k}", "rows"),
                            f"{net}_{k}g": (f"{net}_{k}", "grad_rows")})
            if self.no_undeformed:
                out.update({f"{net}_{k}v": (f"{net}_{k}", "whole") for k in ("b1", "b2", "b3")})
        return out

    def weight_count(self, dim: int) -> int:
        return int(sum(np.prod(s) for s in self.weight_shapes(dim).values()))

    def weights_metadata(self, dim):
        return {"law": self.name, "dim": str(int(dim)), "variant": self.variant, "width": str(int(self.width)),
                "alpha": repr(float(self.alpha)), "seed": str(int(self.seed))}

    def initial_weights(self, dim):
        if self.weights_file:
            return self._load(dim)
        rng = np.random.default_rng(int(self.seed))
        out = {}
        for k, s in self.weight_shapes(dim).items():
            if "_W" in k:   # torch.nn.init.xavier_uniform_: U(-a, a), a = sqrt(6 / (fan_in + fan_out))
                a = math.sqrt(6.0 / (s[0] + s[1]))
                out[k] = rng.uniform(-a, a, size=s)
            else:
                out[k] = np.zeros(s)
        return out

    def _load(self, dim):
        from safetensors import SafetensorError, safe_open

        path = self.weights_file
        where = f"law '{self.name}' weights_file '{path}'"
        try:
            with safe_open(path, framework="numpy") as f:
                meta = dict(f.metadata() or {})
                arrays = {k: np.asarray(f.get_tensor(k), dtype=np.float64) for k in f.keys()}
        except (OSError, ValueError, RuntimeError, SafetensorError) as e:  # SafetensorError: a bare Exception (0.8)
            raise ConfigError(f"{where}: cannot read it ({type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}).") from None
        want = self.weights_metadata(dim)
        if meta.get("law", self.name) != self.name:
            raise ConfigError(f"{where}: the file holds weights of law '{meta['law']}', not '{self.name}'.")
        for key, what in (("dim", "dimension"), ("variant", "variant"), ("width", "width")):
            if key in meta and meta[key] != want[key]:
                raise ConfigError(f"{where}: the file is for {what} {meta[key]}, this law instance is {what} "
                                  f"{want[key]} (options no_rotation/no_undeformed/width, scene dim).")
        if "alpha" in meta and not float(meta["alpha"]) == float(self.alpha):
            raise ConfigError(f"{where}: the file was made with alpha = {meta['alpha']}, this law instance has "
                              f"alpha = {float(self.alpha)!r}; set material.options.alpha to the file's value.")
        shapes = self.weight_shapes(dim)
        got = {k: tuple(a.shape) for k, a in arrays.items()}
        if got != {k: tuple(s) for k, s in shapes.items()}:
            diff = sorted(set(got) ^ set(shapes)) or [f"{k} {got[k]} (wants {tuple(shapes[k])})" for k in shapes
                                                       if got[k] != tuple(shapes[k])]
            raise ConfigError(f"{where}: its arrays do not fit a {dim}D '{self.variant}' nclaw of width "
                              f"{self.width}: {', '.join(map(str, diff[:4]))}.")
        return arrays

    # ---- where the law was trained -----------------------------------------------------------
    def trained_range(self) -> dict | None:
        """The states its training rollout visited (``mpmlab.nclaw.probe.state_range``: largest deviatoric
        log-stretch, its largest 99th percentile, J's range), as ``task=nclaw_train`` records it in the
        weight file (metadata ``state_range``); None without a weight file or for a file written before
        it was recorded."""
        if not self.weights_file:
            return None
        from ...nclaw.probe import read_state_range

        try:
            return read_state_range(self.weights_file)
        except Exception:      # unreadable here: the note says it is not recorded (loading refused it already)
            return None

    def divergence_note(self, fields, particle):
        """Where the failed run took this learned law: the deviatoric log-stretch max_i |log(s_i / J^(1/D))|
        and J of its particles, beside the range its training visited (benchmarks/nclaw.md, "WATER (c)":
        a learned return map brings back only stretches near those it was trained on)."""
        from .._linalg_np import deviatoric_stretch

        F = fields.get("F")
        if F is None or not len(F):
            return None
        dev, J = deviatoric_stretch(F)
        fin = np.isfinite(dev)
        at = (f"the failing particle's deviatoric log-stretch {dev[particle]:.3g} (J {J[particle]:.3g}), "
              if 0 <= particle < len(dev) else "")
        seen = (f"largest {np.max(dev[fin]):.3g}, 99th percentile {np.percentile(dev[fin], 99):.3g}"
                if fin.any() else "none finite")
        inv = int(np.sum(~fin))
        line = (f"law 'nclaw' (learned, {self.weights_file or f'untrained, seed {self.seed}'}): {at}{seen} over "
                f"its {len(dev)} particles" + (f", {inv} inverted or non-finite" if inv else ""))
        rng = self.trained_range()
        if not self.weights_file:
            return line + "; untrained networks (no weight file): there is no training range to compare with"
        if rng is None:
            return (line + "; the weight file records no training range (task=nclaw_train records it); check the "
                           "learned return map's reach with mpmlab.nclaw.probe.return_map_reach")
        if "deviatoric_stretch_max" not in rng:
            where = f" at step {rng['step']}" if "step" in rng else ""
            return line + (f"; its own training rollout (no teacher forcing) diverged{where} when it was recorded: "
                           f"the learned law is not stable even on its training scene")
        worst = float(np.max(dev))              # inf with an inverted or non-finite particle
        outside = worst > rng["deviatoric_stretch_max"] or float(np.nanmin(J)) < rng["J_min"] \
            or float(np.nanmax(J)) > rng["J_max"]
        trained = (f"its training rollout reached a deviatoric log-stretch of {rng['deviatoric_stretch_max']:.3g} "
                   f"and J {rng['J_min']:.3g} to {rng['J_max']:.3g}")
        if rng.get("inverted"):
            trained += f" and already inverted {rng['inverted']} particle-frames (the law is unsound even there)"
        if outside:
            return (line + f"; {trained}: the run took the learned law outside the states it was trained on, "
                           f"where it is not to be trusted (check its return map's reach: "
                           f"mpmlab.nclaw.probe.return_map_reach); the numerics' advice may not apply")
        return line + f"; {trained}: the states are within that range"

    # ---- time step ---------------------------------------------------------------------------
    @classmethod
    def wave_speed(cls, params, density):
        """The default configuration's wave speed (seed 0, 3D); scenes use ``instance_wave_speed``."""
        law = cls()
        return law.instance_wave_speed(params, density, 3, law.initial_weights(3))

    def instance_wave_speed(self, params, density, dim, weights):
        """sqrt(max_n lambda_max(A(n)) / rho), A(n)_ik = C_ijkl n_j n_l the acoustic tensor of the elastic
        network's tangent C = dP/dF at F = I (``reference.rest_tangent``), over 2,000 directions (3D) or
        720 (2D); |eigenvalues|, so an unstable (negative) stiffness still bounds dt."""
        C = _reference.rest_tangent(weights, dim, law=self)            # [D, D, D, D]: dP_ij / dF_kl
        if dim == 2:
            th = np.linspace(0.0, np.pi, 720, endpoint=False)
            n = np.stack([np.cos(th), np.sin(th)], 1)
        else:
            k = np.arange(2000) + 0.5
            phi = np.arccos(1.0 - 2.0 * k / 2000)
            th = np.pi * (1.0 + 5.0 ** 0.5) * k
            n = np.stack([np.cos(th) * np.sin(phi), np.sin(th) * np.sin(phi), np.cos(phi)], 1)
        A = np.einsum("ijkl,nj,nl->nik", C, n, n)
        A = 0.5 * (A + np.swapaxes(A, 1, 2))
        lam = np.max(np.abs(np.linalg.eigvalsh(A)))
        return float(math.sqrt(lam / density))


def save_weights(path: str, weights, law: Law | None = None, dim: int = 3) -> None:
    """Write nclaw weights (numpy, JAX arrays or torch tensors) as a safetensors file whose metadata
    records the law instance's dim, variant, width, alpha and seed (``Law.weights_metadata``)."""
    from safetensors.numpy import save_file

    law = Law() if law is None else law
    arrays = {k: np.ascontiguousarray(np.asarray(getattr(a, "detach", lambda: a)(), dtype=np.float64))
              for k, a in weights.items()}
    law.check_weights(arrays, dim, f"nclaw.save_weights('{path}')")
    save_file(arrays, str(path), metadata=law.weights_metadata(dim))
