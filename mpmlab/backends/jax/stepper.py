"""JAX stepper: one pure ``step(state, params) -> state`` specialised at build time.

Everything the scene does not need is decided in Python before tracing, so it never enters the
compiled program: no ``C`` for PIC/FLIP, no old grid velocity except for FLIP, one law function per
law present, no boundary code for absent boundaries (DESIGN "Skip what a scene doesn't need").
State and parameters are separate pytrees so ``jax.grad`` reaches initial conditions, law
parameters and boundary coefficients alike (issue #4 builds on this).
"""
from __future__ import annotations

import itertools
import time
from functools import partial

import jax

jax.config.update("jax_enable_x64", True)  # fp64 steppers need it; fp32 steppers pass dtypes explicitly

import jax.numpy as jnp
import numpy as np

from ...core.stepper import BaseStepper
from . import boundaries as jbc

DTYPES = {"fp32": jnp.float32, "fp64": jnp.float64}


def bspline_weights(fx):
    """Quadratic B-spline weights and derivatives (in cell units) for fx = x/dx - base in [0.5, 1.5)."""
    w = jnp.stack([0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2], axis=1)  # [N, 3, D]
    dw = jnp.stack([fx - 1.5, -2.0 * (fx - 1.0), fx - 0.5], axis=1)
    return w, dw


