"""Size pre-flight: estimate particles, memory and output sizes of a run before anything is allocated.

A run that cannot fit is refused with a ``ConfigError`` (the CLI prints it on one line and exits with
code 2) that names the key to change and the value that would fit; a run that fits but is large gets
one ``logging.getLogger("mpmlab").warning`` line. Every function here works from the scene
description alone (shapes, ``dx``, ``particles_per_cell``, the grid) and takes milliseconds:
nothing proportional to the particle or grid count is allocated, at most per-axis or per-row index
arrays of a body's lattice (``scene.dx = 1e-5`` on ``nclaw_jelly``, 1.25e14 particles, is refused in
~15 ms with a ~1 MiB allocation peak).

Where to call it (the CLI): :func:`check_memory` before ``scene.particles()`` (particle sampling is
the first big allocation: it builds the bounding-box lattice of every body), and
:func:`check_outputs_fit` before the first output is written; :func:`memory_preflight` and
:func:`output_preflight` make those two calls from a composed config.

Particles (:func:`estimate_particles`)
    Regular and jittered sampling put ``k^D`` points per cell (``particles_per_cell = k^D``) on the
    half-integer lattice ``(i + 1/2) h``, ``h = dx / k``, over the body's bounding box
    (``mpmlab.core.geometry.sample``), and keep those inside the shape. The estimate counts those
    lattice points exactly, without building the lattice: per axis for a box, per lattice row for a
    disc/ball (analytic chord length) and a cylinder (disc rows x axial count); for lattices of more
    than ~250k rows, and for meshes and plugin shapes, it is ``volume / h^D`` (the lattice-count
    error is then far below 1 %). Jittered sampling draws one point in each sub-cell of the
    lattice; its expected count is exactly ``volume / h^D`` (each point is uniform in its sub-cell),
    which is what the estimate uses. ``random`` sampling keeps ``count``.
    A scene whose particles were already sampled reports the real count.

Memory (:func:`estimate_memory`), bytes, order of magnitude (the model's assumptions)
    * ``sampling``: the peak while sampling: per body the bounding-box lattice of ``L`` points as
      ``D`` meshgrid arrays + their ``np.stack`` (``2 L D`` float64), then ``shape.contains``
      temporaries (another ``L D`` float64; jittered: + 2 ``L D``), plus the particles of the bodies
      already sampled and the concatenation into the ``ParticleSet`` (2x its size);
    * ``particles``: the scene's ``ParticleSet`` (float64 x, v, mass, volume, params; int64 ids) and
      the backend's per-particle arrays: JAX keeps the state (x, v, C for affine transfers, the law
      state) in the input, the output and the start-of-chunk copy of the rollout (3 copies) plus
      parameters (mass, volume, law parameters); Warp keeps 3 state buffers (x, v, C, tau, law
      state: the input state and the two ``_advance`` ping-pong buffers) and the static data twice
      (scene order and cell-sorted order);
    * ``grid``: JAX: the node coordinates (kept) and their int64/float64 construction temporaries,
      plus the per-step grid buffers (P2G accumulator of K = D + 1 (+ D for FLIP) lanes, old/new
      velocity, the gathered field); Warp: mass + momentum per node in one private copy per CPU
      thread (``threads``: as the Warp stepper picks them), the force copies for FLIP, the grid
      velocity (+ old velocity for FLIP);
    * ``scratch``: JAX's per-step per-particle temporaries (the ``[N, 3^D, K]`` P2G block, the
      ``[N, 3^D, Kg]`` gathered G2P block and their separable contractions, weights, the stress);
      Warp has none (fused kernels);
    * ``frames``: a rollout with ``keep_frames`` (the default of ``Stepper.rollout``; the simulate
      task keeps them only when it writes a recording without a trajectory) holds every kept frame
      in memory (x, v and the stored fields, in the run's precision) and stacks them into the
      ``Trajectory`` at the end: ``frames`` is both (2 x the kept frames ``F``);
    * ``runtime``: a fixed allowance for the backend's compilation (XLA, Warp module loads) and
      allocator slack (see below);
    * ``total``: ``max(sampling, particles + grid + max(scratch + F, 2 F)) + runtime`` (the scratch
      is gone when the frames are stacked).
    The grid and particle terms scale as ``dx^-D``, which :func:`check_memory` uses to say which
    ``dx`` would fit.

    Measured: the estimate against the peak resident memory of a real run in a fresh
    process (``mpmlab.simulate``, 2 steps, frames kept; peak RSS minus the RSS after importing the
    backend, which is already spent when :func:`available_memory` is read), 2-core CPU, Warp with
    its default 2 threads; ``nclaw_jelly`` with 8 particles per cell (3D), ``dam_break_2d`` with 4
    (2D), and a 0.1 m cube with 1 per cell in an 8.1M-node grid (grid-bound)::

        backend transfer prec dim  particles      nodes  est. w/o runtime  estimate  measured  (MiB)
        jax     mls      fp32 3D      125000     132651       170             298       253
        jax     mls      fp32 3D      512000     531441       694             822       668
        jax     mls      fp32 3D     1000000    1030301      1354            1482      1148
        jax     flip     fp32 3D     1000000    1030301      1778            1906      1610
        jax     mls      fp64 3D      512000     531441      1341            1469      1075
        jax     mls      fp32 2D     1600000     972729      1145            1273      1008
        jax     mls      fp32 3D        8000    8120601       970            1098       965
        jax     flip     fp32 3D        8000    8120601      1252            1380      1049
        warp    mls      fp32 3D      125000     132651        83             211       101
        warp    mls      fp32 3D     1000000    1030301       665             793       714
        warp    flip     fp32 3D     1000000    1030301       597             725       619
        warp    mls      fp64 3D      512000     531441       619             747       654
        warp    mls      fp32 3D        8000    8120601       222             350       234

    The estimate with its runtime allowance is 1.1-1.4x the measured peak for runs above ~0.5 GiB
    (it errs high, so a refusal is safe), and at most 0.6-1.25x without it. Not modelled: a Warp
    kernel cache that is cold (Warp compiles with its LLVM in-process: more runtime memory on the
    first run), the differentiable entry points (``observe``: tapes / checkpointed segments, issue
    #4), and GPU memory (Warp off the CPU: its arrays are left out of the host estimate).

Outputs (:func:`estimate_outputs`), uncompressed upper bounds
    * ``trajectory.h5`` (``mpmlab.io.h5`` layout): per frame x and v ``[N, D]`` plus each stored
      field ``[N_f, ...]`` (F, C, sigma: D x D; J, eps_p: 1) in the run's precision (both backends'
      ``to_numpy`` return it), time and step (16 bytes); once: mass, volume, params
      (float64), material and body ids (int32), field particle indices (int64), plus a fixed
      allowance for HDF5 metadata and the config text. The default ``lzf`` compression usually
      makes the file smaller, never much larger.
    * ``recording.rrd`` (``mpmlab.io.rerun``): per logged frame (every ``record_every``-th and the
      last) the positions as float32 x D, plus a packed RGBA colour (4 bytes) per particle when
      coloured by a scalar; once: radii (float32) and static colours; per frame a small allowance
      for the metrics scalars and message overhead.
"""
from __future__ import annotations

