"""Validation scenes with analytic references (verification note cases 1a/1c, 2a, 3a, 3c).

Each builder returns a plain :class:`mpmlab.Scene`; the matching ``*_reference`` / ``measure_*``
functions hold the closed forms and the post-processing used by ``benchmarks/validation.py`` and
``tests/test_validation.py``.

Geometry convention (all three cases): a wall of ``thickness`` cells constrains the grid nodes with
index ``< thickness`` (``> cells - thickness`` on the upper faces). The domain origin is placed at
``-(thickness - 1) dx`` so that the innermost constrained node lies exactly on the physical wall
plane ``x = 0`` (and ``y = 0``): the fixed end of the bar, the back wall and floor of the dam break,
the base and the rollers of the hydrostatic column. ``thickness = 2`` is the smallest value for which
the first particle row (half a particle spacing off the wall) stays inside the domain interior that
quadratic B-splines need (``>= origin + dx / 2``).

* :func:`vibrating_bar` -- an elastic bar (fixed corotated, nu = 0, so c = sqrt(E / rho)) fixed at
  x = 0 by a sticky wall, free at x = L, started in its first mode v = v0 sin(beta1 x). mpmlab has no
  1D mode: ``lateral="strip"`` is the 1D bar, one cell thick, in a 4-cell-wide lateral grid whose
  faces are slip walls 2 cells thick: every lateral node row has v_y = 0 except the middle one, which
  lies on the strip's mid-plane where v_y = 0 by symmetry (a true 1D problem; measured |v_y| <= 1e-16);
  ``lateral="free"`` is the 2D (or 3D) bar of finite height with free lateral surfaces (with
  nu = 0 there is no Poisson coupling, so the bar is still in uniaxial stress, case 1c).
* :func:`ritter_dam_break` -- the 2D water dam break of JAX-MPM Sec. 4.1.1 (Du & He 2025):
  H0 = 0.1 m, L0 = 1 m, weakly compressible Newtonian fluid with c = 35 m/s, slip walls.
* :func:`hydrostatic_column` -- CB-Geo's hydrostatic column: w = 0.2, h = 0.1 m, rho = 1800,
  bulk modulus 1e6 Pa, roller (slip) sides, 25 particles per cell.
* :func:`mms_axis_aligned` -- the axis-aligned manufactured solution (2a) on the unit square/cube,
  driven by the ``body_force`` boundary; :func:`run_mms` scores the particle displacement against U(X, t).
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np

from ..boundaries import Walls
from ..core import registry
from ..core.scene import Body, Scene

G = 9.81

__all__ = [
    "G", "ProfiledScene", "vibrating_bar", "bar_wave_speed", "bar_reference", "measure_period", "ritter_dam_break",
    "ritter_front", "measure_front", "column_depth", "hydrostatic_column", "hydrostatic_base_stress",
    "particle_sigma_yy", "fit_base_stress", "CBGEO_HYDROSTATIC", "run_vibrating_bar", "run_dam_break",
    "run_hydrostatic_column", "MMS_LAW_NAMES", "mms_axis_aligned", "mms_exact", "mms_errors", "run_mms",
]


# ---------------------------------------------------------------------------------------------
# a Scene whose initial particle velocity is a function of position
# ---------------------------------------------------------------------------------------------
@dataclass
class ProfiledScene(Scene):
    """A ``Scene`` whose initial particle velocities get ``velocity_profile(x) -> [N, D]`` added to every
    body's own velocity (the bar's first mode v0 sin(beta1 x)). Kept for its callers: a ``Body`` takes a
    velocity function (or an array, or expressions) itself, and this is what the profile becomes --
    each body's ``velocity`` replaced by its own plus the profile."""

    velocity_profile: Callable[[np.ndarray], np.ndarray] | None = None

    def __post_init__(self):
        super().__post_init__()
        if self.velocity_profile is not None:
            self.bodies = [dataclasses.replace(b, velocity=_with_profile(b.velocity, self.velocity_profile, self.dim,
                                                                         f"scene '{self.name}', body {b.name or i}"))
                           for i, b in enumerate(self.bodies)]


def _with_profile(own: Any, profile: Callable, dim: int, where: str) -> Callable:
    from ..core.initial_fields import resolve

    def velocity(x):
        v = np.asarray(profile(x), float).reshape(x.shape)
        return v if own is None else v + resolve(own, x, (dim,), "velocity", where)

    return velocity


def _walls(dim: int, faces: dict[str, str], thickness: int) -> Walls:
    return Walls(default="none", faces=faces, thickness=thickness)


# ---------------------------------------------------------------------------------------------
# 1a / 1c: vibrating bar
# ---------------------------------------------------------------------------------------------
def bar_wave_speed(E: float, density: float, nu: float = 0.0, dim: int = 2, lateral: str = "strip") -> float:
    """Long-wave axial speed of the bar (verification 1c): laterally confined (``strip``: slip walls
    hold every lateral node) c_p = sqrt((lambda + 2 mu) / rho); free lateral surfaces: uniaxial stress,
    c = sqrt(E / rho) in 3D and sqrt(E / ((1 - nu^2) rho)) in 2D (plane strain). All equal
    sqrt(E / rho) at nu = 0."""
    if lateral == "strip":
        return math.sqrt(E * (1.0 - nu) / ((1.0 + nu) * (1.0 - 2.0 * nu) * density))
    return math.sqrt(E / density) if dim == 3 else math.sqrt(E / ((1.0 - nu * nu) * density))