class JaxStepper(BaseStepper):
    backend_name = "jax"

    def __init__(self, scene, transfer, precision="fp32", check_every=None):
        super().__init__(scene, transfer, precision, check_every)
        dtype = DTYPES[precision]
        self.dtype = dtype
        D = self.dim
        self.grid_shape = scene.grid_shape
        self.node_count = int(np.prod(self.grid_shape))
        strides = np.cumprod((1,) + self.grid_shape[::-1][:-1])[::-1]
        self._strides = jnp.asarray(strides.copy(), dtype=jnp.int32)
        self._offsets = np.array(list(itertools.product(range(3), repeat=D)), dtype=np.int32)  # [S, D]
        self._laws = []
        for g in self.groups:
            impl = g.law.implementation("jax", "law")(D)
            self._laws.append(impl)
        grid_bcs, self._particle_bcs, self._force_bcs = [], [], []
        for b in scene.boundaries:
            impl = b.implementation("jax", "boundary")(b, scene, dtype)
            {"grid": grid_bcs, "particle_velocity": self._particle_bcs, "particle_force": self._force_bcs}[b.stage].append(impl)
        self._grid_bcs = grid_bcs
        node_idx = np.stack(np.meshgrid(*[np.arange(n) for n in self.grid_shape], indexing="ij"), -1).reshape(-1, D)
        self._node_x = jnp.asarray(scene.origin + node_idx * scene.dx, dtype=dtype)
        self._jit_advance = jax.jit(self._advance_impl, static_argnums=2)
        self._jit_bad = jax.jit(self._bad_impl)

    # ---- state and parameters ----------------------------------------------------------------
    def init(self):
        P = self.particles
        dt = self.dtype
        law_states = []
        for g in self.groups:
            st = g.law.initial_state(g.count, self.dim)
            law_states.append({k: jnp.asarray(v, dtype=dt) for k, v in st.items()})
        state = {"x": jnp.asarray(P.x, dt), "v": jnp.asarray(P.v, dt), "law": tuple(law_states),
                 "t": jnp.asarray(0.0, dt)}
        if self.transfer.needs_affine:
            state["C"] = jnp.zeros((P.count, self.dim, self.dim), dt)
        return state

    def default_params(self):
        """Differentiable parameters: per-group law parameters, particle mass/volume, boundary data."""
        P = self.particles
        return {
            "law": tuple(jnp.asarray(g.params, self.dtype) for g in self.groups),
            "mass": jnp.asarray(P.mass, self.dtype),
            "volume": jnp.asarray(P.volume, self.dtype),
            "gravity": jnp.asarray(self.scene.gravity, self.dtype),
            "boundary": tuple(b.params for b in self._grid_bcs + self._particle_bcs + self._force_bcs),
        }

    @property
    def params(self):
        if not hasattr(self, "_params"):
            self._params = self.default_params()
        return self._params

    # ---- the step ------------------------------------------------------------------------------
    def step_fn(self, state, params):
        """One explicit MLS/APIC/PIC/FLIP/TPIC step (JAX-MPM Sec. 2.2; NCLaw Alg. 3), pure."""
        T = self.transfer
        D, dx, dt = self.dim, self.scene.dx, self.dt
        inv_dx = 1.0 / dx
        x, v = state["x"], state["v"]
        mass, vol = params["mass"], params["volume"]
        N = x.shape[0]
        bc_params = params["boundary"]
        nb = len(self._grid_bcs)

        # stencil -----------------------------------------------------------------------------
        Xp = (x - self._node_x[0]) * inv_dx
        base = jnp.floor(Xp - 0.5).astype(jnp.int32)
        fx = Xp - base
        w1, dw1 = bspline_weights(fx)                                       # [N, 3, D]
        offs = self._offsets                                                # [S, D]
        w = jnp.prod(w1[:, offs, jnp.arange(D)], axis=-1)                    # [N, S]
        gradw = jnp.stack([dw1[:, offs[:, d], d] * jnp.prod(
            jnp.stack([w1[:, offs[:, e], e] for e in range(D) if e != d], -1), -1) for d in range(D)], -1) * inv_dx  # [N,S,D]
        dpos = (offs[None].astype(x.dtype) - fx[:, None, :]) * dx             # x_i - x_p, [N, S, D]
        idx = jnp.sum((base[:, None, :] + offs[None]) * self._strides, axis=-1)  # [N, S]

        # stress (Kirchhoff) from each law present ------------------------------------------------
        tau = jnp.concatenate([jax.vmap(law.kirchhoff)(st, prm) for law, st, prm in
                               zip(self._laws, state["law"], params["law"])], axis=0).astype(x.dtype)  # [N, D, D]

        # P2G ------------------------------------------------------------------------------------
        p_mom = mass[:, None] * v
        mom = w[..., None] * p_mom[:, None, :]                              # [N, S, D]
        if T.affine is not None:
            mom = mom + w[..., None] * mass[:, None, None] * jnp.einsum("pij,psj->psi", state["C"], dpos)
        if T.force == "mls":
            # Hu et al. 2018: f_i = -V M^-1 tau (x_i - x_p) w, M^-1 = 4/dx^2 (quadratic B-spline)
            force = -(4.0 * inv_dx * inv_dx) * vol[:, None, None] * w[..., None] * jnp.einsum("pij,psj->psi", tau, dpos)
        else:
            # JAX-MPM Eq. 12: f_i = -V tau grad w (tau = J sigma, V the reference volume)
            force = -vol[:, None, None] * jnp.einsum("pij,psj->psi", tau, gradw)
        ext = None
        for bc, bp in zip(self._force_bcs, bc_params[nb + len(self._particle_bcs):]):
            f = bc.particle_force(x, mass, state["t"], bp)
            ext = f if ext is None else ext + f
        if ext is not None:
            force = force + w[..., None] * ext[:, None, :]
        G = self.node_count
        flat = idx.reshape(-1)
        grid_m = jnp.zeros(G, x.dtype).at[flat].add((w * mass[:, None]).reshape(-1))
        grid_mv = jnp.zeros((G, D), x.dtype).at[flat].add(mom.reshape(-1, D))
        grid_f = jnp.zeros((G, D), x.dtype).at[flat].add(force.reshape(-1, D))

        # grid update (JAX-MPM Eqs. 13-14) ----------------------------------------------------------
        has_mass = grid_m > 0
        safe_m = jnp.where(has_mass, grid_m, 1.0)[:, None]
        v_old = jnp.where(has_mass[:, None], grid_mv / safe_m, 0.0)
        v_new = jnp.where(has_mass[:, None], v_old + dt * (grid_f / safe_m + params["gravity"]), 0.0)
        for bc, bp in zip(self._grid_bcs, bc_params[:nb]):
            v_new = bc.apply(v_new, self._node_x, grid_m, state["t"], bp)

        # G2P ---------------------------------------------------------------------------------------
        vi = v_new[idx]                                                      # [N, S, D]
        v_pic = jnp.sum(w[..., None] * vi, axis=1)
        new = {"t": state["t"] + dt}
        if T.flip_ratio is not None:
            dv = jnp.sum(w[..., None] * (vi - v_old[idx]), axis=1)
            r = T.flip_ratio
            v_p = r * (v + dv) + (1.0 - r) * v_pic
        else:
            v_p = v_pic
        grad_from_w = None
        if T.grad_v == "gradient" or T.affine == "velocity_gradient":
            grad_from_w = jnp.einsum("psi,psj->pij", vi, gradw)             # JAX-MPM Eq. 18
        if T.affine == "apic":
            C = (4.0 * inv_dx * inv_dx) * jnp.einsum("ps,psi,psj->pij", w, vi, dpos)  # B D^-1, D = dx^2/4 I
            new["C"] = C
        elif T.affine == "velocity_gradient":
            new["C"] = grad_from_w
        grad_v = new["C"] if T.grad_v == "affine" else grad_from_w
        for bc, bp in zip(self._particle_bcs, bc_params[nb:nb + len(self._particle_bcs)]):
            v_p = bc.apply_particles(v_p, state["t"] + dt, bp)
            # a prescribed particle velocity also moves the particle with it
            v_pic = bc.apply_particles(v_pic, state["t"] + dt, bp)
        new["x"] = x + dt * v_pic                                             # JAX-MPM Eq. 17
        new["v"] = v_p

        # law update per material block ------------------------------------------------------------
        laws = []
        for g, law, st, prm in zip(self.groups, self._laws, state["law"], params["law"]):
            gv = grad_v[g.start:g.stop]
            upd = jax.vmap(law.update, in_axes=(0, 0, None, 0))(st, gv, dt, prm)
            # a law (or a plugin's law) may build constants in float64: keep the state in the stepper's precision
            laws.append({k: a.astype(x.dtype) for k, a in upd.items()})
        new["law"] = tuple(laws)
        return new

    def _advance_impl(self, state, params, steps):
        def body(s, _):
            return self.step_fn(s, params), None

        if steps == 1:
            return self.step_fn(state, params)
        state, _ = jax.lax.scan(body, state, None, length=steps)
        return state

    def _advance(self, state, steps):
        return self._jit_advance(state, self.params, steps)

    def _block(self, state):
        jax.block_until_ready(state)

    # ---- guards --------------------------------------------------------------------------------
    def _bad_impl(self, state):
        lo, hi = self.scene.inner_bounds
        bad = ~jnp.all(jnp.isfinite(state["x"])) | ~jnp.all(jnp.isfinite(state["v"]))
        bad = bad | jnp.any((state["x"] < lo) | (state["x"] >= hi))
        for st in state["law"]:
            for k, a in st.items():
                bad = bad | ~jnp.all(jnp.isfinite(a))
            if "J" in st:
                bad = bad | jnp.any(st["J"] <= 0)
            elif "F" in st:
                bad = bad | jnp.any(jnp.linalg.det(st["F"]) <= 0)
        return bad

    def _is_bad(self, state) -> bool:
        return bool(self._jit_bad(state))

    # ---- numpy views ------------------------------------------------------------------------------
    def to_numpy(self, state):
        out = {"x": np.asarray(state["x"]), "v": np.asarray(state["v"]), "t": float(state["t"])}
        if "C" in state:
            out["C"] = np.asarray(state["C"])
        for name in ("F", "J", "sigma", "eps_p"):
            parts = [(g, st[name]) for g, st in zip(self.groups, state["law"]) if name in st]
            if parts:
                out[name] = np.concatenate([np.asarray(a) for _, a in parts])
                out[name + "_particles"] = np.concatenate([np.arange(g.start, g.stop) for g, _ in parts])
        return out
