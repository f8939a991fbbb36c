"""Large-shear manufactured solutions (issue 19, item 4): axisymmetric twists with shear strain >= 5.

Both solutions are the same family, a rotation by an angle that depends on the reference radius
R = |X| and on time (Kamojjala, Brannon, Sadeghirad & Guilkey 2015, "Verification tests in solid
mechanics", Eng. Comput. 31:193, the "generalized vortex"):

    x = Q(alpha(R, t)) X,      alpha = A g(u) h(t),      u = (R - Rc) / w,      g = (1 - u^2)^2,

so every particle stays on its circle (r = R) and the motion is isochoric (J = 1 exactly). With
e_R, e_Theta the reference polar basis and e_r = Q e_R, e_theta = Q e_Theta the current one:

    F = Q (I + gamma e_Theta (x) e_R) = Q + gamma e_theta (x) e_R,    gamma = R d(alpha)/dR,
    v = alpha_t r e_theta,    a = alpha_tt r e_theta - alpha_t^2 r e_r,

a simple shear gamma(R, t) in the local polar frame. g and dg/du vanish at u = +-1, so F = I there
(up to the rigid rotation): the rims are traction free and the body needs no wall. The Cauchy stress
depends on r only; in the current polar frame, with s = sqrt(4 + gamma^2) (V = (B + I) / s is the
left stretch of the local simple shear, B = [[1, gamma], [gamma, 1 + gamma^2]]):

* ``fixed_corotated`` (J = 1, so lambda does not enter): sigma = 2 mu (B - V):
  s_rr = 2 mu (1 - 2/s), s_rt = 2 mu gamma (1 - 1/s), s_tt = 2 mu (1 + gamma^2 - (2 + gamma^2)/s);
* ``hencky`` (``hencky_von_mises`` with a yield stress it never reaches): sigma = 2 mu ln V with
  L = asinh(gamma / 2) = ln((gamma + s) / 2): s_rr = -2 mu L gamma / s, s_rt = 4 mu L / s, s_tt = -s_rr.

The body force per unit mass is b = a - div(sigma) / rho0 with (axisymmetric stress)

    div(sigma)_r = d s_rr/dr + (s_rr - s_tt) / r,     div(sigma)_theta = d s_rt/dr + 2 s_rt / r,

d/dr = (d/d gamma) * dgamma/dR, dgamma/dR = A h (g_R + R g_RR). It is written once
(:func:`fields`, generic in the arithmetic) and evaluated three ways: NumPy (the float64 oracle),
and as the ``expression`` body force's strings in ``X[0], X[1], t`` and named constants, which
mpmlab compiles for JAX and Warp (nothing in mpmlab is specific to these solutions).

Three solutions (:data:`SOLUTIONS`):

* ``annulus`` -- the twisted annulus of issue 19 (Kamojjala's generalized vortex): Rc = 1, w = 0.25
  (0.75 <= R <= 1.25: g = 1 - 32 (R-1)^2 + 256 (R-1)^4), h = sin(pi t / T), T = 1, A = 1: peak
  rotation 1 rad at t = T/2, peak |gamma| = 7.04 A at R = 1 +- 0.144; it starts undeformed with
  velocity alpha_t r e_theta (and, for APIC/MLS, the affine field C = grad v).
* ``vortex`` -- a solid disc twisted and untwisted from rest: Rc = 0, w = Ro = 1, h = (1 - cos(2 pi t / T)) / 2,
  T = 1, A = 6: the centre turns by 6 rad (about one turn) at t = T/2 and back at t = T; peak
  |gamma| = A u^2 4 (1 - u^2) max = A at R = Ro / sqrt(2); it starts at rest (v = 0, F = I).
* ``vortex3`` -- the same disc with g = (1 - u^2)^3 (``power`` 3) and A = 6.75 (peak |gamma| = 6.0 at
  R = 1/sqrt(3)): the shear vanishes at the free rim with zero slope, where ``vortex``'s falls to zero
  linearly (gamma ~ -8 A h (1 - R), slope 48 at the peak). MPM's free surface (particle-sampled, no
  boundary quadrature) integrates that steep stress gradient with a low-order error, which is where
  ``vortex``'s finest-grid error sits (benchmarks/large_shear.md); ``vortex3`` tests that.

Material: rho0 = 1000, E = 1e4, nu = 0.3 (c_s = 1.96 m/s, c_p = 3.67 m/s): the annulus' material
speed peaks at A pi R g = pi m/s at R = 1, above the shear wave speed, as in the issue.

Errors: ``displacement_error`` is the particle-RMS of |x - X - U(X, t)| (equal particle volumes),
in metres, and relative to the RMS of |U| at the same time.

The ``shape_function`` axis: :func:`run` takes ``shape_function``, any of ``mpmlab.shapes``'
shape functions (``quadratic``, ``cubic``, ``ugimp``, ``cpdi``), handed to the stepper as ``shape``.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace
from typing import Any, Callable

import numpy as np

from ..core.geometry import Shape
from ..core.scene import Body, Scene

__all__ = ["Twist", "SOLUTIONS", "Annulus", "solution", "exact", "body_force", "body_force_expressions",
           "scene", "run", "displacement_error", "make_transfer_for", "SHAPE_FUNCTIONS", "LAWS"]

#: the mpmlab law each closed form's stress belongs to
LAWS = {"fixed_corotated": "fixed_corotated", "hencky": "hencky_von_mises"}
#: shape functions a run may ask for (mpmlab.shapes)
SHAPE_FUNCTIONS = ("quadratic", "cubic", "ugimp", "cpdi")


@dataclass(frozen=True)
class Twist:
    """One axisymmetric twist: alpha(R, t) = A (1 - u^2)^power h(t), u = (R - Rc) / w, on Rc - w <= R <= Rc + w
    (R >= 0, power >= 2); ``time`` is ``"sin"`` (h = sin(pi t / T)) or ``"pulse"`` (h = (1 - cos(2 pi t / T)) / 2)."""

    name: str
    A: float
    Rc: float
    w: float
    T: float = 1.0
    time: str = "sin"
    law: str = "fixed_corotated"
    E: float = 1.0e4
    nu: float = 0.3
    density: float = 1000.0
    power: int = 2

    @property
    def mu(self) -> float:
        return self.E / (2.0 * (1.0 + self.nu))

    @property
    def lam(self) -> float:
        return self.E * self.nu / ((1.0 + self.nu) * (1.0 - 2.0 * self.nu))

    @property
    def r_in(self) -> float:
        return max(self.Rc - self.w, 0.0)

    @property
    def r_out(self) -> float:
        return self.Rc + self.w

    @property
    def t_peak(self) -> float:
        """Time of the peak twist (h = 1)."""
        return 0.5 * self.T

    def wave_speeds(self) -> tuple[float, float]:
        """(c_s, c_p) of the undeformed material [m/s]."""
        return math.sqrt(self.mu / self.density), math.sqrt((self.lam + 2.0 * self.mu) / self.density)

    def constants(self) -> dict[str, float]:
        return {"A": self.A, "Rc": self.Rc, "w": self.w, "T": self.T, "mu": self.mu, "rho": self.density}

    def peak_shear(self, n: int = 20001) -> float:
        """max |gamma| over R at h = 1."""
        R = np.linspace(self.r_in, self.r_out, n)
        return float(np.max(np.abs(self.A * R * _profile((R - self.Rc) / self.w, self.w, self.power)[1])))

    def peak_speed(self, n: int = 20001) -> float:
        """max over R and t of |v| = R |alpha_t|."""
        R = np.linspace(self.r_in, self.r_out, n)
        g = _profile((R - self.Rc) / self.w, self.w, self.power)[0]
        ht = math.pi / self.T
        return float(np.max(R * self.A * g) * ht)


SOLUTIONS = {
    "annulus": Twist("annulus", A=1.0, Rc=1.0, w=0.25, T=1.0, time="sin"),
    "vortex": Twist("vortex", A=6.0, Rc=0.0, w=1.0, T=1.0, time="pulse"),
    "vortex3": Twist("vortex3", A=6.75, Rc=0.0, w=1.0, T=1.0, time="pulse", power=3),
}


def solution(name: str = "annulus", **changes) -> Twist:
    """A named solution of :data:`SOLUTIONS`, with fields replaced (``solution("annulus", A=0.1)``)."""
    if name not in SOLUTIONS:
        raise ValueError(f"large-shear solution {name!r}: use one of {sorted(SOLUTIONS)}")
    return replace(SOLUTIONS[name], **changes)


# ---------------------------------------------------------------------------------------------
# the closed form, written once for numbers (NumPy) and for expression strings
# ---------------------------------------------------------------------------------------------
class _Sym:
    """An expression string that composes with + - * / ** (the ``expression`` body force's syntax)."""

    def __init__(self, s):
        self.s = s if isinstance(s, str) else repr(float(s))

    @staticmethod
    def _w(o):
        return o if isinstance(o, _Sym) else _Sym(o)

    def __add__(self, o): return _Sym(f"({self.s} + {self._w(o).s})")
    def __radd__(self, o): return _Sym(f"({self._w(o).s} + {self.s})")
    def __sub__(self, o): return _Sym(f"({self.s} - {self._w(o).s})")
    def __rsub__(self, o): return _Sym(f"({self._w(o).s} - {self.s})")
    def __mul__(self, o): return _Sym(f"({self.s} * {self._w(o).s})")
    def __rmul__(self, o): return _Sym(f"({self._w(o).s} * {self.s})")
    def __truediv__(self, o): return _Sym(f"({self.s} / {self._w(o).s})")
    def __rtruediv__(self, o): return _Sym(f"({self._w(o).s} / {self.s})")
    def __pow__(self, k): return _Sym(f"({self.s} ** {int(k)})")
    def __neg__(self): return _Sym(f"(-{self.s})")


class _SymOps:
    sin = staticmethod(lambda a: _Sym(f"sin({a.s})"))
    cos = staticmethod(lambda a: _Sym(f"cos({a.s})"))
    sqrt = staticmethod(lambda a: _Sym(f"sqrt({a.s})"))
    log = staticmethod(lambda a: _Sym(f"log({a.s})"))
    maximum = staticmethod(lambda a, b: _Sym(f"max({_Sym._w(a).s}, {_Sym._w(b).s})"))


def _profile(u, w, power: int):
    """g = (1 - u^2)^power and its derivatives in R (u = (R - Rc) / w): g, g_R, g_RR."""
    if power < 2 or int(power) != power:
        raise ValueError(f"twist power {power!r}: use an integer >= 2 (the rim must be traction free)")
    q = 1.0 - u * u
    if power == 2:                       # the original solutions' expressions, term for term
        return q * q, -4.0 * u * q / w, (12.0 * u * u - 4.0) / (w * w)
    pw = lambda k: q if k == 1 else q ** k  # noqa: E731
    n = int(power)
    return pw(n), -2.0 * n * u * pw(n - 1) / w, (-2.0 * n / (w * w)) * pw(n - 2) * (q - 2.0 * (n - 1) * u * u)


def _time_profile(kind: str, t, T, ops):
    """h, dh/dt, d2h/dt2."""
    pi = math.pi
    if kind == "sin":
        a = pi / T
        return ops.sin(a * t), a * ops.cos(a * t), -(a * a) * ops.sin(a * t)
    if kind == "pulse":
        a = 2.0 * pi / T
        return 0.5 - 0.5 * ops.cos(a * t), 0.5 * a * ops.sin(a * t), 0.5 * (a * a) * ops.cos(a * t)
    raise ValueError(f"time profile {kind!r}: use 'sin' or 'pulse'")


def _stress(law: str, gam, mu, ops):
    """(s_rr, s_rt, s_rr - s_tt) and their derivatives d/d gamma (s_rr', s_rt') in the current polar frame."""
    s = ops.sqrt(4.0 + gam * gam)
    if law == "fixed_corotated":
        srr = 2.0 * mu * (1.0 - 2.0 / s)
        srt = 2.0 * mu * gam * (1.0 - 1.0 / s)
        diff = -2.0 * mu * gam * gam * (1.0 - 1.0 / s)
        d_srr = 4.0 * mu * gam / (s * s * s)
        d_srt = 2.0 * mu * (1.0 - 1.0 / s + gam * gam / (s * s * s))
    elif law == "hencky":
        L = ops.log(0.5 * (gam + s))          # asinh(gamma / 2)
        srr = -2.0 * mu * L * gam / s
        srt = 4.0 * mu * L / s
        diff = -4.0 * mu * L * gam / s
        d_srr = -2.0 * mu * (gam / (s * s) + 4.0 * L / (s * s * s))
        d_srt = 4.0 * mu * (1.0 / (s * s) - L * gam / (s * s * s))
    else:
        raise ValueError(f"law {law!r}: use one of {sorted(LAWS)}")
    return srr, srt, diff, d_srr, d_srt


def fields(X0, X1, t, c: dict, time_kind: str, law: str, ops, power: int = 2) -> dict[str, Any]:
    """Every closed-form quantity at reference point (X0, X1), time t (``c``: :meth:`Twist.constants`;
    ``ops``: ``numpy`` or the string arithmetic; ``power``: :attr:`Twist.power`). Returns alpha, its
    derivatives, gamma, the stress, and the body force components ``bx, by``."""
    A, Rc, w, T, mu, rho = c["A"], c["Rc"], c["w"], c["T"], c["mu"], c["rho"]
    R = ops.maximum(ops.sqrt(X0 * X0 + X1 * X1), 1e-30)
    u = (R - Rc) / w
    g, g_R, g_RR = _profile(u, w, power)
    h, h_t, h_tt = _time_profile(time_kind, t, T, ops)
    alpha, alpha_t, alpha_tt = A * g * h, A * g * h_t, A * g * h_tt
    gam = A * h * R * g_R
    gam_R = A * h * (g_R + R * g_RR)
    srr, srt, diff, d_srr, d_srt = _stress(law, gam, mu, ops)
    # b = a - div(sigma) / rho, polar components divided by R (e_r = Q X / R, e_theta = Q J X / R)
    br_R = -alpha_t * alpha_t - (d_srr * gam_R + diff / R) / (rho * R)
    bt_R = alpha_tt - (d_srt * gam_R + 2.0 * srt / R) / (rho * R)
    ca, sa = ops.cos(alpha), ops.sin(alpha)
    qx, qy = ca * X0 - sa * X1, sa * X0 + ca * X1        # Q X = r e_r
    bx = br_R * qx - bt_R * qy
    by = br_R * qy + bt_R * qx
    return {"R": R, "alpha": alpha, "alpha_t": alpha_t, "alpha_tt": alpha_tt, "gamma": gam, "gamma_R": gam_R,
            "gamma_t": A * h_t * R * g_R, "s_rr": srr, "s_rt": srt, "s_rr_minus_s_tt": diff, "bx": bx, "by": by}


def _np_fields(tw: Twist, X: np.ndarray, t: float) -> dict[str, Any]:
    X = np.asarray(X, float)
    return fields(X[:, 0], X[:, 1], float(t), tw.constants(), tw.time, tw.law, np, tw.power)


def exact(tw: Twist, X: np.ndarray, t: float) -> dict[str, np.ndarray]:
    """Closed form at reference positions X [N, 2], time t: ``x``, ``U`` = x - X, ``v``, ``F`` [N, 2, 2],
    ``L`` = grad v = dF/dt F^-1 [N, 2, 2] (the APIC affine field), ``gamma`` [N]."""
    X = np.asarray(X, float)
    f = _np_fields(tw, X, t)
    ca, sa = np.cos(f["alpha"]), np.sin(f["alpha"])
    Q = np.stack([np.stack([ca, -sa], -1), np.stack([sa, ca], -1)], -2)
    x = np.einsum("nij,nj->ni", Q, X)
    Jx = np.stack([-x[:, 1], x[:, 0]], -1)                 # r e_theta
    v = f["alpha_t"][:, None] * Jx
    R = f["R"][:, None]
    eR, eT = X / R, np.stack([-X[:, 1], X[:, 0]], -1) / R  # reference polar basis
    S = np.eye(2)[None] + f["gamma"][:, None, None] * np.einsum("ni,nj->nij", eT, eR)
    F = Q @ S
    J2 = np.array([[0.0, -1.0], [1.0, 0.0]])
    shear_dir = Q @ np.einsum("ni,nj->nij", eT, eR)          # e_theta (x) e_R
    Fdot = f["alpha_t"][:, None, None] * (J2[None] @ F) + f["gamma_t"][:, None, None] * shear_dir
    return {"x": x, "U": x - X, "v": v, "F": F, "L": Fdot @ np.linalg.inv(F), "gamma": f["gamma"]}


def body_force(tw: Twist, X: np.ndarray, t: float) -> np.ndarray:
    """The manufactured body force b(X, t) per unit mass [N, 2] (NumPy float64)."""
    f = _np_fields(tw, X, t)
    return np.stack([f["bx"], f["by"]], -1)


def body_force_expressions(tw: Twist) -> dict[str, Any]:
    """The ``expression`` body force's ``values`` for this solution: two strings in X[0], X[1], t and the
    constants A, Rc, w, T, mu, rho (their values are the field's parameters, packed in sorted order)."""
    names = sorted(tw.constants())
    c = {k: _Sym(k) for k in names}
    f = fields(_Sym("X[0]"), _Sym("X[1]"), _Sym("t"), c, tw.time, tw.law, _SymOps, tw.power)
    return {"b": [f["bx"].s, f["by"].s], "constants": tw.constants()}


# ---------------------------------------------------------------------------------------------
# scene
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Annulus(Shape):
    """An annulus r_in <= |x - center| <= r_out in 2D (a disc for r_in = 0)."""

    center: tuple[float, float]
    r_in: float
    r_out: float

    def bounds(self, dim):
        c = np.asarray(self.center, float)
        return c - self.r_out, c + self.r_out

    def contains(self, x):
        r2 = np.sum((x - np.asarray(self.center)) ** 2, axis=1)
        return (r2 >= self.r_in**2) & (r2 <= self.r_out**2)

    def volume(self, dim):
        return math.pi * (self.r_out**2 - self.r_in**2)


def scene(tw: Twist | str = "annulus", dx: float = 0.05, particles_per_axis: int = 2, t_end: float | None = None,
          cfl: float = 0.3, affine: bool = True, pad_cells: int = 4, dt: float | None = None,
          step_multiple: int = 1, dt_scale: float = 1.0) -> Scene:
    """The solution's 2D plane-strain scene: the annulus/disc centred at the origin, no walls, no
    gravity, the exact body force (``expression`` field), the exact initial velocity and (``affine``)
    C = grad v at t = 0 (needs APIC/MLS/TPIC; pass False for PIC/FLIP). F = I at t = 0 (h(0) = 0).

    dt: fixed, ``t_end / n`` with n = ceil(t_end / (cfl dx / (c_p + max |v|))) rounded up to a multiple of
    ``step_multiple`` (frames at the same times on every grid), so that ``t_end`` (default: 1.1 x the peak
    time, past the peak deformation) is hit exactly; or give ``dt``. ``dt_scale``: that step count divided
    by it (rounded), so t_end is still hit exactly (dt/2: ``dt_scale`` 0.5)."""
    from ..boundaries.body_force import BodyForce

    tw = solution(tw) if isinstance(tw, str) else tw
    if tw.law not in LAWS:
        raise ValueError(f"law {tw.law!r}: use one of {sorted(LAWS)}")
    t_end = 1.1 * tw.t_peak if t_end is None else t_end
    params = {"E": tw.E, "nu": tw.nu}
    if tw.law == "hencky":
        params["yield_stress"] = 1.0e30
    k = particles_per_axis
    body = Body(shape=Annulus((0.0, 0.0), tw.r_in, tw.r_out), material=LAWS[tw.law], params=params,
                density=tw.density, particles_per_cell=k * k, name=tw.name,
                velocity=lambda x: exact(tw, x, 0.0)["v"],
                C=(lambda x: exact(tw, x, 0.0)["L"]) if affine else None)
    half = tw.r_out + pad_cells * dx
    n = int(math.ceil(half / dx))
    lo, hi = [-n * dx] * 2, [n * dx] * 2
    if dt is None:
        c = tw.wave_speeds()[1] + tw.peak_speed()
        steps = int(math.ceil(t_end / (cfl * dx / c) / step_multiple)) * step_multiple
        dt = t_end / (steps if dt_scale == 1.0 else int(round(steps / dt_scale)))
    bf = BodyForce(field="expression", values=body_force_expressions(tw))
    return Scene(dim=2, dx=dx, domain=(lo, hi), bodies=[body], gravity=None, boundaries=[bf], dt=dt, cfl=cfl,
                 cfl_limit=max(0.6, 1.01 * cfl), name=f"large_shear_{tw.name}_{tw.law}_{dx:g}")


def displacement_error(tw: Twist, X0: np.ndarray, x: np.ndarray, t: float) -> dict[str, float]:
    """Particle-RMS |x - X - U(X, t)| [m] and relative to the RMS of |U(X, t)|; max error and where."""
    ex = exact(tw, X0, t)
    e = np.linalg.norm(x - ex["x"], axis=1)
    rms = float(np.sqrt(np.mean(e**2)))
    u_rms = float(np.sqrt(np.mean(np.sum(ex["U"] ** 2, axis=1))))
    p = int(np.argmax(e))
    return {"displacement_error": rms, "relative_error": rms / u_rms if u_rms > 0 else float("nan"),
            "max_error": float(e[p]), "max_error_radius": float(np.linalg.norm(X0[p]))}


def make_transfer_for(transfer: str, shape_function: str = "quadratic"):
    """The transfer object for a (transfer, shape function) pair (the shape goes to the stepper as
    ``shape``; this only checks that it is one the runs know)."""
    from ..transfers import make_transfer

    if shape_function not in SHAPE_FUNCTIONS:
        raise ValueError(f"shape function {shape_function!r}: mpmlab has {SHAPE_FUNCTIONS}")
    return make_transfer(transfer)


def run(tw: Twist | str = "annulus", dx: float = 0.05, backend: str = "jax", transfer: str = "apic",
        precision: str = "fp64", shape_function: str = "quadratic", t_end: float | None = None,
        frames: int = 22, particles_per_axis: int = 2, cfl: float = 0.3, dt_scale: float = 1.0,
        check_every: int | None = None, on_frame: Callable | None = None, keep_x: bool = False) -> dict[str, Any]:
    """Roll the solution out to ``t_end`` keeping ``frames`` frames; score each frame
    (:func:`displacement_error`). A divergence ends the run: its time, step and diagnosis are returned
    (``diverged``, ``t_diverged``, ``cause``, ``message``, ``measures``), not raised. ``keep_x``: also return
    the last frame's particle positions (``x_last``) and the reference positions (``X0``)."""
    from ..core.errors import SimulationDiverged
    from ..simulator import build_stepper

    tw = solution(tw) if isinstance(tw, str) else tw
    t_end = 1.1 * tw.t_peak if t_end is None else t_end
    affine = transfer in ("apic", "mls", "tpic")
    sc = scene(tw, dx=dx, particles_per_axis=particles_per_axis, t_end=t_end, cfl=cfl, affine=affine,
               step_multiple=frames, dt_scale=dt_scale)
    dt = sc.resolve_dt()
    steps = int(round(t_end / dt))
    every = max(1, steps // frames)     # frames at t_end k / frames on every grid (steps is a multiple)
    X0 = sc.particles().x
    hist: list[dict[str, float]] = []
    last: dict[str, Any] = {}

    def frame(i, npstate):
        last["x"] = np.array(npstate["x"], float)
        e = displacement_error(tw, X0, npstate["x"].astype(float), float(npstate["time"]))
        F = npstate.get("F")
        Jdev = float(np.max(np.abs(np.linalg.det(F) - 1.0))) if F is not None else float("nan")
        hist.append({"t": float(npstate["time"]), "step": int(npstate["step"]), **e, "max_abs_J_minus_1": Jdev})
        if on_frame is not None:
            on_frame(hist[-1])

    t0 = time.perf_counter()
    st = build_stepper(sc, backend=backend, transfer=make_transfer_for(transfer, shape_function),
                       precision=precision, check_every=check_every, shape=shape_function)
    out: dict[str, Any] = {"solution": tw.name, "law": tw.law, "A": tw.A, "dx": dx, "backend": backend,
                           "transfer": transfer, "shape_function": shape_function, "precision": precision,
                           "particles": int(len(X0)), "dt": dt, "steps": steps, "t_end": t_end,
                           "peak_shear": tw.peak_shear(), "particles_per_axis": particles_per_axis}
    try:
        st.rollout(steps=steps, every=every, progress=False, on_frame=frame, keep_frames=False)
        out.update(diverged=False)
    except SimulationDiverged as e:
        out.update(diverged=True, step_diverged=e.step, t_diverged=e.step * dt, cause=getattr(e, "cause", None),
                   message=str(e), measures=getattr(e, "measures", None))
    out["run_s"] = time.perf_counter() - t0
    if keep_x:
        out["x_last"], out["X0"] = last.get("x"), X0
    out["history"] = hist
    fin = hist[-1] if hist else {}
    out.update({k: fin.get(k) for k in ("displacement_error", "relative_error", "max_error")})
    out["t_last"] = fin.get("t")
    return out