def bar_reference(length: float = 25.0, E: float = 100.0, density: float = 1.0, v0: float = 0.1, nu: float = 0.0,
                  dim: int = 2, lateral: str = "strip") -> dict[str, float]:
    """First axial mode of a fixed-free bar (verification 1a): beta1 = pi / 2L, omega1 = beta1 c
    (c from :func:`bar_wave_speed`; sqrt(E / rho) at nu = 0). ``v(x, t) = v0 cos(omega1 t) sin(beta1 x)``;
    the centre-of-mass velocity is ``v0 cos(omega1 t) (1 - cos(beta1 L)) / (beta1 L) = (2 v0 / pi) cos(omega1 t)``."""
    c = bar_wave_speed(E, density, nu, dim, lateral)
    beta = math.pi / (2.0 * length)
    omega = beta * c
    return {"c": c, "beta": beta, "omega": omega, "period": 2.0 * math.pi / omega,
            "v_com_amplitude": v0 * (1.0 - math.cos(beta * length)) / (beta * length)}


def vibrating_bar(dim: int = 2, cells: int = 50, length: float = 25.0, E: float = 100.0, density: float = 1.0,
                  v0: float = 0.1, nu: float = 0.0, particles_per_cell: int | None = None, lateral: str = "strip",
                  height_cells: int = 1, cfl: float = 0.1, thickness: int = 2) -> Scene:
    """Fixed-free elastic bar in its first mode (verification 1a "1D" / 1c "2D, 3D").

    Args:
        dim: 2 or 3.
        cells: cells along the bar (dx = length / cells).
        length, E, density, v0: bar length [m], Young's modulus [Pa], density [kg/m^3], mode amplitude [m/s].
        nu: Poisson ratio (0 for cases 1a/1c; otherwise the wave speed of :func:`bar_wave_speed` applies).
        particles_per_cell: k^dim points per cell (default 2^dim).
        lateral: ``"strip"`` -- 1D bar: ``height_cells`` cells thick, lateral faces slip walls
            ``thickness`` cells thick; with one cell and thickness 2 they hold every lateral node row
            but the middle one, on the strip's mid-plane (v_y = 0 there by symmetry);
            ``"free"`` -- 2D/3D bar with free lateral surfaces (uniaxial stress because nu = 0).
        height_cells: bar thickness in cells (``"strip"`` uses 1 unless given).
        cfl: dt = cfl dx / (c + |v|max) (verification 1a uses 0.1).
        thickness: wall thickness in cells (>= 2; the innermost sticky node is at x = 0).
    """
    if lateral not in ("strip", "free"):
        raise ValueError(f"lateral = {lateral!r}: use 'strip' or 'free'")
    if thickness < 2:
        raise ValueError("thickness must be >= 2 (see module docstring)")
    dx = length / cells
    ppc = particles_per_cell or 2**dim
    t = thickness
    origin_x = -(t - 1) * dx
    if lateral == "strip":
        # lateral grid: as few cells as Walls allows (thickness <= cells // 2), strip centred in it
        n_lat = max(height_cells + 2 * (t - 1), 2 * t)
        lat_faces = "slip"
    else:
        n_lat = height_cells + 2 * (t + 1)            # free margin: no lateral node is constrained
        lat_faces = "none"
    pad = (n_lat - height_cells) / 2.0
    lo = [origin_x] + [-pad * dx] * (dim - 1)
    hi = [length + (t + 2) * dx] + [(height_cells + pad) * dx] * (dim - 1)
    faces = {"x-": "sticky"}
    for a in "yz"[: dim - 1]:
        faces[f"{a}-"] = lat_faces
        faces[f"{a}+"] = lat_faces
    beta = math.pi / (2.0 * length)
    body = Body(shape={"kind": "box", "lo": [0.0] * dim, "hi": [length] + [height_cells * dx] * (dim - 1)},
                material="fixed_corotated", params={"E": E, "nu": nu}, density=density,
                particles_per_cell=ppc, name="bar")

    def profile(x):
        v = np.zeros_like(x)
        v[:, 0] = v0 * np.sin(beta * x[:, 0])
        return v

    return ProfiledScene(dim=dim, dx=dx, domain=(lo, hi), bodies=[body], gravity=None,
                         boundaries=[_walls(dim, faces, t)], dt="auto", cfl=cfl,
                         name=f"vibrating_bar_{dim}d_{lateral}_{cells}", velocity_profile=profile)


