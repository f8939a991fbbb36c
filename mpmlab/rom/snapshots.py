"""The full-order snapshot studies of the deformation-map ROM (Chen et al. 2023, Sec. 5, Table 2;
notes/nclaw-rom.md 2.4, 2.7, 2.8), as data: each study's runs (a list of Hydra overrides each), their
parameters and the seeded train/test split, plus a runner and a reader.

    from mpmlab.rom.snapshots import study, run_study, load_snapshots
    s = study("torsion")                    # 36 runs, s.train (29) / s.test (7)
    s.runs[3].overrides                      # ('scene=rom_torsion', 'scene.vars.v=0.0', 'scene.vars.omega=1.2', ...)
    run_study(s, "data/torsion", runs=s.test, overrides=["scene.resolution=tiny"])   # or, with the CLI:
    #   mpmlab -m experiment=rom_snapshots_torsion
    snap = load_snapshots("data/torsion", s, split="test")
    snap.x.shape, snap.F.shape               # [runs, frames, N, 3], [runs, frames, N, 3, 3]

Studies (``STUDIES``):

======================  ========================  ==========================================  ===========
study                   scene                     runs (parameters)                           train/test
======================  ========================  ==========================================  ===========
``gravity``             ``cylinder_wall_gravity``  g = 30 values evenly in [1, 10] m/s^2 (5.1)  24/6 seeded
``torsion``             ``rom_torsion``            6 x 6 grid v in [0, 0.6] m/s x omega in      29/7 seeded
                                                   [0, 2] rad/s (5.2)
``torsion_fine``        ``rom_torsion`` (fine)     the torsion test runs, 2x finer (5.2.1)      0/7
``poke``                ``rom_poke``               theta = k pi/18, k = 0..35 (5.3)             12/24 (k % 3 == 0 trains)
``poke_slow``           ``rom_poke``               the same at 4.8 mm/s (the other reading)     12/24
``poke_continual``      ``rom_poke``               10 pokes, random theta, one every 3 s (5.3.2)  0/1
``poke_slow_continual`` ``rom_poke``               the same at 4.8 mm/s                         0/1
``tower``               ``rom_tower``              Latin hypercubes over (r, theta, phi) (5.4)   16/4
``beam_2d``             ``rom_beam_2d``            g = 2, 3, ..., 8 m/s^2 (mpmlab's 2D problem)   4/3 (even g trains)
======================  ========================  ==========================================  ===========

Choices the paper leaves open, made here:

- The random splits (gravity, torsion) are ``numpy.random.default_rng(seed).permutation``; the test runs
  are the first ``n_test`` of the permutation (seed 0 by default). The paper says "randomly".
- Tower ranges: r in [0.06, 0.08) m/s (the text's "[0.6, 0.8)" contradicts Fig. 15's r = 0.062 - 0.080,
  and 0.6 m/s would move the top of a 0.6 m tower by 2 m in 3.33 s), theta in [0, pi/2), phi in
  [-pi/3, -pi/6) (Fig. 15's phi = -0.97 ... -0.54 lie inside). Training: one Latin hypercube of 16
  (``scipy.stats.qmc.LatinHypercube(d=3, seed=seed)``), test: another of 4 (seed + 1): the paper's
  "Another 4 simulations are sampled using the same approach".
- Continual poking: the poke directions theta_i ~ U[0, 2 pi) (``default_rng(seed)``), phi as in the
  single pokes, poke i during [3 i, 3 i + 0.25) s, each released for the rest of its 3 s: 10 x 432
  snapshots = 30 s. The pokes are ten timed ``grid_velocity`` boundaries (``poke_0`` ... ``poke_9``)
  added to ``rom_poke`` with its single ``poke`` disabled.
- Every run stores x, v and F at the snapshots (``output.fields=[F]``), no recording, and runs the PIC
  transfer, as the reduced model does (``OUTPUT_OVERRIDES``); the FOM's dt comes from the CFL bound
  with substepping (:func:`substeps`; the scenes document their numbers).

Every problem the reader finds is a one-line ``ConfigError``.
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable, Sequence

import numpy as np

from ..core.errors import ConfigError

#: the CFL number the snapshot scenes' fixed dt stays below (mpmlab's ``dt: auto`` factor)
SNAPSHOT_CFL = 0.3
#: what every snapshot run stores and skips (x and v are always stored), and its transfer: the reduced
#: model steps with PIC (Alg. 5), so its full-order truth does too -- the ROM's error then measures the
#: reduction, not the transfer (on rom_beam_2d at dx 2.5 cm, MLS and PIC full-order runs differ by
#: E = 11-24 %, more than any ROM error of the paper)
OUTPUT_OVERRIDES = ("transfer=pic", "output.fields=[F]", "output.recording=false")


def substeps(interval: float, dx: float, wave_speed: float, max_speed: float, cfl: float = SNAPSHOT_CFL) -> int:
    """The number of FOM steps per snapshot: the smallest n with (interval / n) (c_p + |v|_max) / dx <= cfl."""
    return int(math.ceil(interval * (wave_speed + max_speed) / (cfl * dx) - 1e-9))


def p_wave_speed(E: float, nu: float, density: float) -> float:
    """c_p = sqrt((lambda + 2 mu) / rho) [m/s] (the CFL wave speed of mpmlab's elastic laws)."""
    mu, lam = E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))
    return math.sqrt((lam + 2 * mu) / density)


