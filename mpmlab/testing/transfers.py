"""The kit's checks of a transfer scheme (a plugin's or a built-in): conservation it declares, JAX vs
Warp trajectories and gradients against finite differences with it."""
from __future__ import annotations

import numpy as np

from ._common import Report, fail

#: the law the transfer checks run with (a built-in; its Law.test_params)
LAW = "fixed_corotated"


def _transfer(transfer):
    """(instance, registered name) of a transfer given by name, class or instance."""
    from ..core import registry
    from ..transfers import make_transfer

    if isinstance(transfer, str):
        return make_transfer(transfer), transfer
    inst = transfer() if isinstance(transfer, type) else transfer
    name = type(inst).name
    if name not in registry.transfers.names():
        registry.transfers.register(name, type(inst), provenance="mpmlab.testing")
    return inst, name


def conservation_scene(dim: int, *, law: str = LAW):
    """A spinning (4 rad/s; 3D (1, 2, 3)), drifting elastic block (0.2 wide, 2^D particles per cell) in
    the middle of a unit box, no gravity and no walls it can reach in the kit's steps: nothing but the
    scheme's transfers and internal forces acts."""
    import mpmlab
    from ._common import params_of

    lo, hi = np.full(dim, 0.4), np.full(dim, 0.6)
    v = np.zeros(dim); v[0], v[1] = 0.3, -0.2
    w = 4.0 if dim == 2 else [1.0, 2.0, 3.0]
    body = mpmlab.Body(shape={"kind": "box", "lo": lo.tolist(), "hi": hi.tolist()}, material=law,
                       params=params_of(law), density=1000.0, velocity=v.tolist(), angular_velocity=w,
                       particles_per_cell=2**dim)
    return mpmlab.Scene(dim=dim, dx=0.05, domain=([0.0] * dim, [1.0] * dim), bodies=[body],
                        gravity=[0.0] * dim, dt=1e-3, name=f"conservation_{dim}d")


def inertia(shape, x, origin, dx: float, lp=None, domain=None) -> np.ndarray:
    """D_p = sum_i w_ip (x_i - x_p)(x_i - x_p)^T [N, D, D] of particles at ``x`` (``mpmlab.shapes``; NumPy
    reference weights, fp64): for a separable shape function diagonal, dx^2 sum_k w_ka (k - fx_a)^2; for
    CPDI (``domain``: the particles' domains [N, D, D]) ``cpdi.reference.inertia``."""
    import importlib

    from ..shapes import make_shape

    s = make_shape(shape)
    if s.kind == "corners":
        from ..shapes.cpdi.reference import inertia as corner_inertia

        return corner_inertia(np.asarray(x, float), np.asarray(domain, float), dx, np.asarray(origin, float))
    ref = importlib.import_module(f"{type(s).__module__}.reference")
    X = (np.asarray(x, float) - np.asarray(origin, float)) / dx
    fx = X - np.floor(X - s.offset)
    N, D = fx.shape
    lp_ = None if lp is None else np.broadcast_to(np.asarray(lp, float)[:, None], (N, D))
    w, _ = ref.weights_1d(fx, lp_)                                      # [N, D, W]
    k = np.arange(w.shape[-1], dtype=float)
    Dc = (w * (k[None, None, :] - fx[..., None]) ** 2).sum(-1)        # [N, D]
    return dx * dx * np.eye(D)[None] * Dc[:, None, :]


def momenta(x, v, C, mass: np.ndarray, dx: float, dim: int, D=None):
    """Total linear momentum sum m v and angular momentum about the origin sum m (x x v) plus each
    particle's affine spin m eps : (C D_p)^T (the angular momentum its C puts on the grid; Jiang et al.
    2015 Sec. 5.3). ``D``: D_p [N, D, D] (:func:`inertia`), None for quadratic B-splines' dx^2/4 I."""
    x, v = np.asarray(x, float), np.asarray(v, float)
    m = np.asarray(mass, float)
    P = (m[:, None] * v).sum(0)
    C = np.zeros((len(m), dim, dim)) if C is None else np.asarray(C, float)
    B = (dx * dx / 4.0) * C if D is None else np.einsum("nij,njk->nik", C, D)
    if dim == 2:
        L = np.array([(m * (x[:, 0] * v[:, 1] - x[:, 1] * v[:, 0] + (B[:, 1, 0] - B[:, 0, 1]))).sum()])
    else:
        spin = np.stack([B[:, 2, 1] - B[:, 1, 2], B[:, 0, 2] - B[:, 2, 0], B[:, 1, 0] - B[:, 0, 1]], -1)
        L = (m[:, None] * (np.cross(x, v) + spin)).sum(0)
    return P, L