def measure_period(time: np.ndarray, signal: np.ndarray) -> dict[str, Any]:
    """Period of an oscillating signal from its zero crossings (linear interpolation between frames).

    Returns the period (2 x the least-squares slope of crossing time vs crossing index, i.e. twice
    the mean half-period), the crossing times, the number of cycles spanned, and the ratio of the
    last half-cycle peak |signal| to the initial one (amplitude retention).
    """
    s = np.asarray(signal, float)
    t = np.asarray(time, float)
    idx = np.nonzero(np.sign(s[:-1]) * np.sign(s[1:]) < 0)[0]
    tz = t[idx] - s[idx] * (t[idx + 1] - t[idx]) / (s[idx + 1] - s[idx])
    if len(tz) < 2:
        return {"period": float("nan"), "crossings": tz, "amplitude_ratio": float("nan"), "cycles": 0.0}
    half = np.diff(tz)
    # least-squares slope of crossing time vs crossing index = half period
    k = np.arange(len(tz))
    slope = np.polyfit(k, tz, 1)[0]
    peaks = [np.max(np.abs(s[(t >= a) & (t <= b)])) for a, b in zip(tz[:-1], tz[1:])]
    first = np.max(np.abs(s[t <= tz[0]])) if np.any(t <= tz[0]) else peaks[0]
    return {"period": float(2.0 * slope), "half_periods": half, "crossings": tz,
            "amplitude_ratio": float(peaks[-1] / first) if first > 0 else float("nan"),
            "cycles": float((tz[-1] - tz[0]) / (2.0 * slope))}


# ---------------------------------------------------------------------------------------------
# 3a: Ritter dam break
# ---------------------------------------------------------------------------------------------
def ritter_front(y: Any, t: Any, H0: float = 0.1, L0: float = 1.0, g: float = 9.8) -> np.ndarray:
    """Ritter (1892) dry-bed dam break: the point of the free surface at height y, time t:
    ``x = L0 + (2 sqrt(g H0) - 3 sqrt(g y)) t`` (0 <= y <= H0; tip speed 2 sqrt(g H0))."""
    y = np.asarray(y, float)
    t = np.asarray(t, float)
    return L0 + (2.0 * np.sqrt(g * H0) - 3.0 * np.sqrt(g * y)) * t


def ritter_dam_break(dx: float = 0.008, H0: float = 0.1, L0: float = 1.0, length: float = 2.0,
                     height: float = 0.12, sound_speed: float = 35.0, viscosity: float = 0.0, g: float = 9.8,
                     density: float = 1000.0, particles_per_cell: int = 4, dt: Any = "auto", cfl: float = 0.3,
                     law: str = "newtonian_fluid", wall: str = "slip", thickness: int = 2,
                     min_pressure: float = 0.0) -> Scene:
    """2D dam break (JAX-MPM Sec. 4.1.1): a water column L0 x H0 at the back wall x = 0 on the floor
    y = 0 of a ``length`` x ``height`` tank with ``wall`` (slip) walls; dam removed at t = 0.

    The paper uses dx = 4 mm, 2 x 2 particles per cell, dt = 1e-5 s, c = 35 m/s (K = rho c^2 = 1.225 MPa),
    zero viscosity, g = 9.8 m/s^2.
    ``law``: ``"newtonian_fluid"`` (params sound_speed, viscosity, min_pressure) or ``"weakly_compressible"``
    (bulk_modulus = rho c^2).
    ``min_pressure``: the fluid's tension cut-off p >= min_pressure (default 0: water carries no tension;
    ``-1e30`` is JAX-MPM's Eq. 20 as written, which lets the stretching front carry up to -33 kPa and
    holds it back by 30-80 %, benchmarks/validation.md).

    Geometry: with ``thickness`` = 2 the grid nodes at index 0 and 1 of every face are walls and node 1
    lies on x = 0 / y = 0, so the back wall and the floor are exactly the planes x = 0 and y = 0 that the
    body starts on (first particles a quarter cell off them); Ritter's x is measured from the same
    origin, the dam site is x = L0. The back wall is reached by the reflected rarefaction only at
    t = L0 / sqrt(g H0) = 1.01 s, after the scored window.
    """
    t = thickness
    n_x = int(round(length / dx))
    n_y = int(round(height / dx))
    lo = [-(t - 1) * dx, -(t - 1) * dx]
    hi = [n_x * dx + (t - 1) * dx, n_y * dx + (t - 1) * dx]
    names = set(registry.laws.get(law).param_names())
    if {"sound_speed", "viscosity", "rest_density"} <= names:        # newtonian_fluid and its variants
        params = {"sound_speed": sound_speed, "viscosity": viscosity, "rest_density": density}
        if "min_pressure" in names:
            params["min_pressure"] = min_pressure
    elif names == {"bulk_modulus"}:                                     # weakly_compressible
        params = {"bulk_modulus": density * sound_speed**2}
    else:
        raise ValueError(f"law {law!r}: use 'newtonian_fluid' or 'weakly_compressible'")
    body = Body(shape={"kind": "box", "lo": [0.0, 0.0], "hi": [L0, H0]}, material=law, params=params,
                density=density, particles_per_cell=particles_per_cell, name="water")
    faces = {"x-": wall, "x+": wall, "y-": wall, "y+": wall}
    return Scene(dim=2, dx=dx, domain=(lo, hi), bodies=[body], gravity=[0.0, -g],
                 boundaries=[_walls(2, faces, t)], dt=dt, cfl=cfl, cfl_limit=0.5,
                 name=f"ritter_dam_break_{dx * 1000:g}mm")