def _num(x: float) -> str:
    """A float as an override value that reads back exactly."""
    return repr(float(x))


@dataclass(frozen=True)
class Run:
    """One FOM run: its name, parameters and the Hydra overrides that make it (``mpmlab <overrides>``)."""

    name: str
    params: dict
    overrides: tuple


@dataclass(frozen=True)
class Study:
    """A study's runs and split (indices into ``runs``); ``interval`` is the snapshot spacing [s]."""

    name: str
    scene: str
    runs: tuple
    train: tuple
    test: tuple
    param_names: tuple
    snapshots: int
    interval: float
    seed: int = 0
    source: str = ""
    notes: str = ""
    #: reads a run's parameters back from its composed config (a dict): ``{name: value}``
    param_of: Callable[[dict], dict] = field(default=None, compare=False, repr=False)
    #: ``scene.vars`` its experiment sets for every run (the slow poke's speed)
    scene_vars: dict = field(default_factory=dict, compare=False)
    #: False for a single run (continual poking): its experiment is run as is, not swept
    sweep: bool = True

    def split(self, which: str | None) -> tuple:
        """Run indices of ``"train"``, ``"test"`` or all (None)."""
        if which is None:
            return tuple(range(len(self.runs)))
        if which not in ("train", "test"):
            raise ConfigError(f"study '{self.name}': split '{which}' unknown; use 'train', 'test' or None (all runs).")
        return self.train if which == "train" else self.test

    def param_array(self, idx: Sequence[int] | None = None) -> np.ndarray:
        idx = range(len(self.runs)) if idx is None else idx
        return np.array([[self.runs[i].params[k] for k in self.param_names] for i in idx], dtype=float)


def _random_split(n: int, n_test: int, seed: int) -> tuple[tuple, tuple]:
    perm = np.random.default_rng(seed).permutation(n)
    test = tuple(sorted(int(i) for i in perm[:n_test]))
    return tuple(i for i in range(n) if i not in test), test


def _vars(cfg: dict, *names: str) -> dict:
    return {k: float(cfg["scene"]["vars"][k]) for k in names}


# ---------------------------------------------------------------------------------------------------
# the studies
# ---------------------------------------------------------------------------------------------------
def gravity_study(seed: int = 0) -> Study:
    """Sec. 5.1: ``cylinder_wall_gravity`` at g = 30 values evenly in [1, 10] m/s^2 (gravity along -y),
    30 snapshots 10 ms apart (the scene's 1200 steps of 0.25 ms kept every 40), split 24/6 at random."""
    gs = np.linspace(1.0, 10.0, 30)
    runs = tuple(Run(f"g{i:02d}", {"g": float(g)},
                     ("scene=cylinder_wall_gravity", f"scene.gravity=[0.0,{_num(-g)},0.0]", *OUTPUT_OVERRIDES))
                 for i, g in enumerate(gs))
    train, test = _random_split(30, 6, seed)
    return Study("gravity", "cylinder_wall_gravity", runs, train, test, ("g",), 30, 0.01, seed,
                 "Deformation-map ROM paper, Sec. 5.1, Table 2",
                 "density 1000 kg/m^3 (soft_rubber); the snapshot spacing (10 ms) is the scene's choice",
                 param_of=lambda cfg: {"g": -float(cfg["scene"]["gravity"][1])})


