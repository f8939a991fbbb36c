"""JAX stepper: one pure ``step(state, params) -> state`` specialised at build time.

Everything the scene does not need is decided in Python before tracing, so it never enters the
compiled program: no ``C`` for PIC/FLIP, no old grid velocity except for FLIP, one law function per
law present, no boundary code for absent boundaries (DESIGN "Skip what a scene doesn't need").
State and parameters are separate pytrees so ``jax.grad`` reaches initial conditions, law
parameters and boundary coefficients alike (issue #4 builds on this).
"""
from __future__ import annotations

import itertools
from types import SimpleNamespace

import jax

jax.config.update("jax_enable_x64", True)  # fp64 steppers need it; fp32 steppers pass dtypes explicitly

import jax.numpy as jnp
import numpy as np

from ...core.errors import ConfigError
from ...core.stepper import BaseStepper
from .adjoints import ADJOINTS
from . import adjoints
from .laws import law_functions, weights_of
from .transfers import transfer_functions

DTYPES = {"fp32": jnp.float32, "fp64": jnp.float64}


@jax.custom_jvp
def per_mass(q, m):
    """q / m for grid momentum (or force) q [G, K] and node mass m [G, 1] > 0.

    Its derivative is written with the quotient itself, d(q/m) = (dq - (q/m) dm) / m, instead of JAX's
    -q dm / m^2: at free-surface nodes reached only by a stencil's far tail, m can be ~1e-20 in fp32, and
    m^2 underflows to 0 (XLA CPU flushes subnormals), turning the reverse pass into inf/NaN (seen once
    each in two 200-epoch MLP fits, JAX-MPM Sec. 5.2) while the forward value is fine."""
    return q / m


@per_mass.defjvp
def _per_mass_jvp(primals, tangents):
    q, m = primals
    dq, dm = tangents
    v = q / m
    return v, (dq - v * dm) / m


_materialize = adjoints.materialize      # (kept under its old name)