def column_depth(x: np.ndarray, area: np.ndarray, dx: float, x_max: float) -> tuple[np.ndarray, np.ndarray]:
    """Water depth h(x) at nodes x_i = i dx (0 <= x_i <= x_max): the particle areas spread over x with a
    quadratic B-spline of spacing ``dx``, h_i = sum_p A_p N((x_p - x_i) / dx) / dx.

    ``area``: per-particle current area (V0 J). The B-spline is a partition of unity, so sum_i h_i dx is
    the total area; unlike a histogram it does not alias with the particle columns. Returns (x_i, h_i).
    (``measure_front`` passes dx = 2 x the grid spacing: the particle columns in the thin, stretched
    tip region are up to a cell apart and would otherwise make h(x) ripple.)
    """
    n = int(round(x_max / dx)) + 1
    xi = np.arange(n) * dx
    X = x[:, 0] / dx
    base = np.floor(X - 0.5).astype(int)
    fx = X - base
    w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2]
    h = np.zeros(n)
    for k in range(3):
        i = base + k
        ok = (i >= 0) & (i < n)
        np.add.at(h, i[ok], (area * w[k])[ok])
    return xi, h / dx


def measure_front(x: np.ndarray, area: np.ndarray, dx: float, levels: Sequence[float], x_max: float,
                  smoothing: float = 2.0) -> np.ndarray:
    """Simulated surface position at each height y in ``levels``: the last node (counted from the back
    wall) whose depth (:func:`column_depth`, spacing ``smoothing`` x dx) reaches y, linearly interpolated
    to the next node.

    A depth-based front ignores the thin (one cell) tip and single stray particles by construction."""
    dx = smoothing * dx
    xi, h = column_depth(x, area, dx, x_max)
    out = []
    for y in levels:
        above = np.nonzero(h >= y)[0]
        if len(above) == 0:
            out.append(np.nan)
            continue
        i = above[-1]
        if i + 1 < len(h) and h[i] > h[i + 1]:
            out.append(xi[i] + (h[i] - y) / (h[i] - h[i + 1]) * dx)
        else:
            out.append(xi[i])
    return np.asarray(out)


# ---------------------------------------------------------------------------------------------
# 3c: hydrostatic column
# ---------------------------------------------------------------------------------------------
CBGEO_HYDROSTATIC = {  # cb-geo/mpm-doc user/validation/explicit/hydrostatic-column: base sigma_yy [Pa]
    0.010: -1680.2, 0.005: -1724.6, 0.0025: -1746.8,
}


def hydrostatic_base_stress(density: float = 1800.0, height: float = 0.1, g: float = G) -> float:
    """sigma_yy at the base of a column at rest: -rho g h (= -1765.8 Pa for the CB-Geo column)."""
    return -density * g * height


def hydrostatic_column(dx: float = 0.005, width: float = 0.2, height: float = 0.1, density: float = 1800.0,
                       bulk_modulus: float = 1.0e6, particles_per_cell: int = 25, law: str = "newtonian_fluid",
                       viscosity: float = 0.0, base: str = "slip", sides: str = "slip", dt: Any = "auto",
                       cfl: float = 0.3, headroom_cells: int = 4, thickness: int = 2) -> Scene:
    """CB-Geo hydrostatic column: ``width`` x ``height`` of fluid (or ``fixed_corotated`` with E = K,
    nu = 0) on a ``base`` wall (slip / sticky) at y = 0 between roller (``sides`` = slip) walls at
    x = 0 and x = width; gravity switched on at t = 0.

    ``law``: ``"newtonian_fluid"`` (sound_speed = sqrt(K / rho)), ``"weakly_compressible"``
    (bulk_modulus = K) or ``"fixed_corotated"`` (E = K, nu = 0).
    """
    t = thickness
    n_x = int(round(width / dx))
    if abs(n_x * dx - width) > 1e-9 * width:
        raise ValueError(f"width {width} is not a multiple of dx {dx}")
    lo = [-(t - 1) * dx, -(t - 1) * dx]
    hi = [width + (t - 1) * dx, height + (headroom_cells + t) * dx]
    if law == "newtonian_fluid":
        params = {"sound_speed": math.sqrt(bulk_modulus / density), "viscosity": viscosity, "rest_density": density}
    elif law == "weakly_compressible":
        params = {"bulk_modulus": bulk_modulus}
    elif law == "fixed_corotated":
        params = {"E": bulk_modulus, "nu": 0.0}
    else:
        raise ValueError(f"law {law!r}: use 'newtonian_fluid', 'weakly_compressible' or 'fixed_corotated'")
    body = Body(shape={"kind": "box", "lo": [0.0, 0.0], "hi": [width, height]}, material=law, params=params,
                density=density, particles_per_cell=particles_per_cell, name="column")
    faces = {"x-": sides, "x+": sides, "y-": base, "y+": "none"}
    return Scene(dim=2, dx=dx, domain=(lo, hi), bodies=[body], gravity=[0.0, -G],
                 boundaries=[_walls(2, faces, t)], dt=dt, cfl=cfl,
                 name=f"hydrostatic_column_{dx * 1000:g}mm")