def torsion_study(seed: int = 0, resolution: str | None = None) -> Study:
    """Sec. 5.2: ``rom_torsion`` on the 6 x 6 full-factorial grid v in [0, 0.6] m/s x omega in [0, 2] rad/s
    (v the slow index), 30 snapshots 1/1500 s apart, split 29/7 at random."""
    runs = []
    for i, v in enumerate(np.linspace(0.0, 0.6, 6)):
        for j, w in enumerate(np.linspace(0.0, 2.0, 6)):
            res = (f"scene.resolution={resolution}",) if resolution else ()
            runs.append(Run(f"v{i}w{j}", {"v": float(v), "omega": float(w)},
                            ("scene=rom_torsion", f"scene.vars.v={_num(v)}", f"scene.vars.omega={_num(w)}", *res,
                             *OUTPUT_OVERRIDES)))
    train, test = _random_split(36, 7, seed)
    return Study("torsion", "rom_torsion", tuple(runs), train, test, ("v", "omega"), 30, 1.0 / 1500.0, seed,
                 "Deformation-map ROM paper, Sec. 5.2, Table 2",
                 "one end fixed (implied), the other pulled and twisted rigidly; snapshot spacing 1/1500 s (mpmlab's)",
                 param_of=lambda cfg: _vars(cfg, "v", "omega"))


def torsion_fine_study(seed: int = 0) -> Study:
    """Sec. 5.2.1: the torsion test runs again at ``scene.resolution=fine`` (2x finer per axis), the
    super-resolution ground truth; all of them test runs."""
    base = torsion_study(seed, resolution="fine")
    runs = tuple(base.runs[i] for i in base.test)
    return Study("torsion_fine", "rom_torsion", runs, (), tuple(range(len(runs))), base.param_names, 30, base.interval,
                 seed, "Deformation-map ROM paper, Sec. 5.2.1, Table 4", "the torsion study's test runs at 2x resolution",
                 param_of=base.param_of)


def poke_study(speed: float | None = None, name: str = "poke") -> Study:
    """Sec. 5.3: ``rom_poke`` at theta = k pi/18 (k = 0..35); the 12 with theta = j pi/6 (k % 3 == 0)
    train, the other 24 test (the paper's split, not random). 432 snapshots 1/144 s apart (3 s).
    ``speed``: the poke's speed [m/s] instead of the scene's 4.8 cm/s (``poke_slow_study``)."""
    extra = () if speed is None else (f"scene.vars.speed={_num(speed)}",)
    runs = tuple(Run(f"k{k:02d}", {"theta": k * math.pi / 18.0},
                     ("scene=rom_poke", f"scene.vars.theta={_num(k * math.pi / 18.0)}", *extra, *OUTPUT_OVERRIDES))
                 for k in range(36))
    train = tuple(k for k in range(36) if k % 3 == 0)
    test = tuple(k for k in range(36) if k % 3)
    notes = "phi = 3 pi/4 (unreadable in the paper; mpmlab's)"
    if speed is not None:
        notes += f"; poke speed {speed * 1000:g} mm/s"
    return Study(name, "rom_poke", runs, train, test, ("theta",), 432, 1.0 / 144.0, 0,
                 "Deformation-map ROM paper, Sec. 5.3, Table 2", notes, param_of=lambda cfg: _vars(cfg, "theta"),
                 scene_vars={} if speed is None else {"speed": speed})


#: the slow poke's speed [m/s]: the paper's "4.8 cmm/s" (Sec. 5.3) read as 4.8 mm/s instead of 4.8 cm/s
POKE_SLOW_SPEED = 0.0048


def poke_slow_study() -> Study:
    """The poke study at 4.8 mm/s, the other reading of the paper's "4.8 cmm/s": the top point moves 1.2 mm
    (0.3 cells) in the 0.25 s instead of 12 mm, more than the cylinder's radius (``benchmarks/rom.md``,
    "The poke's speed"). Same runs, split and snapshots as ``poke_study``."""
    return poke_study(POKE_SLOW_SPEED, "poke_slow")