import logging
import math
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

from .errors import ConfigError

log = logging.getLogger("mpmlab")

KiB, MiB, GiB, TiB = 1024, 1024**2, 1024**3, 1024**4

#: warn when a run's memory estimate exceeds this fraction of the available memory
MEMORY_WARN_FRACTION = 0.5
#: warn when the outputs exceed this many bytes, or this fraction of the free disk space
OUTPUT_WARN_BYTES = 10 * GiB
OUTPUT_WARN_FRACTION = 0.5

#: lattice rows counted exactly (per row, analytically) before falling back to volume / h^D
_EXACT_ROWS = 250_000
#: per-axis lattices counted with the sampler's own float expressions up to this length
_EXACT_AXIS = 1_000_000


#: fixed allowances for the backend's compilation and allocator slack: the peak RSS above the
#: post-import RSS of a 1000-particle run is ~90 MiB (JAX) and ~15 MiB (Warp, kernel cache warm)
RUNTIME_BYTES = {"jax": 128 * MiB, "warp": 128 * MiB}


# ------------------------------------------------------------------------------------------------
# formatting
# ------------------------------------------------------------------------------------------------
def human_bytes(n: float) -> str:
    """``n`` bytes as a short binary-prefixed size: ``512 B``, ``96 KiB``, ``21.3 GiB``, ``910 TiB``."""
    n = float(n)
    units = ("B", "KiB", "MiB", "GiB", "TiB", "PiB", "EiB")
    i = 0
    while abs(n) >= 1000 and i < len(units) - 1:   # 1000..1023 KiB reads better as 0.98 MiB
        n /= 1024.0
        i += 1
    if i == 0:
        return f"{int(n)} B"
    return f"{n:.3g} {units[i]}" if abs(n) >= 1 else f"{n:.2f} {units[i]}"


def _fmt_count(n: float) -> str:
    """A particle count: ``1000`` as is, ``1.25e+14`` for large ones."""
    return f"{int(n)}" if n < 1e7 else f"{n:.3g}"


def _fmt_grid(cells: Sequence[int]) -> str:
    cells = [int(c) for c in cells]
    if len(set(cells)) == 1:
        return f"{cells[0]}^{len(cells)}-cell"
    return "x".join(map(str, cells)) + "-cell"


def _ceil_sig(x: float, sig: int = 2) -> float:
    """``x`` rounded up to ``sig`` significant digits (a dx that is at least the one that fits)."""
    if x <= 0 or not math.isfinite(x):
        return x
    e = math.floor(math.log10(x)) - sig + 1
    q = 10.0**e
    return math.ceil(x / q - 1e-9) * q


def _fmt_value(x: float) -> str:
    return f"{x:.2g}" if x < 1e-3 or x >= 1e4 else f"{x:.4g}"


# ------------------------------------------------------------------------------------------------
# particles (without sampling)
# ------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class BodyEstimate:
    """One body's estimate: ``particles`` kept, ``lattice`` points of its bounding box (what the
    sampler allocates), the sampler's ``peak`` bytes for it, and whether the count is ``exact``
    (counted on the sampler's lattice) or from ``volume / h^D``."""

    name: str
    particles: int
    lattice: int
    peak: int
    exact: bool


def _axis_range(lo: float, hi: float, h: float) -> tuple[int, int]:
    """The sampler's index range [i0, i1) of the bounding box [lo, hi] on the lattice of spacing h."""
    return math.floor(lo / h), math.ceil(hi / h)


def _count_in(a: float, b: float, i0: int, i1: int, h: float, exact_expr: bool = True) -> int:
    """Points (i + 1/2) h, i in [i0, i1), with a <= point <= b."""
    n = i1 - i0
    if n <= 0 or b < a:
        return 0
    if exact_expr and n <= _EXACT_AXIS:
        import numpy as np

        p = (np.arange(i0, i1) + 0.5) * h          # the sampler's own expression (same round-off)
        return int(np.count_nonzero((p >= a) & (p <= b)))
    lo = max(i0, math.ceil(a / h - 0.5))
    hi = min(i1 - 1, math.floor(b / h - 0.5))
    return max(0, hi - lo + 1)