def particle_sigma_yy(traj, frame: int | slice = -1) -> np.ndarray:
    """Particle Cauchy sigma_yy [Pa] from a trajectory, whatever the law stores:

    * ``sigma`` field (newtonian_fluid: Cauchy stress);
    * ``J`` field only (weakly_compressible): sigma = tau / J, read from the law's own NumPy reference
      ``kirchhoff`` so the equation of state is the law's, not a copy;
    * ``F`` field (fixed_corotated): sigma = tau / J from the law's reference.
    """
    law = registry.laws.get(traj.materials[0]["law"])
    prm = traj.params[0, : len(traj.materials[0]["param_names"])]
    if "sigma" in traj.fields:
        return np.asarray(traj.fields["sigma"][frame])[..., 1, 1]
    name = "J" if "J" in traj.fields else "F" if "F" in traj.fields else None
    if name is None:
        raise KeyError("trajectory has none of the fields sigma, J, F; roll out with fields=('sigma',) / ('J',) / ('F',)")
    arr = np.asarray(traj.fields[name][frame])
    single = arr.ndim == (1 if name == "J" else 3)
    arr = arr[None] if single else arr
    dim = traj.meta["dim"]
    ref = law.reference
    flat = arr.reshape((-1,) + arr.shape[2:])
    J = flat if name == "J" else np.linalg.det(flat)

    def tau_of(st):
        try:
            return np.asarray(ref.kirchhoff(st, prm, dim=dim))
        except TypeError:
            return np.asarray(ref.kirchhoff(st, prm))

    try:  # vectorised: J[:, None, None] / F[n, d, d] broadcast through the reference formula
        tau = tau_of({name: flat[:, None, None] if name == "J" else flat})
        if tau.shape != (len(flat), dim, dim):
            raise ValueError
    except Exception:  # fall back to one particle at a time
        tau = np.stack([tau_of({name: a}) for a in flat])
    out = (tau[:, 1, 1] / J).reshape(arr.shape[:2])
    return out[0] if single else out


def fit_base_stress(y: np.ndarray, sigma_yy: np.ndarray, base: float = 0.0) -> dict[str, float]:
    """Least-squares line sigma_yy = a + b y through the particles, extrapolated to the base y = ``base``."""
    b, a = np.polyfit(np.asarray(y, float) - base, np.asarray(sigma_yy, float), 1)
    return {"base_stress": float(a), "slope": float(b)}


# ---------------------------------------------------------------------------------------------
# runners shared by benchmarks/validation.py and tests/test_validation.py
# ---------------------------------------------------------------------------------------------
def _rollout(scene, backend, transfer, precision, steps, every, fields=()):
    import time

    from ..simulator import build_stepper
    from ..transfers import make_transfer

    tr = make_transfer(transfer) if isinstance(transfer, str) else transfer
    t0 = time.perf_counter()
    stepper = build_stepper(scene, backend=backend, transfer=tr, precision=precision)
    build = time.perf_counter() - t0
    t0 = time.perf_counter()
    traj = stepper.rollout(steps=steps, every=every, fields=tuple(fields), progress=False)
    return stepper, traj, {"build_s": build, "run_s": time.perf_counter() - t0}


def run_vibrating_bar(backend: str = "jax", transfer: Any = "apic", precision: str = "fp64", periods: float = 3.0,
                      frames_per_period: int = 200, **scene_kw) -> dict[str, Any]:
    """Roll the bar out for ``periods`` analytic periods; period from the zero crossings of the
    centre-of-mass velocity (:func:`measure_period`)."""
    scene = vibrating_bar(**scene_kw)
    kw = {k: scene_kw[k] for k in ("length", "E", "density", "v0", "nu", "dim", "lateral") if k in scene_kw}
    ref = bar_reference(**kw)
    dt = scene.resolve_dt()
    every = max(1, int(round(ref["period"] / frames_per_period / dt)))
    steps = int(math.ceil(periods * ref["period"] / (every * dt))) * every
    stepper, traj, timing = _rollout(scene, backend, transfer, precision, steps, every)
    v_com = (traj.v[:, :, 0] * traj.mass).sum(1) / traj.mass.sum()
    m = measure_period(traj.time, v_com)
    return {"scene": scene, "traj": traj, "stepper": stepper, "every": every, "time": traj.time, "v_com": v_com, "reference": ref,
            "period": m["period"], "period_error": m["period"] / ref["period"] - 1.0,
            "amplitude_ratio": m["amplitude_ratio"], "cycles": m["cycles"], "dt": stepper.dt, "steps": steps,
            "particles": traj.particle_count, **timing}