#: the poke scene's geometry (rom_poke.yaml): base centre, radius, height of the cylinder [m]
POKE_BASE, POKE_RADIUS, POKE_HEIGHT = (0.028, 0.028, 0.008), 0.01, 0.04


def continual_pokes(seed: int = 0, pokes: int = 10, period: float = 3.0) -> list[dict]:
    """The continual-poking schedule (Sec. 5.3.2): ``[{theta, t_start, t_end?}]``, theta_i ~ U[0, 2 pi)."""
    thetas = np.random.default_rng(seed).uniform(0.0, 2.0 * math.pi, pokes)
    return [{"theta": float(t), "t_start": i * period} for i, t in enumerate(thetas)]


def continual_poke_boundaries(seed: int = 0, pokes: int = 10, period: float = 3.0) -> dict:
    """The boundaries that turn ``rom_poke`` into the continual run: ``poke`` disabled and ``poke_0`` ...
    added, each a grid_velocity (as ``poke``) on the nodes within poke_radius of its own top point during
    [3 i, 3 i + 0.25) s of step start times (the window ends half a step early, as ``poke``'s). phi, the
    speed, the poke radius and dt stay the scene's (interpolated), so they hold at every resolution. (Hydra
    cannot add a boundary from the command line, a typed dict refuses a plain one: they live in
    ``experiment=rom_snapshots_poke_continual``, written by :func:`experiment_yaml`.)"""
    bx, by, bz = POKE_BASE
    out: dict = {"poke": {"enabled": False}}
    r = "${scene.resolutions.${scene.resolution}.poke_radius}"
    for i, p in enumerate(continual_pokes(seed, pokes, period)):
        th, t0 = p["theta"], p["t_start"]
        s, sp = "${scene.vars.speed}", "${mpmlab.sin:${scene.vars.phi}}"
        c = [_num(bx - POKE_RADIUS * math.cos(th)), _num(by - POKE_RADIUS * math.sin(th)), _num(bz + POKE_HEIGHT)]
        out[f"poke_{i}"] = {
            "kind": "grid_velocity",
            "region": {"kind": "box", "lo": [f"${{mpmlab.add:{a},${{mpmlab.mul:-1,{r}}}}}" for a in c],
                       "hi": [f"${{mpmlab.add:{a},{r}}}" for a in c]},
            "velocity": [f"${{mpmlab.mul:{s},{sp},{_num(math.cos(th))}}}", f"${{mpmlab.mul:{s},{sp},{_num(math.sin(th))}}}",
                         "${mpmlab.mul:${scene.vars.speed},${mpmlab.cos:${scene.vars.phi}}}"],
            "t_start": float(t0),
            "t_end": f"${{mpmlab.add:{_num(t0)},${{scene.vars.duration}},${{mpmlab.mul:-0.5,${{scene.dt}}}}}}",
        }
    return out


def poke_continual_study(seed: int = 0, pokes: int = 10, speed: float | None = None,
                         name: str = "poke_continual") -> Study:
    """Sec. 5.3.2: one run of ``pokes`` random pokes, 3 s each (4,320 snapshots for 10), a test run; its
    overrides select ``experiment=rom_snapshots_<name>`` (seed 0, 10 pokes). ``speed``: as in
    :func:`poke_study`."""
    sched = continual_pokes(seed, pokes)
    run = Run("continual", {"thetas": [p["theta"] for p in sched]}, (f"experiment=rom_snapshots_{name}",))
    notes = "poke directions theta_i ~ U[0, 2 pi) from default_rng(seed); a poke every 3 s"
    if speed is not None:
        notes += f"; poke speed {speed * 1000:g} mm/s"
    return Study(name, "rom_poke", (run,), (), (0,), (), pokes * 432, 1.0 / 144.0, seed,
                 "Deformation-map ROM paper, Sec. 5.3.2, Table 6", notes, param_of=lambda cfg: {},
                 scene_vars={} if speed is None else {"speed": speed}, sweep=False)