def _row_counts(c: "Any", s2: "Any", i0: int, i1: int, h: float) -> int:
    """Sum over rows of the number of points (i + 1/2) h, i in [i0, i1), with (p - c)^2 <= s2 (arrays
    c, s2 of the rows; s2 < 0: empty row)."""
    import numpy as np

    ok = s2 >= 0
    s = np.sqrt(np.where(ok, s2, 0.0))
    lo = np.maximum(i0, np.ceil((c - s) / h - 0.5))
    hi = np.minimum(i1 - 1, np.floor((c + s) / h - 0.5))
    return int(np.sum(np.where(ok, np.maximum(hi - lo + 1, 0), 0)))


def _centres(i0: int, i1: int, h: float):
    import numpy as np

    return (np.arange(i0, i1) + 0.5) * h


def _lattice_count(shape, dim: int, lo, hi, h: float) -> tuple[int, bool]:
    """(points of the sampler's lattice inside ``shape``, exact?) without building the lattice."""
    from .geometry import Box, Cylinder, Sphere

    rng = [_axis_range(float(a), float(b), h) for a, b in zip(lo, hi)]
    ns = [b - a for a, b in rng]
    if isinstance(shape, Box):
        n = 1
        for (i0, i1), a, b in zip(rng, lo, hi):
            n *= _count_in(float(a), float(b), i0, i1, h)
        return n, True
    if isinstance(shape, Sphere) and math.prod(ns[:-1]) <= _EXACT_ROWS:
        import numpy as np

        c = [float(v) for v in shape.center]
        r2 = float(shape.radius) ** 2
        if dim == 2:
            d2 = (_centres(*rng[0], h) - c[0]) ** 2
        else:
            d2 = ((_centres(*rng[0], h) - c[0]) ** 2)[:, None] + ((_centres(*rng[1], h) - c[1]) ** 2)[None, :]
            d2 = d2.reshape(-1)
        return _row_counts(np.float64(c[-1]), r2 - d2, *rng[-1], h), True
    if isinstance(shape, Cylinder) and dim == 3:
        a0, a1 = [a for a in range(3) if a != shape.axis]
        if ns[a0] <= _EXACT_ROWS:
            import numpy as np

            b = [float(v) for v in shape.base]
            axial = _count_in(b[shape.axis], b[shape.axis] + float(shape.height), *rng[shape.axis], h)
            d2 = (_centres(*rng[a0], h) - b[a0]) ** 2
            disc = _row_counts(np.float64(b[a1]), float(shape.radius) ** 2 - d2, *rng[a1], h)
            return axial * disc, True
    try:
        vol = float(shape.volume(dim))
    except Exception:  # a plugin shape without a volume: the bounding-box lattice is an upper bound
        return math.prod(ns), False
    return min(math.prod(ns), int(round(vol / h**dim))), False


def estimate_bodies(scene) -> list[BodyEstimate]:
    """Per body: particles, bounding-box lattice points and the sampler's peak bytes (no sampling)."""
    dim = scene.dim
    out = []
    for b, body in enumerate(scene.bodies):
        name = body.name or str(b)
        lo, hi = body.shape.bounds(dim)
        lo, hi = [float(v) for v in lo], [float(v) for v in hi]
        if body.sampling == "random":
            n = int(body.count or 0)
            # candidates 2n x D per draw: the draw, the scaled copy, contains temporaries, concatenation
            out.append(BodyEstimate(name, n, 2 * n, 4 * 2 * n * dim * 8, True))
            continue
        if body.sampling == "lattice":      # linspace per axis: exactly prod(lattice) points
            lat = body.lattice if body.lattice is not None and len(body.lattice) == dim else None
            n = math.prod(int(a) for a in lat) if lat is not None else 0
            out.append(BodyEstimate(name, n, n, 3 * n * dim * 8, True))
            continue
        k = round(int(body.particles_per_cell) ** (1.0 / dim))
        if k < 1 or k**dim != int(body.particles_per_cell):
            out.append(BodyEstimate(name, 0, 0, 0, True))   # sample() refuses it with its own message
            continue
        h = float(scene.dx) / k
        L = math.prod(b_ - a_ for a_, b_ in (_axis_range(a, c, h) for a, c in zip(lo, hi)))
        n, exact = _lattice_count(body.shape, dim, lo, hi, h)
        if body.sampling == "jittered":
            # each point is uniform in its sub-cell and the sub-cells tile a superset of the shape:
            # the expected count is exactly volume / h^D
            try:
                n, exact = min(L, int(round(float(body.shape.volume(dim)) / h**dim))), False
            except Exception:
                pass
        # meshgrid (D arrays) + np.stack: 2 L D float64; contains(): ~1 more (jittered: the jitter and
        # the shifted copy, 2 more); the kept points
        copies = 3 if body.sampling != "jittered" else 4
        out.append(BodyEstimate(name, int(n), int(L), int(copies * L * dim * 8 + n * dim * 8), exact))
    return out


def _sampled(scene) -> Any:
    """The scene's ParticleSet if it was already sampled (``Scene._particles`` is a cached_property)."""
    return vars(scene).get("_particles")


def estimate_particles(scene) -> int:
    """Number of particles ``scene.particles()`` will hold, without sampling (exact for boxes, discs,
    balls and cylinders on the regular lattice; ``volume / h^D`` for meshes and very large lattices).
    A scene already sampled returns its real count."""
    P = _sampled(scene)
    if P is not None:
        return int(P.count)
    return int(sum(e.particles for e in estimate_bodies(scene)))


def estimate_sampling_peak(scene) -> int:
    """Peak bytes of ``scene.particles()``: the largest bounding-box lattice being filtered while the
    bodies before it are kept, or the final concatenation (2x the ParticleSet), whichever is larger."""
    if _sampled(scene) is not None:
        return 0
    est = estimate_bodies(scene)
    per_particle = _scene_particle_bytes(scene, 1)
    done, peak = 0, 0
    for e in est:
        peak = max(peak, done * per_particle + e.peak)
        done += e.particles
    return int(max(peak, 2 * done * per_particle))