def run_dam_break(backend: str = "jax", transfer: Any = "apic", precision: str = "fp32", t_end: float = 0.45,
                  frame_dt: float = 0.01, levels: Sequence[float] | None = None, window: tuple[float, float] = (0.2, 0.45),
                  **scene_kw) -> dict[str, Any]:
    """Roll the dam break out to ``t_end`` and compare the surface position at heights ``levels``
    (default: 2 dx ... 0.4 H0 in steps of dx) with Ritter at every frame in ``window``.

    Three signed error measures, all over heights ``levels`` and frames in ``window``:

    * ``error`` -- the verification note's e = (x_sim - x_R) / (x_R - L0): relative to how far the
      surface point at height y has moved from the dam site. ``max_abs_error`` over all levels.
      Ill-posed near y = 0.4 H0: x_R - L0 = (2 - 3 sqrt(0.4)) sqrt(g H0) t = 0.103 sqrt(g H0) t, i.e.
      20 mm at t = 0.2 s, so 5 % of it is 1 mm = dx / 4 at dx = 4 mm (sub-cell accuracy of a surface
      point), and Ritter's shallow-water solution is least valid there (vertical accelerations near the dam
      site; t sqrt(g / H0) = 2-4.5 in the window).
    * ``max_abs_error_low`` -- the same e over the heights y <= 0.2 H0 only (x_R - L0 >= 0.66 sqrt(g H0) t).
    * ``error_wave`` -- (x_sim - x_R) / (2 sqrt(g H0) t): the surface position error relative to the
      length of the Ritter wave (dam site to tip) at that time, well-posed at every height.
      ``max_abs_error_wave`` over all levels."""
    scene = ritter_dam_break(**scene_kw)
    dx = scene.dx
    H0, L0 = scene_kw.get("H0", 0.1), scene_kw.get("L0", 1.0)
    g = -float(scene.gravity[1])
    dt = scene.resolve_dt()
    every = max(1, int(round(frame_dt / dt)))
    steps = int(math.ceil(t_end / (every * dt))) * every
    fields = ("J",)
    stepper, traj, timing = _rollout(scene, backend, transfer, precision, steps, every, fields)
    if levels is None:
        levels = np.arange(2 * dx, 0.4 * H0 + 1e-12, dx)
    levels = np.asarray(levels, float)
    x_max = float(scene.domain[1][0])
    fr = np.nonzero((traj.time >= window[0] - 1e-9) & (traj.time <= window[1] + 1e-9))[0]
    J = traj.fields["J"]
    x_sim = np.array([measure_front(traj.x[f], traj.volume * J[f], dx, levels, x_max) for f in fr])
    x_ref = np.array([ritter_front(levels, traj.time[f], H0, L0, g) for f in fr])
    err = (x_sim - x_ref) / (x_ref - L0)
    err_wave = (x_sim - x_ref) / (2.0 * np.sqrt(g * H0) * traj.time[fr][:, None])
    low = levels <= 0.2 * H0 + 1e-12
    tip = traj.x[:, :, 0].max(axis=1)
    return {"scene": scene, "traj": traj, "stepper": stepper, "every": every, "levels": levels, "times": traj.time[fr],
            "x_sim": x_sim, "x_ref": x_ref,
            "error": err, "max_abs_error": float(np.nanmax(np.abs(err))),
            "max_abs_error_low": float(np.nanmax(np.abs(err[:, low]))) if low.any() else float("nan"),
            "error_wave": err_wave, "max_abs_error_wave": float(np.nanmax(np.abs(err_wave))), "tip": tip, "dt": stepper.dt,
            "steps": steps, "particles": traj.particle_count, "H0": H0, "L0": L0, "g": g, **timing}