def poke_slow_continual_study(seed: int = 0, pokes: int = 10) -> Study:
    """Continual poking at 4.8 mm/s: the test run of the weights trained on ``poke_slow``."""
    return poke_continual_study(seed, pokes, POKE_SLOW_SPEED, "poke_slow_continual")


#: the tower's parameter ranges [lo, hi) (see the module docstring for why these)
TOWER_RANGES = {"r": (0.06, 0.08), "theta": (0.0, math.pi / 2), "phi": (-math.pi / 3, -math.pi / 6)}


def tower_study(seed: int = 0, n_train: int = 16, n_test: int = 4) -> Study:
    """Sec. 5.4: ``rom_tower`` with (r, theta, phi) from two Latin hypercubes (train: seed, test:
    seed + 1), 80 snapshots 1/24 s apart."""
    from scipy.stats import qmc

    lo = np.array([TOWER_RANGES[k][0] for k in ("r", "theta", "phi")])
    hi = np.array([TOWER_RANGES[k][1] for k in ("r", "theta", "phi")])
    pts = [qmc.scale(qmc.LatinHypercube(d=3, seed=seed + j).random(n), lo, hi) for j, n in ((0, n_train), (1, n_test))]
    runs = []
    for tag, P in zip(("train", "test"), pts):
        for i, (r, th, ph) in enumerate(P):
            runs.append(Run(f"{tag}{i:02d}", {"r": float(r), "theta": float(th), "phi": float(ph)},
                            ("scene=rom_tower", f"scene.vars.r={_num(r)}", f"scene.vars.theta={_num(th)}",
                             f"scene.vars.phi={_num(ph)}", *OUTPUT_OVERRIDES)))
    return Study("tower", "rom_tower", tuple(runs), tuple(range(n_train)), tuple(range(n_train, n_train + n_test)),
                 ("r", "theta", "phi"), 80, 1.0 / 24.0, seed, "Deformation-map ROM paper, Sec. 5.4, Fig. 15, Table 2",
                 "procedural stand-in tower; r in [0.06, 0.08) m/s (Fig. 15), theta in [0, pi/2), phi in [-pi/3, -pi/6)",
                 param_of=lambda cfg: _vars(cfg, "r", "theta", "phi"))


def beam_2d_study(resolution: str | None = None) -> Study:
    """mpmlab's small 2D problem (not the paper's): ``rom_beam_2d``, a cantilever under g = 2, 3, ..., 8 m/s^2
    (gravity along -y); even g train (4 runs), odd g test (3). Its snapshots are the scene's frames
    (10 ms apart; 20 at ``tiny``, 40 at ``default``)."""
    res = (f"scene.resolution={resolution}",) if resolution else ()
    gs = [float(g) for g in range(2, 9)]
    runs = tuple(Run(f"g{int(g)}", {"g": g}, ("scene=rom_beam_2d", f"scene.gravity=[0.0,{_num(-g)}]", *res,
                                               *OUTPUT_OVERRIDES)) for g in gs)
    train = tuple(i for i, g in enumerate(gs) if int(g) % 2 == 0)
    test = tuple(i for i, g in enumerate(gs) if int(g) % 2)
    return Study("beam_2d", "rom_beam_2d", runs, train, test, ("g",), 20 if resolution == "tiny" else 40, 0.01, 0,
                 "mpmlab (a 2D analogue of the ROM paper's Sec. 5.1)", "density 1000 kg/m^3, E 50 kPa; even g train",
                 param_of=lambda cfg: {"g": -float(cfg["scene"]["gravity"][1])})


STUDIES: dict[str, Callable[..., Study]] = {
    "gravity": gravity_study, "torsion": torsion_study, "torsion_fine": torsion_fine_study, "poke": poke_study,
    "poke_slow": poke_slow_study, "poke_continual": poke_continual_study,
    "poke_slow_continual": poke_slow_continual_study, "tower": tower_study, "beam_2d": beam_2d_study,
}


def study(name: str, **kw) -> Study:
    """The study ``name`` (``STUDIES``), with its builder's keywords (``seed``)."""
    if name not in STUDIES:
        raise ConfigError(f"ROM snapshot study '{name}' unknown; known: {', '.join(STUDIES)}.")
    return STUDIES[name](**kw)