# ------------------------------------------------------------------------------------------------
# memory
# ------------------------------------------------------------------------------------------------
def _laws(scene) -> list[tuple[Any, int]]:
    """(law instance, particles) per material group, in the order of first appearance, estimated: the
    groups of ``scene.particles()`` (bodies of equal law instances, ``Scene._law``) without sampling."""
    P = _sampled(scene)
    if P is not None:
        return [(g.law, int(g.count)) for g in P.groups]
    counts: dict[Any, int] = {}
    for law, e in zip(scene.body_laws(), estimate_bodies(scene)):
        counts[law] = counts.get(law, 0) + e.particles
    return list(counts.items())


def _field_size(name: str, dim: int) -> int:
    """Scalars per particle of a stored field: C is D x D; a law state field as its law declares it
    (an undeclared name counts as D x D, the largest built-in)."""
    from .interfaces import registered_state_fields

    f = registered_state_fields().get(name) if name != "C" else None
    return f.size(dim) if f is not None else dim * dim


def _params_per_particle(scene) -> int:
    """P: the largest parameter count of the scene's law instances (``Scene._law``: a ``phase_change``
    pair declares both laws' parameters)."""
    return max(len(law.param_names()) for law in scene.body_laws())


def _scene_particle_bytes(scene, n: int) -> int:
    """The scene's ParticleSet for ``n`` particles: float64 x, v [N, D], mass, volume; int64 body and
    material ids; float64 params [N, P] (P: the largest parameter count of the scene's laws)."""
    return n * (8 * (2 * scene.dim + 2 + _params_per_particle(scene)) + 16)


def _transfer(transfer):
    if transfer is None:
        transfer = "mls"     # the config default
    if isinstance(transfer, str):
        from ..transfers import make_transfer

        transfer = make_transfer(transfer)
    return transfer


def carried_fields(scene, transfer=None) -> set[str]:
    """The per-particle fields this scene's laws and transfer carry (C for affine transfers)."""
    tr = _transfer(transfer)
    out = {"C"} if tr.needs_affine else set()
    for law, _ in _laws(scene):
        out |= set(law.state_fields)
    return out


def field_particles(scene, fields: Iterable[str], transfer=None, derived: Iterable[str] = ()) -> dict[str, int]:
    """Particles each stored field covers (C: all; a law field: the groups whose law carries it, and
    for a field in ``derived`` also those it is synthesised for: :mod:`mpmlab.io.derived`)."""
    from ..io.derived import RULES

    groups = _laws(scene)
    N = sum(n for _, n in groups)
    derived = set(derived)
    out = {}
    for f in fields:
        if f == "C":
            out[f] = N if _transfer(transfer).needs_affine else 0
        else:
            src = RULES[f].source if f in derived and f in RULES else None
            out[f] = sum(n for law, n in groups if f in law.state_fields or (src and src in law.state_fields))
    return out