def run_hydrostatic_column(backend: str = "jax", transfer: Any = "pic", precision: str = "fp64",
                           settle_periods: float = 40.0, average_periods: float = 4.0, frames_per_period: int = 10,
                           **scene_kw) -> dict[str, Any]:
    """Switch gravity on, let the column settle for ``settle_periods`` fundamental periods
    T1 = 4 h / c (PIC damps the oscillation), then time-average particle sigma_yy and y over the last
    ``average_periods`` periods (``frames_per_period`` equally spaced frames each) and fit sigma_yy(y) by
    least squares through all particles, extrapolated to the base y = 0.

    Why the period mean: for the undamped linear 1D column, fixed at the base and free at the top,
    the modes have periods T1 / (2n - 1), so the mean over a whole T1 of the response to suddenly
    applied gravity is exactly the static solution; PIC damping makes what is left small. The
    discrete column's period differs slightly from 4 h / c, so a few periods are averaged (at
    dx = 2.5 mm: 1-T1 means after 40 T1 scatter by +-0.07 % of the base stress, 4-T1 means by less).
    Per-frame fits are kept as ``history_base``."""
    scene = hydrostatic_column(**scene_kw)
    body = scene.bodies[0]
    height = scene_kw.get("height", 0.1)
    K = scene_kw.get("bulk_modulus", 1.0e6)
    c = math.sqrt(K / body.density)
    T1 = 4.0 * height / c
    dt = scene.resolve_dt()
    every = max(1, int(round(T1 / frames_per_period / dt)))
    n_avg = max(1, int(round(average_periods * frames_per_period)))
    frames = int(math.ceil(settle_periods * T1 / (every * dt)))
    steps = frames * every
    field = {"newtonian_fluid": "sigma", "weakly_compressible": "J", "fixed_corotated": "F"}[body.material]
    hist, acc = [], {"s": 0.0, "y": 0.0, "n": 0}

    class _Frame:  # particle_sigma_yy reads a Trajectory-like object; wrap one numpy state
        def __init__(self, npstate, traj_meta):
            self.fields = {field: npstate[field][None]}
            self.materials, self.params, self.meta = traj_meta

    from ..simulator import build_stepper
    from ..transfers import make_transfer
    import time as _time

    t0 = _time.perf_counter()
    stepper = build_stepper(scene, backend=backend, transfer=make_transfer(transfer) if isinstance(transfer, str)
                            else transfer, precision=precision)
    build = _time.perf_counter() - t0
    g = stepper.groups[0]
    meta = ([{"law": g.law.name, "param_names": list(g.law.param_names())}], g.params[:1], {"dim": scene.dim})

    def on_frame(i, npstate):
        if i == 0:
            return
        sig = particle_sigma_yy(_Frame(npstate, meta), 0)
        y = npstate["x"][:, 1]
        hist.append(fit_base_stress(y, sig)["base_stress"])
        if i > frames - n_avg:
            acc["s"] = acc["s"] + sig
            acc["y"] = acc["y"] + y
            acc["n"] += 1

    t0 = _time.perf_counter()
    traj = stepper.rollout(steps=steps, every=every, fields=(), progress=False, on_frame=on_frame)
    run = _time.perf_counter() - t0
    s_avg, y_avg = acc["s"] / acc["n"], acc["y"] / acc["n"]
    fit = fit_base_stress(y_avg, s_avg)
    ref = hydrostatic_base_stress(body.density, height, -float(scene.gravity[1]))
    # the same fit through the particles more than two cells above the base (diagnostic only)
    inner = y_avg > 2.0 * scene.dx
    fit_inner = fit_base_stress(y_avg[inner], s_avg[inner])
    v_scale = math.pi * G * height / (4.0 * c)   # velocity amplitude of the undamped fundamental mode
    return {"scene": scene, "traj": traj, "stepper": stepper, "every": every, "reference": ref,
            "base_stress": fit["base_stress"], "slope": fit["slope"],
            "error": fit["base_stress"] / ref - 1.0, "base_stress_inner": fit_inner["base_stress"],
            "error_inner": fit_inner["base_stress"] / ref - 1.0, "y_avg": y_avg, "sigma_avg": s_avg,
            "history_t": traj.time[1:], "history_base": np.asarray(hist), "averaged_frames": acc["n"],
            "residual_speed": float(np.abs(traj.v[-1]).max() / v_scale), "T1": T1, "dt": stepper.dt,
            "steps": steps, "particles": traj.particle_count, "build_s": build, "run_s": run}


# ---------------------------------------------------------------------------------------------
# 2a: axis-aligned manufactured solution (body force)
# ---------------------------------------------------------------------------------------------
MMS_LAW_NAMES = {"fixed_corotated": "fixed_corotated", "hencky": "hencky_von_mises"}