class JaxStepper(BaseStepper):
    backend_name = "jax"

    def __init__(self, scene, transfer, precision="fp32", check_every=None, adjoints="custom", shape="quadratic"):
        super().__init__(scene, transfer, precision, check_every)
        if adjoints not in ADJOINTS:
            raise ConfigError(f"adjoints = {adjoints!r}: 'custom' (hand-written P2G/G2P adjoints, "
                              f"backends/jax/adjoints.py) or 'derived' (JAX's own).")
        #: reverse mode through P2G / G2P: "custom" (hand-written transposes, adjoints.py) or "derived"
        #: (XLA's); read when a step is traced, so set it before the first trace (tests build one of each)
        self.adjoints = adjoints
        dtype = DTYPES[precision]
        self.dtype = dtype
        D = self.dim
        self.grid_shape = scene.grid_shape
        self.node_count = int(np.prod(self.grid_shape))
        strides = np.cumprod((1,) + self.grid_shape[::-1][:-1])[::-1]
        self._strides = jnp.asarray(strides.copy(), dtype=jnp.int32)
        # the shape function (mpmlab.shapes; issue 19): its window, its weights and, for a shape that uses the
        # particle size (uGIMP), each particle's half width lp in cells (fixed at its initial value: a
        # constant of the run, params["lp"], never a control)
        from ...shapes import inner_bounds, resolve

        self.shape, lp = resolve(shape, transfer, D, scene.dx, self.particles.volume)
        #: CPDI (``kind = "corners"``): P2G / G2P over the 2^D corners of each particle's domain, carried as
        #: ``state["domain"]`` (mpmlab/shapes/cpdi/reference.py)
        self.corners = self.shape.kind == "corners"
        self._shape_fns = self.shape.implementation("jax", "shape")(self.shape, D)
        self._lp = None if lp is None else np.asarray(lp, np.float64)
        #: the region a particle may occupy: its width^D window must stay on the grid (the scene's own
        #: ``inner_bounds`` for the 3-node shapes; one cell less on each side for cubic B-splines)
        self.inner_bounds = inner_bounds(self.shape, scene)
        # refuses particles (CPDI: domain corners) outside it, one line
        inner_bounds(self.shape, scene, self.particles.x, self.initial_domain() if self.corners else None)
        W = int(self.shape.width)
        self._offsets = np.array(list(itertools.product(range(W), repeat=D)), dtype=np.int32)  # [S, D]
        # the scheme's p2g / g2p (mpmlab/transfers/<name>/jax.py), checked with the Dinv it will see
        self._tf = transfer_functions(transfer, D, dtype, per_particle_Dinv=self.shape.inv_D_cells is None)
        if self.corners:
            S = self._shape_fns.signs                                           # [2^D, D]
            self._corner_signs = S
            self._offsets = np.array(list(itertools.product(range(2), repeat=D)), dtype=np.int32)
        self._laws = []
        for g in self.groups:
            self._laws.append(law_functions(g.law, D, dtype))
        grid_bcs, self._particle_bcs, self._force_bcs = [], [], []
        for b in scene.boundaries:
            impl = b.implementation("jax", "boundary")(b, scene, dtype)
            {"grid": grid_bcs, "particle_velocity": self._particle_bcs, "particle_force": self._force_bcs}[b.stage].append(impl)
        self._grid_bcs = grid_bcs
        # params["boundary"] is ordered grid, particle-velocity, particle-force; controls() use scene order
        stages = [b.stage for b in scene.boundaries]
        self._bc_order = [i for st in ("grid", "particle_velocity", "particle_force")
                          for i, s_ in enumerate(stages) if s_ == st]
        node_idx = np.stack(np.meshgrid(*[np.arange(n) for n in self.grid_shape], indexing="ij"), -1).reshape(-1, D)
        self._node_x = jnp.asarray(scene.origin + node_idx * scene.dx, dtype=dtype)
        #: each material group's rows of the per-particle arrays step_fn sees (a sharded stepper's
        #: step_fn sees one device's block: backends/jax/sharding.py)
        self._group_slices = [slice(g.start, g.stop) for g in self.groups]
        self._jit_advance = jax.jit(self._advance_impl, static_argnums=2)
        self._jit_bad = jax.jit(self._bad_impl)

    # ---- state and parameters ----------------------------------------------------------------
    def init(self):
        P = self.particles
        dt = self.dtype
        law_states = []
        for g in self.groups:
            st = g.initial_state(self.dim)         # the law's rest state, with the bodies' initial F
            law_states.append({k: jnp.asarray(v, dtype=dt) for k, v in st.items()})
        state = {"x": jnp.asarray(P.x, dt), "v": jnp.asarray(P.v, dt), "law": tuple(law_states),
                 "t": jnp.asarray(0.0, dt)}
        if self.transfer.needs_affine:
            state["C"] = jnp.asarray(self.initial_C(), dt)
        if self.corners:
            state["domain"] = jnp.asarray(self.initial_domain(), dt)
        return state

    def default_params(self):
        """Differentiable parameters: per-group law parameters, particle mass/volume, boundary data."""
        P = self.particles
        return {
            "law": tuple(jnp.asarray(g.params, self.dtype) for g in self.groups),
            "law_weights": tuple(weights_of(g, self.dtype) for g in self.groups),
            "mass": jnp.asarray(P.mass, self.dtype),
            "volume": jnp.asarray(P.volume, self.dtype),
            "gravity": jnp.asarray(self.scene.gravity, self.dtype),
            "boundary": tuple(b.params for b in self._grid_bcs + self._particle_bcs + self._force_bcs),
            **self._shape_params(),
        }

    def _shape_params(self) -> dict:
        """``{"lp": [N]}`` for a shape function that uses the particle size (uGIMP), else ``{}``: a constant
        of the run kept with the per-particle parameters so that a sharded stepper lays it out with them
        (``step_fn`` stops its gradient; it is not a control)."""
        return {} if self._lp is None else {"lp": jnp.asarray(self._lp, self.dtype)}

    # ---- the state's layout (identity here; a sharded stepper reorders and pads particles) ---------
    def to_layout(self, state=None, params=None):
        """(state, params) in scene order -> the layout ``step_fn`` works on (either may be None)."""
        return state, params

    def to_scene_order(self, state):
        """A state of ``step_fn``'s layout -> scene order (what observations and ``to_numpy`` read)."""
        return state

    def _sum_grid(self, grid):
        """The P2G sums of the particles this program holds -> the sums over all particles."""
        return grid

    # ---- differentiable entry points (AbstractStepper contract; backends/jax/differentiable.py) ----
    def controls(self):
        from . import differentiable
        return differentiable.controls(self)

    def observe(self, controls, observation, steps, segment=None):
        """Observations [T, L, d] of the rollout from ``controls`` after each of ``steps``; pure JAX,
        so ``jax.grad`` of any loss of it reaches every control (checkpointed segments). Every step
        uses the build-time dt (an adaptive ``dt: auto`` is not recomputed here; a warning says so)."""
        from . import differentiable
        self._observe_dt_note()
        return differentiable.observe(self, controls, observation, steps, segment)

    @property
    def params(self):
        if not hasattr(self, "_params"):
            self._params = self.default_params()
        return self._params

    # ---- the step ------------------------------------------------------------------------------
    def step_fn(self, state, params, dt=None, *, particle_bcs: bool = True, update_law: bool = True, nodes=None):
        """One explicit MPM step (JAX-MPM Sec. 2.2; NCLaw Alg. 3) with the scheme's transfer math, pure.

        Layout for speed on CPU (the math is the textbook one): each particle's W^D stencil is one
        *window* of the grid, so P2G is a single windowed ``lax.scatter_add`` of a ``[N, W, .., W, K]``
        block (K = mass, momentum [, force]) at the particle's base node and G2P a single windowed
        ``lax.gather`` -- one index per particle instead of W^D, and no [N*W^D] index arrays. Weights
        are separable products; the affine terms are folded into one per-particle matrix
        (``A = m C - dt V tau D^-1`` for MLS). Both live in ``adjoints.py``; with ``self.adjoints ==
        "custom"`` (the default) reverse mode uses their hand-written transposes (P2G's adjoint is a
        gather + G2P-like contractions, G2P's a P2G-like expansion + scatter, no XLA ``reduce``), with
        ``"derived"`` the ones XLA derives; the forward values are identical. The window is the shape
        function's (``self.shape``: W = 3 nodes per axis for quadratic B-splines and uGIMP, 4 for cubic
        B-splines, lowest node ``floor(x/dx - offset)``); the transfer scheme supplies
        the per-particle terms (``p2g``) and what becomes of the gathered sums (``g2p``); this function
        contracts only the terms it declares (``AbstractTransfer``), it never branches on a scheme.

        ``dt``: None bakes the build-time ``self.dt`` into the program as a constant (fixed-dt runs,
        gradient rollouts); a traced scalar is the adaptive ``dt: auto`` step (one compiled program
        for every dt value).

        A reduced model (``mpmlab.rom.stepper``, Eulerian quadrature) steps pseudo-particles that are not
        the scene's particles: ``particle_bcs=False`` leaves out the boundaries that address particles
        by index (it applies them to its own points), ``update_law=False`` the law-state update (its F
        comes from the deformation map; the returned state has no ``law``), and ``nodes`` (a
        ``node_windows.NodeWindows``) runs P2G, the grid update and G2P on the compact node set around its
        points instead of the scene's grid (the same result; the cost no longer grows with the grid).
        """
        T, tf = self.transfer, self._tf
        D, dx = self.dim, self.scene.dx
        dt = self.dt if dt is None else dt
        inv_dx = 1.0 / dx
        x, v = state["x"], state["v"]
        dtype = x.dtype
        mass, vol = params["mass"], params["volume"]
        N = x.shape[0]
        bc_params = params["boundary"]
        nb = len(self._grid_bcs)
        split = bool(T.split_force)
        gshape = tuple(self.grid_shape) if nodes is None else nodes.shape

        # stencil: the shape function's window and weights ------------------------------------------------
        shape = self.shape
        lp = jax.lax.stop_gradient(params["lp"]) if "lp" in params else None
        if self.corners:                          # CPDI: the stencil of the domain's corners (``_corners``)
            cp = self._corners(x, state["domain"])
            base, fx, w1, dw1, Dinv = cp.base, cp.fx, cp.w1, cp.dw1, cp.Dinv
        else:
            Xp = (x - self._node_x[0]) * inv_dx
            base = jnp.floor(Xp - shape.offset).astype(jnp.int32)
            fx = Xp - base
            w1, dw1 = self._shape_fns.weights(fx, lp)                        # [N, W, D]
            Dinv = self._Dinv(w1, fx, inv_dx)                                # APIC's D_p^-1 (Jiang et al. 2015)
            dw1 = dw1 * inv_dx                                              # d w / d x (not cell units)
        node_x, node_ids = self._node_x, None
        if nodes is not None:                     # the compact node set: base nodes within each particle's window
            if self.corners:
                raise ConfigError("step_fn: a compact node set (nodes=) does not carry CPDI's corner stencils.")
            at = nodes.nodes()
            node_x, node_ids = self._node_x[0] + at.astype(dtype) * dx, nodes.scene_ids(at, self.grid_shape)
            base = nodes.local_base(base, int(shape.width))

        # stress (Kirchhoff) from each law present ----------------------------------------------------
        tau = jnp.concatenate([jax.vmap(law.kirchhoff, in_axes=(0, 0, None))(st, prm, w) for law, st, prm, w in
                               zip(self._laws, state["law"], params["law"], params["law_weights"])],
                              axis=0).astype(dtype)  # [N, D, D]

        # P2G ---------------------------------------------------------------------------------------------
        # Node o of a particle gets, per lane (momentum D, mass 1 [, force D when split]):
        #   w_o (lin + sum_d o_d Acol_d) + sum_e (grad w_o)_e Gcol_e
        # with per-particle columns from the scheme's terms (P2GTerms: w (q + A (x_i - x_p)) + G grad w):
        # lin = q - A fx dx, Acol_d = A[:, d] dx, Gcol_e = G[:, e]; mass lin = m. They are computed once
        # per particle and materialised so the [N, W^D, K] block is a cheap elementwise expression of them.
        zero = jnp.zeros((N, D), dtype)
        mv = lambda M, c: jnp.stack([sum(M[:, a, j] * c[:, j] for j in range(D)) for a in range(D)], -1)  # M c
        pt = tf.p2g(SimpleNamespace(m=mass, V=vol, v=v, C=state.get("C"), tau=tau, dt=dt, inv_dx=inv_dx, dx=dx,
                                    Dinv=Dinv))
        q, A, G, Fm, Fg = pt.q, pt.A, pt.G, pt.force_A, pt.force_G
        ext = None
        for bc, bp in zip(self._force_bcs, bc_params[nb + len(self._particle_bcs):]):
            f = bc.particle_force(x, mass, state["t"], bp)
            ext = f if ext is None else ext + f
        if ext is not None and not split:
            q = q + dt * ext
        m1 = mass[:, None]
        # the columns at the particle (CPDI: fx = 0 here, each corner's own offsets added in _corner_terms)
        fx_lin = zero if self.corners else fx
        lin = [q - mv(A, fx_lin) * dx if A is not None else q, m1]
        acol = [[A[:, :, d] * dx if A is not None else zero, jnp.zeros_like(m1)] for d in range(D)]
        gcol = [[G[:, :, e] if G is not None else zero, jnp.zeros_like(m1)] for e in range(D)]
        if split:
            f0 = zero if Fm is None else -mv(Fm, fx_lin) * dx
            lin.append(f0 if ext is None else f0 + ext)
            for d in range(D):
                acol[d].append(Fm[:, :, d] * dx if Fm is not None else zero)
                gcol[d].append(Fg[:, :, d] if Fg is not None else zero)
        cat = lambda parts: jnp.concatenate(parts, axis=-1)                      # [N, K]
        lin = cat(lin)
        acol = [cat(c) for c in acol] if (A is not None or Fm is not None) else None
        gcol = [cat(c) for c in gcol] if (G is not None or Fg is not None) else None
        if self.corners:
            lin, acol, gcol = self._corner_terms(cp, lin, acol, (A, G), (Fm, Fg) if split else None)
        pred = state["t"] >= 0
        w1, dw1, lin, acol, gcol = _materialize((w1, dw1, lin, acol, gcol), pred)
        K = lin.shape[-1]
        grid = self._sum_grid(adjoints.p2g(base, w1, dw1, lin, acol, gcol, pred, gshape, self.adjoints))
        grid = grid.reshape(-1, K)
        if nodes is not None:                     # every copy of a node gets the sum over its copies
            grid = nodes.merge(grid, at)
        grid_mv, grid_m = grid[:, :D], grid[:, D]

        # grid update (JAX-MPM Eqs. 13-14) -------------------------------------------------------------------
        has_mass = grid_m > 0
        safe_m = jnp.where(has_mass, grid_m, 1.0)[:, None]
        v_old = jnp.where(has_mass[:, None], per_mass(grid_mv, safe_m), 0.0)
        acc = params["gravity"]
        if split:
            acc = per_mass(grid[:, D + 1:], safe_m) + acc
        v_new = jnp.where(has_mass[:, None], v_old + dt * acc, 0.0)
        for bc, bp in zip(self._grid_bcs, bc_params[:nb]):
            v_new = bc.apply(v_new, node_x, grid_m, state["t"], bp) if node_ids is None else \
                bc.apply(v_new, node_x, grid_m, state["t"], bp, node_ids=node_ids)

        # G2P: one windowed gather per particle (adjoints.g2p) -------------------------------------------------
        gfield = jnp.concatenate([v_new, v_old], axis=-1) if split else v_new
        Kg = gfield.shape[-1]
        # then separable contractions of the gathered block, one stencil axis at a time (adjoints.contract).
        # Weight kinds per axis: "w" (weights), "o" (o_d w, first moment, APIC), "d" (d w / d x_d,
        # velocity gradient).
        specs = {"v": ("w",) * D}
        if "first" in T.moments:
            specs.update({f"o{d}": tuple("o" if e == d else "w" for e in range(D)) for d in range(D)})
        if "gradient" in T.moments and not self.corners:
            specs.update({f"d{d}": tuple("d" if e == d else "w" for e in range(D)) for d in range(D)})
        out = adjoints.g2p(gfield.reshape(gshape + (Kg,)), base, w1, dw1, pred, specs, self.adjoints)  # [N, Kg] each

        new = {"t": state["t"] + dt}
        if self.corners:                # the corners' sums -> the particle's (v_pic, B / dx, grad v, domain)
            v_pic, v_old, first, grad, new["domain"] = self._corner_moments(cp, out, state["domain"], dt)
            fx = jnp.zeros_like(x)
            Dinv_moved = self._shape_fns.inv(self._shape_fns.inertia(x + dt * v_pic, new["domain"], dx, self._node_x[0]))
        else:
            v_pic = out["v"][:, :D]
            v_old = out["v"][:, D:] if split else None
            first = jnp.stack([out[f"o{d}"][:, :D] for d in range(D)], axis=-1) if "first" in T.moments else None
            grad = jnp.stack([out[f"d{e}"][:, :D] for e in range(D)], axis=-1) if "gradient" in T.moments else None  # Eq. 18
            Dinv_moved = self._Dinv_moved(x + dt * v_pic, lp, Dinv)
        res = tf.g2p(SimpleNamespace(v=v, v_pic=v_pic, v_old=v_old, first=first, grad=grad, fx=fx, inv_dx=inv_dx,
                                     dx=dx, Dinv=Dinv_moved))
        v_p, grad_v = res.v, res.grad_v
        if T.carries_C:
            new["C"] = res.C
        for bc, bp in zip(self._particle_bcs if particle_bcs else (), bc_params[nb:nb + len(self._particle_bcs)]):
            # a prescribed particle velocity also moves the particle with it (v_pic)
            v_p, v_pic = bc.apply_particles(x, v_p, v_pic, state["t"] + dt, dt, bp)
        new["x"] = x + dt * v_pic                                              # JAX-MPM Eq. 17
        new["v"] = v_p
        if not update_law:
            return new

        # law update per material block ------------------------------------------------------------------------
        laws = []
        for rows, law, st, prm, w in zip(self._group_slices, self._laws, state["law"], params["law"],
                                         params["law_weights"]):
            gv = grad_v[rows]
            upd = jax.vmap(law.update, in_axes=(0, 0, None, 0, None))(st, gv, dt, prm, w)
            # a law (or a plugin's law) may build constants in float64: keep the state in the stepper's precision
            laws.append({k: a.astype(dtype) for k, a in upd.items()})
        new["law"] = tuple(laws)
        return new

    # ---- CPDI: the corners of each particle's domain as pseudo-particles (mpmlab/shapes/cpdi/reference.py) --
    def _corners(self, x, R):
        """The corner stencil of particles x [N, D] with domains R [N, D, D]: 2^D pseudo-particles each, at
        x_c = x_p + R s_c with the linear hat's window (2 nodes per axis from floor(x_c / dx)), rows
        ordered particle-major ([N * 2^D]); ``r`` = R s_c and ``g`` = R^-T s_c [N, 2^D, D] (each corner's share
        of grad S_ip = 2^-D sum_c N_i(x_c) R^-T s_c, Sadeghirad et al. 2011); ``Dinv`` = D_p^-1 [N, D, D]."""
        N, D = x.shape
        inv_dx, dx = 1.0 / self.scene.dx, self.scene.dx
        s = jnp.asarray(self._corner_signs, x.dtype)                            # [NC, D]
        r = jnp.einsum("nij,cj->nci", R, s)                                      # R s_c
        g = jnp.einsum("nji,cj->nci", self._shape_fns.inv(R), s)                      # R^-T s_c
        Xc = ((x[:, None, :] + r) - self._node_x[0]) * inv_dx                    # corners in cells
        base = jnp.floor(Xc).astype(jnp.int32)
        fxc = Xc - base                                                          # [N, NC, D]
        w1, dw1 = self._shape_fns.weights(fxc.reshape(-1, D))                   # [N * NC, 2, D]
        Dinv = self._shape_fns.inv(self._shape_fns.inertia(x, R, dx, self._node_x[0]))
        return SimpleNamespace(base=base.reshape(-1, D), fx=fxc.reshape(-1, D), fxc=fxc, w1=w1, dw1=dw1 * inv_dx,
                               r=r, g=g, Dinv=Dinv, NC=s.shape[0])

    def _corner_terms(self, cp, lin, acol, mom, force):
        """The particle's P2G columns, formed at fx = 0 (``lin`` [N, K] = q | m [| f]; ``acol`` per axis), ->
        its corners' [N * NC, K], each with its 2^-D share. x_i - x_p = (x_i - x_c) + r_c, so a corner adds
        A (r_c - fx_c dx) to the momentum lanes (its own window offsets come from ``acol`` as usual), and
        the gradient terms G grad S_ip = sum_c 2^-D N_i(x_c) G R^-T s_c become G g_c times the corner's
        weight: folded into ``lin``, no weight-gradient column remains (``gcol`` None). The same for the
        force lanes of a ``split_force`` scheme with (F, H)."""
        N, K = lin.shape
        NC, D, dx = cp.NC, self.dim, self.scene.dx
        off = cp.r - cp.fxc * dx                                                 # r_c - fx_c dx  [N, NC, D]

        def lanes(M, Gm):
            e = 0.0
            if M is not None:
                e = e + jnp.einsum("nij,ncj->nci", M, off)
            if Gm is not None:
                e = e + jnp.einsum("nij,ncj->nci", Gm, cp.g)
            return e if M is not None or Gm is not None else jnp.zeros((N, NC, D), lin.dtype)

        extra = [lanes(*mom), jnp.zeros((N, NC, 1), lin.dtype)]
        if force is not None:
            extra.append(lanes(*force))
        lin_c = ((lin[:, None, :] + jnp.concatenate(extra, axis=-1)) / NC).reshape(N * NC, K)
        acol_c = None if acol is None else [jnp.repeat(a / NC, NC, axis=0) for a in acol]
        return lin_c, acol_c, None

    def _corner_moments(self, cp, out, R, dt):
        """The corners' G2P sums [N * NC, Kg] -> the particle's v_pic, v_old, B / dx (``first``, read with
        fx = 0), grad v = sum_i v_i grad S_ip^T = 2^-D sum_c v_c (R^-T s_c)^T (always: the domain update
        needs it) and the updated domain (Cayley, ``reference.update_domain``)."""
        D, NC, dx = self.dim, cp.NC, self.scene.dx
        N = R.shape[0]
        vc = out["v"].reshape(N, NC, -1)
        v_pic = jnp.mean(vc[..., :D], axis=1)
        v_old = jnp.mean(vc[..., D:], axis=1) if self.transfer.split_force else None
        grad = jnp.einsum("nci,ncj->nij", vc[..., :D], cp.g) / NC
        first = None
        if "first" in self.transfer.moments:
            Bc = jnp.stack([out[f"o{d}"][:, :D] for d in range(D)], axis=-1).reshape(N, NC, D, D)
            # B / dx = 2^-D sum_c [(B_c - v_c fx_c^T) + v_c (r_c / dx)^T]  (B_c: the corner's own first moment)
            first = jnp.mean(Bc + jnp.einsum("nci,ncj->ncij", vc[..., :D], cp.r / dx - cp.fxc), axis=1)
        return v_pic, v_old, first, grad, self._shape_fns.update_domain(R, grad, dt)

    def _Dinv(self, w1, fx, inv_dx):
        """D_p^-1 in 1/length^2, as the schemes read it (``p.Dinv``, ``g.Dinv``; AbstractTransfer):

        * a Python float c, D^-1 = c I for every particle, when the shape function's D_p is a constant
          (B-splines: c = inv_D_cells / dx^2, 4/dx^2 quadratic, 3/dx^2 cubic): nothing per particle is
          computed, and the schemes multiply by one number as before shape functions were a choice;
        * an [N, D, D] array otherwise (uGIMP): diagonal, D_p[a, a] = dx^2 sum_k w_ka (k - fx_a)^2 from
          the particle's own weights (separable and linearly complete, so the off-diagonal sums vanish).

        ``mpmlab.transfers._common.jax.times_Dinv(M, Dinv)`` = M D^-1 takes either form."""
        c = self.shape.inv_D_cells
        if c is not None:
            return float(c) * inv_dx * inv_dx
        W, D = w1.shape[1], w1.shape[2]
        r = jnp.arange(W, dtype=fx.dtype)[None, :, None] - fx[:, None, :]       # node offsets in cells [N, W, D]
        Dc = jnp.sum(w1 * r * r, axis=1)                                          # [N, D]
        return jnp.eye(D, dtype=fx.dtype) * ((inv_dx * inv_dx) / Dc)[:, None, :]

    def _Dinv_moved(self, x_new, lp, Dinv):
        """G2P's D_p^-1: that of the position the particle moves to, x_new = x + dt v_pic, where the next
        P2G spreads C (``g.Dinv``). C = B D^-1 is applied there as C (x_i - x_new) with the weights, and so
        the D_p, of x_new: with D_p of x_new the affine momentum the next P2G puts on the grid is exactly
        the B gathered here (Jiang et al. 2015 store B and form C at P2G for this reason), and APIC / MLS
        conserve angular momentum to round-off with uGIMP too. B-splines (constant D_p): ``Dinv`` itself,
        unchanged. The base of x_new is its own; its floor has zero derivative, so reverse mode reaches x
        and v_pic through fx and the weights."""
        if self.shape.inv_D_cells is not None:
            return Dinv
        inv_dx = 1.0 / self.scene.dx
        Xp = (x_new - self._node_x[0]) * inv_dx
        fx = Xp - jnp.floor(Xp - self.shape.offset)
        w1, _ = self._shape_fns.weights(fx, lp)
        return self._Dinv(w1, fx, inv_dx)

    def _advance_impl(self, state, params, steps, dt=None):
        def body(s, _):
            return self.step_fn(s, params, dt), None

        if steps == 1:
            return self.step_fn(state, params, dt)
        state, _ = jax.lax.scan(body, state, None, length=steps)
        return state

    def _advance(self, state, steps):
        # dt_arg None: the build-time dt is a compile-time constant (bit-identical fixed-dt runs);
        # an array: the rollout's current dt: auto step, a runtime argument (no recompilation)
        return self._jit_advance(state, self.params, steps, getattr(self, "_dt_arg", None))

    def _set_dt(self, dt):
        super()._set_dt(dt)
        self._dt_arg = None if dt is None else jnp.asarray(self.dt, self.dtype)

    def _max_speed(self, state) -> float:
        if not hasattr(self, "_jit_speed"):
            self._jit_speed = jax.jit(lambda v: jnp.sqrt(jnp.max(jnp.sum(v * v, axis=1), initial=0.0)))
        return float(self._jit_speed(state["v"]))

    def _block(self, state):
        jax.block_until_ready(state)

    # ---- guards --------------------------------------------------------------------------------
    def _bad_impl(self, state):
        lo, hi = self.inner_bounds
        bad = ~jnp.all(jnp.isfinite(state["x"])) | ~jnp.all(jnp.isfinite(state["v"]))
        pts = state["x"]
        if self.corners:                   # CPDI: every corner of the domain must stay on the grid
            from ...shapes.cpdi.reference import corners
            pts = corners(pts, state["domain"], jnp)
            bad = bad | ~jnp.all(jnp.isfinite(state["domain"]))
        bad = bad | jnp.any((pts < lo) | (pts >= hi))
        for g, st in zip(self.groups, state["law"]):
            for k, a in st.items():
                bad = bad | ~jnp.all(jnp.isfinite(a))
            for f in g.law.state:          # the declared sign checks (J > 0, det F > 0)
                if f.check == "positive":
                    bad = bad | jnp.any(st[f.name] <= 0)
                elif f.check == "positive_det":
                    bad = bad | jnp.any(jnp.linalg.det(st[f.name]) <= 0)
        return bad

    def _is_bad(self, state) -> bool:
        return bool(self._jit_bad(state))

    # ---- numpy views ------------------------------------------------------------------------------
    def to_numpy(self, state):
        dt = np.dtype(self.dtype)   # one float dtype per precision (fp32 -> float32), as on Warp
        out = {"x": np.asarray(state["x"], dt), "v": np.asarray(state["v"], dt), "t": float(state["t"])}
        if "C" in state:
            out["C"] = np.asarray(state["C"], dt)
        if "domain" in state:
            out["domain"] = np.asarray(state["domain"], dt)
        for name in self.state_field_names:
            parts = [(g, st[name]) for g, st in zip(self.groups, state["law"]) if name in st]
            if parts:
                out[name] = np.concatenate([np.asarray(a, dt) for _, a in parts])
                out[name + "_particles"] = np.concatenate([np.arange(g.start, g.stop) for g, _ in parts])
        return out