def sweep_value(s: Study) -> dict[str, str]:
    """The Hydra sweeper ``params`` that run every run of ``s``: one swept key (``scene.vars`` as dicts,
    which Hydra merges into the scene's, or ``scene.gravity`` as vectors), so that co-varying
    parameters (the tower's Latin hypercube) stay together."""
    if s.name == "beam_2d":
        return {"scene.gravity": ",".join(f"[0.0,{_num(-r.params['g'])}]" for r in s.runs)}
    if s.name == "gravity":
        return {"scene.gravity": ",".join(f"[0.0,{_num(-r.params['g'])},0.0]" for r in s.runs)}
    if not s.sweep:
        raise ConfigError(f"study '{s.name}' is one run; it is not a sweep.")
    return {"scene.vars": ",".join("{" + ",".join(f"{k}:{_num(r.params[k])}" for k in s.param_names) + "}"
                                   for r in s.runs)}


def experiment_yaml(s: Study) -> str:
    """The text of ``conf/experiment/rom_snapshots_<name>.yaml`` (written by ``python -m
    mpmlab.rom.snapshots``; tests/test_rom_snapshots.py checks that the shipped files equal it)."""
    import yaml

    head = [f"# @package _global_",
            f"# GENERATED by `python -m mpmlab.rom.snapshots` from mpmlab/rom/snapshots.py ({s.name}_study, seed "
            f"{s.seed}): edit that, not this.",
            f"# {s.source}: the {len(s.runs)} full-order run(s) of study '{s.name}' "
            f"({len(s.train)} train / {len(s.test)} test, the split is in the module), each writing",
            f"# trajectory.h5 with x, v and F at the {s.snapshots} snapshots ({s.notes}).",
            f"# Read them back with mpmlab.rom.snapshots.load_snapshots(<sweep dir>, '{s.name}'" + (", split='train')." if s.train else ")."),
            (f"# Run: `mpmlab -m experiment=rom_snapshots_{s.name}` (add scene.resolution=tiny for a smoke test)."
             if s.sweep else
             f"# Run: `mpmlab experiment=rom_snapshots_{s.name}` (one run; scene.resolution=tiny for a smoke test).")]
    body: dict = {"defaults": [{"override /scene": s.scene}, {"override /transfer": "pic"}],
                  "output": {"fields": ["F"], "recording": False}}
    if s.name == "torsion_fine":
        body["scene"] = {"resolution": "fine"}
    if s.scene_vars:
        body["scene"] = {"vars": dict(s.scene_vars)}
    if not s.sweep:
        body.setdefault("scene", {})["boundaries"] = continual_poke_boundaries(s.seed, len(s.runs[0].params["thetas"]))
        body["steps"] = f"${{mpmlab.imul:{s.snapshots},${{scene.frame_every}}}}"
    else:
        body["hydra"] = {"sweeper": {"params": sweep_value(s)}}
    return "\n".join(head) + "\n" + yaml.safe_dump(body, sort_keys=False, width=100000, default_flow_style=None)


def experiment_path(name: str) -> Path:
    from ..config import CONF_DIR

    return CONF_DIR / "experiment" / f"rom_snapshots_{name}.yaml"


def write_experiments() -> list[Path]:
    """(Re)write every ``conf/experiment/rom_snapshots_<study>.yaml`` from the studies (default seeds)."""
    out = []
    for name in STUDIES:
        p = experiment_path(name)
        p.write_text(experiment_yaml(study(name)))
        out.append(p)
    return out


# ---------------------------------------------------------------------------------------------------
# running
# ---------------------------------------------------------------------------------------------------
def run_study(s: Study, root: str | os.PathLike, runs: Iterable[int] | None = None, overrides: Sequence[str] = (),
              overwrite: bool = False) -> list[Path]:
    """Run the runs ``runs`` (indices; default all) of ``s`` one after another in this process, each into
    ``root/<run name>/`` (trajectory.h5 with x, v, F at the snapshots, summary.json, config.yaml);
    ``overrides`` are added to every run's (``scene.resolution=tiny``, ``backend=warp``). The CLI's
    ``mpmlab -m experiment=rom_snapshots_<study>`` does the same as a Hydra sweep."""
    from ..config import compose
    from ..tasks import RunContext, run_task

    root = Path(root)
    done = []
    for i in (range(len(s.runs)) if runs is None else runs):
        run = s.runs[i]
        ov = [*run.overrides, *overrides]
        cfg = compose(ov)
        out = root / run.name
        out.mkdir(parents=True, exist_ok=True)
        run_task(cfg, RunContext(output_dir=out, overwrite=overwrite, progress=False,
                                 job={"name": f"rom_{s.name}", "num": i, "overrides": ov}))
        done.append(out / "trajectory.h5")
    return done