def mms_axis_aligned(cells: int = 16, dim: int = 2, law: str = "fixed_corotated", E: float = 1.0e4, nu: float = 0.3,
                     density: float = 1.0, amplitude: float = 0.05, c: float | None = None,
                     particles_per_axis: int = 2, cfl: float = 0.3, t_end: float = 0.015,
                     thickness: int = 2, boundary: str = "slip") -> Scene:
    """Verification note #2a on the unit cube (square in 2D, plane strain): E = 1e4, nu = 0.3, rho0 = 1,
    A = 0.05, c = sqrt(E / rho0) = 100 (period 2 / c = 0.02 s), driven by the ``body_force`` field
    ``mms_axis_aligned`` (:mod:`mpmlab.boundaries.body_force`) for ``law`` (``fixed_corotated`` or
    ``hencky`` = ``hencky_von_mises`` with a yield stress it never reaches).

    Phases 0: U = 0 and F = I at t = 0, initial velocity A pi c sin(pi X_i).

    ``boundary="slip"`` (the note's problem): the exact U_i vanishes on the faces X_i = 0, 1 and the
    tangential displacement there is free with zero shear stress (F is diagonal), so the faces are slip
    walls (odd mirror symmetry of U_i). Walls ``thickness`` cells thick put their innermost node on the
    face (module docstring). With quadratic B-splines this boundary is only first-order-ish: the
    normal stress at the face is not zero, and the node one cell inside the wall, whose stencil reaches
    past the face, gets 1/8 of the face traction as an unbalanced force (a mirror image of the body
    would balance it); the ghost node behind the face is held at v_n = 0 instead of the mirror value.
    ``boundary="free"`` (needs nu = 0): U_i = A sin(pi (X_i + 1/2)) sin(pi c t), i.e. ``shift`` = 1/2,
    so F_ii = 1 on every face and, with lambda = 0, the faces are traction free: a free-floating cube
    with no wall, which measures the interior discretisation error. ``particles_per_axis`` k: k^dim regular
    particles per cell; dt = t_end / ceil(t_end / (cfl dx / c_p)) so that t_end is reached exactly.
    """
    from ..boundaries.body_force import BodyForce, MMSAxisAligned

    if law not in MMS_LAW_NAMES:
        raise ValueError(f"law {law!r}: use one of {sorted(MMS_LAW_NAMES)}")
    dx = 1.0 / cells
    t = thickness
    if boundary not in ("slip", "free"):
        raise ValueError(f"boundary {boundary!r}: use 'slip' or 'free'")
    if boundary == "free" and nu != 0.0:
        raise ValueError("boundary='free' needs nu = 0 (traction-free faces need lambda = 0)")
    values = {"A": amplitude, "c": c, "E": E, "nu": nu, "density": density, "law": law,
              "shift": 0.5 if boundary == "free" else 0.0}
    params = {"E": E, "nu": nu}
    if law == "hencky":
        params["yield_stress"] = 1.0e30
    body = Body(shape={"kind": "box", "lo": [0.0] * dim, "hi": [1.0] * dim}, material=MMS_LAW_NAMES[law],
                params=params, density=density, particles_per_cell=particles_per_axis**dim, name="cube")
    faces = {f"{a}{s}": "slip" for a in "xyz"[:dim] for s in "-+"}
    bf = BodyForce(field="mms_axis_aligned", values=values)
    p = bf.packed(dim)
    mu, lam = MMSAxisAligned.lame(E, nu)
    c_p = math.sqrt((lam + 2.0 * mu) / density) + amplitude * math.pi * p[1]
    steps = int(math.ceil(t_end / (cfl * dx / c_p)))
    if boundary == "slip":
        lo, hi, bcs = [-(t - 1) * dx] * dim, [1.0 + (t - 1) * dx] * dim, [_walls(dim, faces, t), bf]
    else:   # room for A pi / 2 ... A motion of the faces (|U| <= A) plus the stencil
        pad = int(math.ceil(amplitude / dx)) + 2
        lo, hi, bcs = [-pad * dx] * dim, [1.0 + pad * dx] * dim, [bf]
    return ProfiledScene(dim=dim, dx=dx, domain=(lo, hi), bodies=[body], gravity=None,
                         boundaries=bcs, dt=t_end / steps, cfl=cfl, cfl_limit=0.6,
                         name=f"mms_axis_aligned_{dim}d_{law}_{boundary}_{cells}",
                         velocity_profile=lambda x: MMSAxisAligned.velocity(x, 0.0, p, dim))


def mms_exact(scene: Scene, X: np.ndarray, t: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact displacement U [N, D] and diagonal of F [N, D] of the scene's MMS at reference X, time t."""
    from ..boundaries.body_force import BodyForce, MMSAxisAligned

    bf = next(b for b in scene.boundaries if isinstance(b, BodyForce))
    return MMSAxisAligned.exact(np, np.asarray(X, float), float(t), bf.packed(scene.dim), scene.dim)


def mms_errors(scene: Scene, X0: np.ndarray, x: np.ndarray, t: float, F: np.ndarray | None = None) -> dict[str, float]:
    """L2 (particle RMS; equal particle volumes) errors at time t, normalised by the amplitude A:
    ``position_error`` = |x - X - U(X, t)|_2 / A, and with F the deformation-gradient error
    ``F_error`` = |F - F_exact|_2 / (A pi) (F_exact diagonal, the strain amplitude is A pi)."""
    from ..boundaries.body_force import BodyForce

    bf = next(b for b in scene.boundaries if isinstance(b, BodyForce))
    A = float(bf.packed(scene.dim)[0])
    U, Fd = mms_exact(scene, X0, t)
    out = {"position_error": float(np.sqrt(np.mean(np.sum((x - X0 - U) ** 2, axis=1))) / A)}
    if F is not None:
        Fe = np.zeros_like(F)
        for d in range(scene.dim):
            Fe[:, d, d] = Fd[:, d]
        out["F_error"] = float(np.sqrt(np.mean(np.sum((F - Fe) ** 2, axis=(1, 2)))) / (A * math.pi))
    return out


def run_mms(backend: str = "jax", transfer: Any = "apic", precision: str = "fp64", t_end: float = 0.015,
            **scene_kw) -> dict[str, Any]:
    """Roll the manufactured solution out to ``t_end`` (one frame at the end) and score it (:func:`mms_errors`)."""
    scene = mms_axis_aligned(t_end=t_end, **scene_kw)
    dt = scene.resolve_dt()
    steps = int(round(t_end / dt))
    stepper, traj, timing = _rollout(scene, backend, transfer, precision, steps, steps, ("F",))
    err = mms_errors(scene, traj.x[0], traj.x[-1], float(traj.time[-1]), np.asarray(traj.fields["F"][-1]))
    return {"scene": scene, "traj": traj, "stepper": stepper, "every": steps, "dt": stepper.dt, "steps": steps,
            "particles": traj.particle_count, **err, **timing}