def check_conservation(transfer, dim: int, backend: str, *, steps: int = 40, tol: float = 1e-11,
                       quantities=None, shape: str = "quadratic") -> dict:
    """Over ``steps`` fp64 steps of ``conservation_scene``, each quantity the scheme declares in
    ``conserves`` (or ``quantities``) stays within ``tol`` of its initial value, relative to its
    magnitude (angular momentum about the block's centroid scale). Returns the drift by quantity and,
    for information, the drift of the quantities it does not declare. ``shape``: the shape function
    (``mpmlab.shapes``) the stepper runs with; the affine spin counts its D_p (:func:`inertia`)."""
    import mpmlab

    inst, name = _transfer(transfer)
    declared = set(inst.conserves if quantities is None else quantities)
    scene = conservation_scene(dim)
    st = mpmlab.build_stepper(scene, backend, name, "fp64", **({} if shape == "quadratic" else {"shape": shape}))
    lp = getattr(st, "_lp", None)
    corners = st.shape.kind == "corners"            # CPDI: D_p from the particles' domains
    fields = (("C",) if inst.needs_affine else ()) + (("domain",) if corners else ())
    traj = st.rollout(steps=steps, every=1, fields=fields)
    dom = traj.fields.get("domain")
    Dp = ((lambda k: None) if shape == "quadratic" else
          (lambda k: inertia(shape, traj.x[k], scene.origin, scene.dx, lp, None if dom is None else dom[k])))
    mass = traj.mass
    C = traj.fields.get("C")
    frame = lambda k: (traj.x[k], traj.v[k], None if C is None else C[k])      # noqa: E731
    P0, L0 = momenta(*frame(0), mass, scene.dx, dim, Dp(0))
    # scales: total mass x the block's speeds (drift and spin) so a conserved zero component is tested too
    M = float(np.sum(mass))
    r = 0.1 * np.sqrt(dim)
    p_scale = M * 0.5
    l_scale = float(M * r * r * 4.0 + np.linalg.norm(L0))
    drift = {"linear_momentum": 0.0, "angular_momentum": 0.0}
    for k in range(1, traj.frame_count):
        P, L = momenta(*frame(k), mass, scene.dx, dim, Dp(k))
        drift["linear_momentum"] = max(drift["linear_momentum"], float(np.abs(P - P0).max()) / p_scale)
        drift["angular_momentum"] = max(drift["angular_momentum"], float(np.abs(L - L0).max()) / l_scale)
    where = f"transfer '{name}' {dim}D {backend} fp64, {steps} steps" + ("" if shape == "quadratic" else f", shape {shape}")
    for q in sorted(declared):
        if q not in drift:
            fail(f"{where}: conserves '{q}' is not a quantity the kit measures ({sorted(drift)})")
        if not drift[q] <= tol:
            fail(f"{where}: {q.replace('_', ' ')} drifts by {drift[q]:.3e} (relative) > tolerance {tol:.0e}, "
                 f"although the scheme declares it conserved")
    return {"declared": sorted(declared), "drift": drift}


def check_transfer(transfer, *, dims=(2,), backends=("jax", "warp"), gradients=True, law: str = LAW,
                   raise_on_failure: bool = True) -> dict:
    """Every check of the kit on a transfer scheme: the conservation it declares (each backend x dim),
    JAX vs Warp trajectories of the law scene with ``law`` (each dim) and gradients against central
    differences (each backend, 2D when 2 is in ``dims``). Same report and failure convention as
    ``check_law``."""
    from .gradients import check_gradients
    from .trajectories import check_backends_agree

    _, name = _transfer(transfer)
    report = Report("transfer", name)
    run = report.run
    for dim in dims:
        for b in backends:
            run(f"conservation[{b},{dim}d]", check_conservation, name, dim, b)
        if {"jax", "warp"} <= set(backends):
            run(f"backends_agree[{law},{dim}d]", check_backends_agree, law, name, dim)
    grad_backends = tuple(backends) if gradients is True else tuple(gradients or ())
    gdim = 2 if 2 in dims else dims[0]
    for b in grad_backends:
        run(f"gradients[{b},{law},{gdim}d]", check_gradients, law, b, name, gdim)
    return report.finish(raise_on_failure)