# ---------------------------------------------------------------------------------------------------
# reading
# ---------------------------------------------------------------------------------------------------
@dataclass
class Snapshots:
    """A study's snapshots: ``x``, ``v`` ``[runs, frames, N, d]``, ``F`` ``[runs, frames, N, d, d]``, the
    runs' ``params`` ``[runs, P]`` (columns ``param_names``), ``time`` ``[frames]`` [s], the run indices
    ``runs`` into ``study.runs`` and the files read."""

    study: Study
    runs: tuple
    names: tuple
    param_names: tuple
    params: np.ndarray
    x: np.ndarray
    v: np.ndarray
    F: np.ndarray
    time: np.ndarray
    paths: tuple
    attrs: list = field(default_factory=list)

    @property
    def X(self) -> np.ndarray:
        """Reference positions ``[runs, N, d]`` (the first snapshot)."""
        return self.x[:, 0]


def _config_of(attrs: dict, path: Path) -> dict:
    from omegaconf import OmegaConf

    text = attrs.get("config_yaml") or ""
    if not text:
        raise ConfigError(f"'{path}' records no config (config_yaml), so its run's parameters are unknown; "
                          f"write it with `mpmlab` (task=simulate).")
    return OmegaConf.to_container(OmegaConf.create(text), resolve=True)


def _match(s: Study, params: dict, path: Path) -> int:
    want = np.array([params[k] for k in s.param_names], float)
    have = s.param_array()
    hit = [i for i in range(len(s.runs)) if np.allclose(have[i], want, rtol=1e-9, atol=1e-12)] if len(want) else \
        list(range(len(s.runs)))
    if len(hit) != 1:
        raise ConfigError(f"'{path}' is a run of scene '{s.scene}' with {params}, which is "
                          f"{'not a run' if not hit else 'ambiguous among the runs'} of study '{s.name}'.")
    return hit[0]