def _warp_threads(N: int, device: str | None, threads: int | None) -> int:
    """The Warp stepper's CPU thread count (= private P2G grid copies) for N particles."""
    if device is not None and not str(device).startswith("cpu"):
        return 1
    if threads is None:
        threads = int(os.environ.get("MPMLAB_WARP_THREADS", 0) or 0)
    if not threads:
        try:
            cores = len(os.sched_getaffinity(0))
        except AttributeError:  # pragma: no cover - not Linux
            cores = os.cpu_count() or 1
        threads = max(1, min(cores, 8, N // 4096))
    return max(1, int(threads))


def estimate_memory(scene, backend: str = "jax", precision: str = "fp32", transfer=None, *, frames: int = 0,
                    fields: Sequence[str] = (), device: str | None = None, threads: int | None = None,
                    shape: str = "quadratic") -> dict[str, int]:
    """Bytes of host memory a run of ``scene`` needs, by part (see the module docstring for the model).

    Args:
        scene: a ``Scene`` (its particles need not be sampled).
        backend: ``jax`` or ``warp`` (another name is estimated like ``jax``).
        precision: ``fp32`` or ``fp64``.
        transfer: a transfer name or object (None: ``mls``, the config default).
        frames: frames the rollout keeps in memory (``frame_counts``); 0: none counted.
        fields: per-particle fields kept per frame besides x, v (only those the scene carries count).
        device: Warp device; off the CPU the backend's arrays live on the device and are left out.
        threads: Warp CPU threads (None: as the stepper chooses them).
        shape: the transfer's shape function (``mpmlab.shapes``): its window of ``width``^D nodes sizes
            the JAX stencil blocks (the fitted constants are those of the 3-node quadratic B-spline); CPDI
            adds its domain R [D, D] per particle to the Warp state.

    Returns:
        ``{"sampling", "particles", "grid", "scratch", "frames", "runtime", "total"}`` in bytes.
    """
    D = int(scene.dim)
    s = 8 if precision == "fp64" else 4
    tr = _transfer(transfer)
    groups = _laws(scene)
    N = sum(n for _, n in groups)
    G = math.prod(int(g) for g in scene.grid_shape)
    split = bool(tr.split_force)
    affine = tr.needs_affine
    law_state = sum(n * sum(_field_size(f, D) for f in law.state_fields) for law, n in groups)
    law_params = sum(n * len(law.param_names()) for law, n in groups)
    on_host = device is None or str(device).startswith("cpu")

    particles = _scene_particle_bytes(scene, N)
    if backend == "warp":
        from ..shapes import make_shape

        corners = make_shape(shape).kind == "corners"                              # CPDI: the domain R [D, D]
        state = N * (2 * D + D * D + (D * D if affine else 0) + (D * D if corners else 0)) + law_state  # x, v, tau, C, R, law
        static = 2 * (2 * N + law_params)                                          # + cell-sorted copies
        backend_particles = s * (3 * state + static) + N * 8 * (D + 1)             # + sort keys/cells
        copies = _warp_threads(N, device, threads)
        grid = s * G * (copies * (D + 1) + (copies * D if split else 0) + D + (D if split else 0))
        scratch = 0
        if not on_host:
            backend_particles, grid = 0, 0
        runtime = RUNTIME_BYTES["warp"]
    else:
        state = N * (2 * D + (D * D if affine else 0)) + law_state
        backend_particles = s * (3 * state + 2 * N + law_params)
        K = D + 1 + (D if split else 0)                                            # P2G lanes
        Kg = 2 * D if split else D                                                 # G2P lanes
        from ..shapes import make_shape

        S = int(make_shape(shape).width) ** D                                      # window nodes per particle
        # node coordinates (kept) + their construction (int64 meshgrid and stack, float64 products)
        grid = s * G * D + 32 * G * D
        # per step: accumulator (in, out), v_old, v_new, the gathered field, masks and XLA's copies
        # (fitted to the measured peak of an 8.1M-node grid with 8000 particles, MLS and FLIP)
        grid = max(grid, s * G * (2 * K + 4 * D + Kg + 8))
        # the P2G block [N, S, K] and the gathered G2P block [N, S, Kg] (XLA fuses part of them away)
        # plus ~60 scalars per particle of stencil weights, stress, affine columns and law update
        # (fitted to the measured peaks of 2D and 3D MLS and FLIP steps; the module docstring's table)
        scratch = s * N * ((4 * S * (K + Kg)) // 5 + 60)
        runtime = RUNTIME_BYTES["jax"]
    particles += backend_particles

    fp = field_particles(scene, [f for f in fields if f in carried_fields(scene, tr)], tr)
    per_frame = s * (2 * N * D + sum(n * _field_size(f, D) for f, n in fp.items())) + 16
    kept = int(frames) * per_frame
    sampling = estimate_sampling_peak(scene)
    # while stepping: the kept frames beside the step's scratch; at the end: the kept frames and their
    # stacked copy (the Trajectory), the scratch gone
    run = particles + grid + max(scratch + kept, 2 * kept)
    return {"sampling": int(sampling), "particles": int(particles), "grid": int(grid), "scratch": int(scratch),
            "frames": int(2 * kept), "runtime": int(runtime), "total": int(max(sampling, run) + runtime)}


def available_memory() -> int:
    """Bytes of memory this process may still use: ``psutil.virtual_memory().available``, lowered to
    the cgroup (container) limit minus its usage where one is set."""
    try:
        import psutil

        avail = int(psutil.virtual_memory().available)
    except Exception:  # pragma: no cover - psutil missing
        avail = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    for limit_f, usage_f in (("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory.current"),
                             ("/sys/fs/cgroup/memory/memory.limit_in_bytes",
                              "/sys/fs/cgroup/memory/memory.usage_in_bytes")):
        try:
            limit = Path(limit_f).read_text().strip()
            usage = int(Path(usage_f).read_text().strip())
        except (OSError, ValueError):
            continue
        if limit.isdigit() and int(limit) < 1 << 60:
            avail = min(avail, max(0, int(limit) - usage))
        break
    return avail


def _with_dx(scene, dx: float):
    """A copy of ``scene`` with grid spacing ``dx`` (nothing sampled)."""
    import dataclasses

    return dataclasses.replace(scene, dx=float(dx), domain=(list(scene.domain[0]), list(scene.domain[1])))


def fitting_dx(scene, need: float, budget: float, estimate) -> float:
    """The smallest ``dx`` (2 significant digits, rounded up) whose ``estimate(scene_at_dx)`` total
    fits ``budget``: memory scales as dx^-D, refined on the estimate itself."""
    dx = float(scene.dx) * (need / max(budget, 1.0)) ** (1.0 / scene.dim) * 1.02
    for _ in range(20):
        cand = _ceil_sig(dx)
        try:
            if estimate(_with_dx(scene, cand))["total"] <= budget:
                return cand
        except ConfigError:
            pass
        dx = cand * 1.05
    return _ceil_sig(dx)


def _fitting_frame_every_memory(est: Mapping[str, int], frames: int, steps: int, every: int, budget: float):
    """The smallest frame_every >= ``every`` whose kept frames fit ``budget`` beside the rest of the
    estimate (None: not even two frames fit)."""
    per = est["frames"] / max(frames, 1)
    room = budget - (est["total"] - est["frames"])
    if room < 2 * per:
        return None
    lo, hi = max(1, every), max(1, steps)
    if frame_counts(steps, hi)[0] * per > room:
        return None
    while lo < hi:
        mid = (lo + hi) // 2
        if frame_counts(steps, mid)[0] * per <= room:
            hi = mid
        else:
            lo = mid + 1
    return lo


def check_memory(scene, backend: str = "jax", precision: str = "fp32", transfer=None, available: int | None = None,
                 *, frames: int = 0, fields: Sequence[str] = (), steps: int | None = None,
                 frame_every: int | None = None, device: str | None = None, threads: int | None = None,
                 warn_fraction: float = MEMORY_WARN_FRACTION, shape: str = "quadratic") -> dict[str, int]:
    """Refuse a run whose memory estimate exceeds the available memory; warn above ``warn_fraction``.

    Args:
        available: bytes available (default :func:`available_memory`); injectable for tests.
        frames, fields, device, threads, shape: as for :func:`estimate_memory`.
        steps, frame_every: the run's, to suggest a ``frame_every`` when the kept frames dominate.

    Returns:
        The estimate (:func:`estimate_memory`).

    Raises:
        ConfigError: e.g. ``scene 'nclaw_jelly': dx = 1e-05 m needs about 248 PiB of memory (a
        100000^3-cell grid, ~1.25e+14 particles) but 21.3 GiB are available; set scene.dx >= 0.003
        (memory scales as dx^-3) or choose a coarser scene.resolution.`` The suggested dx brings the
        estimate below ``warn_fraction`` of the available memory. When the frames a rollout keeps
        dominate: ``scene 'nclaw_jelly': keeping 1000001 frames of ~1000 particles in memory needs
        about 179 GiB (the frames and their stacked copy: 179 GiB; dx = 0.05 m, a 20^3-cell grid)
        but 21.3 GiB are available; raise frame_every (>= 17 fits) or reduce steps.``
    """
    est = estimate_memory(scene, backend, precision, transfer, frames=frames, fields=fields, device=device,
                          threads=threads, shape=shape)
    avail = available_memory() if available is None else int(available)
    need = est["total"]
    N = estimate_particles(scene)
    frames_dominate = est["frames"] > 0.5 * (need - est["runtime"]) and frames > 1
    if frames_dominate:
        what = (f"scene '{scene.name}': keeping {frames} frames of ~{_fmt_count(N)} particles in memory needs "
                f"about {human_bytes(need)} (the frames and their stacked copy: {human_bytes(est['frames'])}; "
                f"dx = {scene.dx:g} m, a {_fmt_grid(scene.cells)} grid)")
    else:
        what = (f"scene '{scene.name}': dx = {scene.dx:g} m needs about {human_bytes(need)} of memory "
                f"(a {_fmt_grid(scene.cells)} grid, ~{_fmt_count(N)} particles)")
    if need > avail:
        if frames_dominate and steps and frame_every:
            fe = _fitting_frame_every_memory(est, frames, int(steps), int(frame_every), avail * warn_fraction)
            if fe is not None:
                raise ConfigError(f"{what} but {human_bytes(avail)} are available; raise frame_every "
                                  f"(>= {fe} fits) or reduce steps.")
        budget = avail * warn_fraction
        dx_fit = fitting_dx(scene, need, budget,
                            lambda sc: estimate_memory(sc, backend, precision, transfer, frames=frames, shape=shape,
                                                       fields=fields, device=device, threads=threads))
        raise ConfigError(
            f"{what} but {human_bytes(avail)} are available; set scene.dx >= {_fmt_value(dx_fit)} "
            f"(memory scales as dx^-{scene.dim}) or choose a coarser scene.resolution."
        )
    if need > warn_fraction * avail:
        less = "a larger frame_every" if frames_dominate else "a larger scene.dx or a coarser scene.resolution"
        log.warning("%s, %.0f %% of the %s available; %s needs less.", what, 100.0 * need / max(avail, 1),
                    human_bytes(avail), less)
    return est


# ------------------------------------------------------------------------------------------------
# outputs
# ------------------------------------------------------------------------------------------------
TRAJECTORY_FILE = "trajectory.h5"
RECORDING_FILE = "recording.rrd"
#: fixed allowances: HDF5 superblock, groups, attributes (config text, metadata JSON); rerun
#: metadata document, blueprint and stream header
_H5_FIXED = 256 * KiB
_H5_PER_FRAME_DATASET = 64        # chunk index entries per frame and dataset
_RRD_FIXED = 160 * KiB           # blueprint, legends, colour bar, one entity per metric
_RRD_PER_FRAME = 1 * KiB          # per frame: metrics scalars, time stamps, message framing


def frame_counts(steps: int, frame_every: int, record_every: int = 1) -> tuple[int, int]:
    """(frames the rollout keeps, frames the recording logs) for ``steps`` and ``frame_every``:
    frame 0, every ``frame_every``-th step and the last one (``steps // frame_every + 1``, + 1 when
    ``steps % frame_every``; ``frame_every`` > ``steps`` > 0 keeps frames 0 and ``steps``, as the
    simulate task does); the recording logs every ``record_every``-th frame and the last."""
    steps, every, re = int(steps), max(1, int(frame_every)), max(1, int(record_every))
    if 0 < steps < every:
        every = steps
    T = steps // every + 1 + (1 if steps % every else 0)
    R = (T + re - 1) // re + (1 if (T - 1) % re else 0)
    return T, R


def estimate_outputs(particles: int, dim: int, precision: str, frames: int, fields: Sequence[str] = (),
                     recording_frames: int | None = None, *,
                     field_particles: Mapping[str, int] | None = None, params_per_particle: int = 4,
                     color_scalar: bool = False, trajectory: bool = True, recording: bool = True) -> dict[str, int]:
    """Uncompressed upper bounds of the run's output files, in bytes.

    Args:
        particles, dim: N and D.
        precision: ``fp32`` or ``fp64`` (the item size of x, v and the fields on both backends).
        frames: frames in the trajectory (:func:`frame_counts`).
        fields: stored per-particle fields besides x, v (F, C, sigma: D x D; J, eps_p: 1).
        recording_frames: frames the recording logs (default: all ``frames``).
        field_particles: particles each field covers (default: all).
        params_per_particle: columns of the static params array.
        color_scalar: the recording colours particles by a scalar (``speed``, ``J``, ...): 4 bytes per
            particle and logged frame.
        trajectory, recording: which files the run writes.

    Returns:
        ``{"trajectory.h5": bytes, "recording.rrd": bytes}`` (only the files written).
    """
    N, D, T = int(particles), int(dim), int(frames)
    item = 8 if precision == "fp64" else 4
    fp = {f: int((field_particles or {}).get(f, N)) for f in fields}
    out: dict[str, int] = {}
    if trajectory:
        per_frame = item * (2 * N * D + sum(n * _field_size(f, D) for f, n in fp.items())) + 16
        per_frame += _H5_PER_FRAME_DATASET * (4 + len(fp))
        static = N * (2 * 4 + 2 * 8 + 8 * int(params_per_particle)) + 8 * sum(fp.values())
        out[TRAJECTORY_FILE] = int(_H5_FIXED + static + T * per_frame)
    if recording:
        R = T if recording_frames is None else int(recording_frames)
        # positions f32 x D, a scalar colour u32, and the hover values (Particle:values, f32 each):
        # speed, J (from J or F), eps_p and the stress norm where stored, material and particle id
        n_values = 1 + ("J" in fp or "F" in fp) + ("eps_p" in fp) + ("sigma" in fp) + 2
        per_logged = N * (4 * D + (4 if color_scalar else 0) + 4 * n_values)
        static = N * (4 + 4)                                    # radii f32, static colours u32
        out[RECORDING_FILE] = int(_RRD_FIXED + static + R * per_logged + T * _RRD_PER_FRAME)
    return out


def free_disk(output_dir: str | os.PathLike) -> tuple[int, Path]:
    """(free bytes, the directory measured): the output directory or its nearest existing parent."""
    p = Path(output_dir).absolute()
    while not p.exists() and p != p.parent:
        p = p.parent
    return int(shutil.disk_usage(p).free), p


_DISABLE = {TRAJECTORY_FILE: "set output.trajectory=false", RECORDING_FILE: "set output.recording=false"}


def check_outputs_fit(output_dir: str | os.PathLike, sizes: Mapping[str, int], free: int | None = None, *,
                      frames: int | None = None, recording_frames: int | None = None, steps: int | None = None,
                      frame_every: int | None = None, record_every: int = 1,
                      warn_bytes: int = OUTPUT_WARN_BYTES, warn_fraction: float = OUTPUT_WARN_FRACTION) -> int:
    """Refuse outputs that do not fit the free disk space of ``output_dir``; warn when they are large.

    Args:
        output_dir: the run directory (it need not exist yet: its nearest existing parent is measured).
        sizes: ``{file name: bytes}`` (:func:`estimate_outputs`).
        free: free bytes (default: ``shutil.disk_usage``); injectable for tests.
        frames, recording_frames: frame counts behind ``sizes`` (for the message; computed from
            ``steps`` / ``frame_every`` / ``record_every`` when those are given).
        steps, frame_every, record_every: the run's, to suggest a ``frame_every`` that fits.
        warn_bytes, warn_fraction: warn above this total, or above this fraction of ``free``.

    Returns:
        The total bytes.

    Raises:
        ConfigError: e.g. ``trajectory.h5 would need about 89.8 GiB (1000001 frames x 94.1 KiB) but
        '/data/run' has 50 GiB free; raise frame_every (>= 4 fits) or set output.trajectory=false.``
        The suggested frame_every brings the outputs below ``warn_fraction`` of the free space.
    """
    sizes = {k: int(v) for k, v in sizes.items() if v}
    total = sum(sizes.values())
    if not sizes:
        return 0
    if free is None:
        free, where = free_disk(output_dir)
    else:
        where = Path(output_dir)
    if steps is not None and frame_every is not None:
        frames, recording_frames = frame_counts(steps, frame_every, record_every)
    counts = {TRAJECTORY_FILE: frames, RECORDING_FILE: recording_frames if recording_frames is not None else frames}

    def detail(name: str, size: int) -> str:
        n = counts.get(name)
        return f"{n} frames x {human_bytes(size / n)}" if n else human_bytes(size)

    order = sorted(sizes, key=sizes.get, reverse=True)
    names = " + ".join(order)
    if len(order) == 1:
        what = f"{names} would need about {human_bytes(total)} ({detail(order[0], total)})"
    else:
        what = (f"{names} would need about {human_bytes(total)} ("
                + "; ".join(f"{n}: {detail(n, sizes[n])}" for n in order) + ")")
    if total > free:
        fixes = []
        if steps is not None and frame_every is not None and int(steps) > 0:
            fe = _fitting_frame_every(sizes, int(steps), int(frame_every), int(record_every), free * warn_fraction)
            if fe is not None:
                fixes.append(f"raise frame_every (>= {fe} fits)")
        fixes += [_DISABLE[n] for n in order if n in _DISABLE][:1 if fixes else 2]
        if not fixes:
            fixes.append("free disk space")
        fix = " or ".join(fixes) + (" or choose another hydra.run.dir" if len(fixes) < 2 else "")
        raise ConfigError(f"{what} but '{where}' has {human_bytes(free)} free; {fix}.")
    if total > warn_bytes or total > warn_fraction * free:
        log.warning("%s, %.0f %% of the %s free in '%s'; raise frame_every or output.record_every for less.",
                    what, 100.0 * total / max(free, 1), human_bytes(free), where)
    return total


def _fitting_frame_every(sizes: Mapping[str, int], steps: int, every: int, record_every: int, budget: float):
    """The smallest frame_every >= ``every`` whose outputs (scaled per frame count) fit ``budget``."""
    T0, R0 = frame_counts(steps, every, record_every)

    def total(fe: int) -> float:
        T, R = frame_counts(steps, fe, record_every)
        return sum(v * ((R / R0) if k == RECORDING_FILE else (T / T0)) for k, v in sizes.items())

    if total(steps) > budget:       # even frames 0 and `steps` alone do not fit
        return None
    lo, hi = every, steps           # total() is non-increasing in fe (up to the +1 of a remainder)
    while lo < hi:
        mid = (lo + hi) // 2
        if total(mid) <= budget:
            hi = mid
        else:
            lo = mid + 1
    return lo


# ------------------------------------------------------------------------------------------------
# the CLI's two calls
# ------------------------------------------------------------------------------------------------
def memory_preflight(cfg, scene, *, frames: int = 0, fields: Sequence[str] = (), steps: int | None = None,
                     frame_every: int | None = None, available: int | None = None) -> dict[str, int]:
    """:func:`check_memory` with a composed config's backend, precision, transfer and Warp device
    (for ``build_scene``, before ``scene.particles()``). Returns the estimate."""
    from ..build import make_transfer_from_config

    backend = cfg.get("backend", None) or {}
    precision = cfg.get("precision", None) or {}
    transfer = make_transfer_from_config(cfg) if cfg.get("transfer", None) is not None else None
    return check_memory(scene, str(backend.get("name", "jax")), str(precision.get("name", "fp32")), transfer,
                        available, frames=frames, fields=fields, steps=steps, frame_every=frame_every,
                        device=backend.get("device", None),
                        shape=str((cfg.get("transfer", None) or {}).get("shape", None) or "quadratic"))


def output_preflight(cfg, scene, output_dir: str | os.PathLike, *, steps: int | None = None,
                     frame_every: int | None = None, fields: Sequence[str] | None = None,
                     keep_frames: bool | None = None, free: int | None = None,
                     available: int | None = None) -> dict[str, int]:
    """The simulate task's check before its first output: the sizes of the files ``cfg.output`` asks
    for (:func:`estimate_outputs`) against the free disk space (:func:`check_outputs_fit`), and, when
    the rollout keeps its frames in memory, those frames against the memory (:func:`check_memory`).

    Args:
        steps, frame_every: the run's (default ``cfg.steps`` / ``cfg.frame_every``).
        fields: the stored fields (default: ``cfg.output.fields`` that the scene carries).
        keep_frames: whether the rollout keeps the frames in memory (default: as the simulate task
            does it, only for a recording without a trajectory).
        free, available: injectable free disk bytes / available memory bytes.

    Returns:
        ``{file name: bytes}`` of the outputs.
    """
    from ..build import make_transfer_from_config

    tr = make_transfer_from_config(cfg)
    precision = str(cfg.precision.name)
    steps = int(cfg.steps if steps is None else steps)
    every = int(cfg.frame_every if frame_every is None else frame_every)
    out_cfg = cfg.output
    record_every = int(out_cfg.get("record_every", 1))
    carried = carried_fields(scene, tr)
    requested = list(out_cfg.get("fields", []) if fields is None else fields)
    if "all" in requested:                 # every carried field (output.fields default)
        requested = list(dict.fromkeys([f for f in requested if f != "all"] + sorted(carried)))
    from ..io.derived import RULES

    # a field asked for by name that some law can only have synthesised (F from J) is written too
    derived = [f for f in requested if f in RULES and RULES[f].source in carried]
    fields = [f for f in requested if f in carried or f in derived]
    T, R = frame_counts(steps, every, record_every)
    write_traj, write_rec = bool(out_cfg.get("trajectory", True)), bool(out_cfg.get("recording", True))
    if keep_frames is None:
        keep_frames = write_rec and not write_traj
    if keep_frames:
        memory_preflight(cfg, scene, frames=T, fields=fields, steps=steps, frame_every=every, available=available)
    P = _params_per_particle(scene)
    sizes = estimate_outputs(estimate_particles(scene), scene.dim, precision, T, fields, R,
                             field_particles=field_particles(scene, fields, tr, derived), params_per_particle=P,
                             color_scalar=str(out_cfg.get("color_by", "material")) not in ("material", "body"),
                             trajectory=write_traj, recording=write_rec)
    check_outputs_fit(output_dir, sizes, free, steps=steps, frame_every=every, record_every=record_every)
    return sizes


# ------------------------------------------------------------------------------------------------
# gradient memory: keep a rollout's step states or recompute them (issue 17)
# ------------------------------------------------------------------------------------------------
#: fraction of the available memory that ``segment="auto"`` lets a gradient spend on kept step states
GRADIENT_MEMORY_FRACTION = 0.25


def resolve_segment(segment, steps: int, bytes_per_step: float, *, default: int = 100,
                    budget: float | None = None) -> tuple[int, bool]:
    """The segment length of a checkpointed gradient and whether to keep every step state.

    ``segment``: an int >= 1 (recompute segments of that many steps from their saved starts:
    memory O(steps / segment + segment) states, time F + F + B), None (``default``), or ``"auto"``:
    keep every step's state (and the residuals the adjoint needs) from the forward pass when
    ``steps * bytes_per_step`` fits ``budget`` (default: ``GRADIENT_MEMORY_FRACTION`` of
    :func:`available_memory`), so small problems pay F + B instead of 2F + B (JAX-MPM Remark 5's
    trade-off, decided by size); otherwise ``default``.

    ``bytes_per_step``: the backend's estimate of what one kept step costs (its state and per-step
    residuals). Returns ``(segment, keep)``; ``keep`` is True only for ``"auto"`` when it fits, and
    then ``segment == steps``."""
    steps = max(int(steps), 1)
    if segment is None:
        return max(1, min(int(default), steps)), False
    if isinstance(segment, str):
        if segment.strip().lower() != "auto":
            raise ConfigError(f"segment = {segment!r}: give a number of steps >= 1, or 'auto' (keep every step "
                              f"state when they fit in memory, else recompute segments of {default} steps).")
        cap = float(budget) if budget is not None else GRADIENT_MEMORY_FRACTION * available_memory()
        if steps * float(bytes_per_step) <= cap:
            return steps, True
        return max(1, min(int(default), steps)), False
    try:
        k = int(segment)
    except (TypeError, ValueError):
        raise ConfigError(f"segment = {segment!r}: give a number of steps >= 1, or 'auto'.") from None
    if k < 1 or k != segment:
        raise ConfigError(f"segment = {segment!r} must be a whole number of steps >= 1 (or 'auto').")
    return k, False