def load_snapshots(root: str | os.PathLike | Sequence[str | os.PathLike], s: Study | str, split: str | None = None,
                   runs: Sequence[int] | None = None, dtype=None) -> Snapshots:
    """Read study ``s``'s snapshots (its ``split``: ``train``, ``test`` or all; or the run indices ``runs``)
    from the ``trajectory.h5``
    files under ``root`` (a directory searched recursively, or a list of files), in the study's run order.

    Each file is matched to a run by the parameters its recorded config holds (``scene.vars`` /
    ``scene.gravity``); files of another scene are skipped. Refused with a one-line ``ConfigError``: a run
    of the split without a file, two files for one run, a file whose parameters are no run of the study,
    a file without v or F (or F on only some particles), an incomplete file, runs with different particle
    counts or snapshot times.
    """
    from ..io.h5 import read_attrs, read_trajectory

    s = study(s) if isinstance(s, str) else s
    want = s.split(split) if runs is None else tuple(int(i) for i in runs)
    if any(not 0 <= i < len(s.runs) for i in want):
        raise ConfigError(f"study '{s.name}' has runs 0..{len(s.runs) - 1}; got runs={list(want)}.")
    if isinstance(root, (str, os.PathLike)):
        base = Path(root)
        if not base.is_dir():
            raise ConfigError(f"ROM snapshots: '{base}' is not a directory; give the directory the study's runs "
                              f"wrote into (or a list of trajectory.h5 files).")
        files = sorted(base.rglob("trajectory.h5"))
        where = str(base)
    else:
        files = [Path(p) for p in root]
        where = f"the {len(files)} files given"
    found: dict[int, tuple[Path, dict, dict]] = {}
    for path in files:
        attrs = read_attrs(path)
        if attrs.get("scene") not in (None, s.scene):
            continue
        resolved = _config_of(attrs, path)
        if resolved.get("scene", {}).get("name") != s.scene:
            continue
        i = _match(s, s.param_of(resolved), path)
        if i in found:
            raise ConfigError(f"study '{s.name}': run {s.runs[i].name} has two files, '{found[i][0]}' and '{path}'; "
                              f"keep one.")
        found[i] = (path, attrs, resolved)
    missing = [s.runs[i].name for i in want if i not in found]
    if missing:
        exp = "run_study" if not s.sweep else f"mpmlab -m experiment=rom_snapshots_{s.name}"
        which = "asked for" if runs is not None else f"of the {split or 'whole'} split"
        raise ConfigError(f"study '{s.name}': {len(missing)} run(s) {which} have no "
                          f"trajectory.h5 under {where} ({', '.join(missing[:4])}{', ...' if len(missing) > 4 else ''}); "
                          f"make them with `{exp}` (or mpmlab.rom.snapshots.run_study).")
    xs, vs, Fs, paths, times, attrs_all = [], [], [], [], None, []
    n_ref = None
    for i in want:
        path, attrs, _ = found[i]
        traj = read_trajectory(path, require_complete=True)
        N = int(traj.mass.shape[0])
        if np.asarray(traj.v).size == 0 and N:
            raise ConfigError(f"'{path}' (study '{s.name}', run {s.runs[i].name}) stores no v; rerun it.")
        if "F" not in traj.fields or np.asarray(traj.fields["F"]).size == 0 and N:
            raise ConfigError(f"'{path}' (study '{s.name}', run {s.runs[i].name}) stores no F (fields: "
                              f"{', '.join(traj.fields) or 'none'}); rerun it with output.fields=[F].")
        idx = traj.field_particles.get("F")
        if idx is not None and len(idx) != N:
            raise ConfigError(f"'{path}' holds F for {len(idx)} of its {N} particles; the ROM needs F at every particle.")
        if n_ref is None:
            n_ref, first = N, path
        elif N != n_ref:
            raise ConfigError(f"study '{s.name}': '{path}' has {N} particles but '{first}' has {n_ref}; the runs of a "
                              f"study must share one discretisation (the same scene.resolution).")
        t = np.asarray(traj.time, float)
        if times is None:
            times = t
        elif t.shape != times.shape or not np.allclose(t, times, rtol=1e-6, atol=1e-9):
            raise ConfigError(f"study '{s.name}': '{path}' keeps {len(t)} snapshots up to t = {t[-1]:.6g} s but "
                              f"'{first}' keeps {len(times)} up to t = {times[-1]:.6g} s; rerun with the same steps.")
        cast = (lambda a: np.asarray(a, dtype)) if dtype is not None else np.asarray
        xs.append(cast(traj.x)); vs.append(cast(traj.v)); Fs.append(cast(traj.fields["F"]))
        paths.append(path); attrs_all.append(attrs)
    if not want:
        raise ConfigError(f"study '{s.name}' has no run in the {split} split.")
    return Snapshots(s, tuple(want), tuple(s.runs[i].name for i in want), s.param_names, s.param_array(want),
                     np.stack(xs), np.stack(vs), np.stack(Fs), times, tuple(paths), attrs_all)


def write_params(snap: Snapshots, path: str | os.PathLike) -> None:
    """The runs' names and parameters as JSON (``{name: {param: value}}``), for a ROM training record."""
    Path(path).write_text(json.dumps({n: dict(zip(snap.param_names, map(float, p)))
                                      for n, p in zip(snap.names, snap.params)}, indent=1))


__all__ = ["Run", "Study", "Snapshots", "STUDIES", "study", "gravity_study", "torsion_study", "torsion_fine_study",
           "poke_study", "poke_slow_study", "POKE_SLOW_SPEED", "poke_continual_study", "tower_study", "beam_2d_study", "continual_pokes", "continual_poke_boundaries", "experiment_yaml",
           "sweep_value", "experiment_path", "write_experiments", "run_study", "load_snapshots", "substeps", "p_wave_speed", "SNAPSHOT_CFL", "TOWER_RANGES"]


if __name__ == "__main__":
    for _p in write_experiments():
        print(_p)
