"""Pieces the tasks share: output names, atomic JSON/YAML/PNG writes, frame timing, energy plot,
the one-line summary."""
from __future__ import annotations

import logging
import math
import time
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from ..core.errors import ConfigError

log = logging.getLogger("mpmlab")

TRAJECTORY = "trajectory.h5"
RECORDING = "recording.rrd"
SUMMARY = "summary.json"
CONFIG = "config.yaml"
ENERGY_PLOT = "energy.png"


def check_outputs(output_dir: Path, names: Iterable[str], overwrite: bool) -> None:
    """Refuse to run when an output would replace an existing file (before any work is done)."""
    from ..io.files import check_target

    output_dir = Path(output_dir)
    if output_dir.exists() and not output_dir.is_dir():
        raise ConfigError(f"output directory '{output_dir}' is a file; choose another with hydra.run.dir=PATH.")
    for name in names:
        check_target(output_dir / name, overwrite)


def write_text(path: Path, text: str, overwrite: bool = False) -> Path:
    from ..io.files import write_atomically

    return write_atomically(path, lambda tmp: Path(tmp).write_text(text), overwrite)


def write_json(path: Path, obj: Any, overwrite: bool = False) -> Path:
    from ..io.h5 import to_json

    return write_text(path, to_json(obj) + "\n", overwrite)


def write_config(output_dir: Path, cfg, overwrite: bool = False) -> Path:
    """The composed config (values resolved) as ``config.yaml`` (``OmegaConf.load`` reads it back; the
    overrides that produced it are in ``summary.json``, so ``mpmlab <overrides>`` repeats the run)."""
    from omegaconf import OmegaConf

    return write_text(Path(output_dir) / CONFIG, OmegaConf.to_yaml(cfg, resolve=True), overwrite)


class FrameClock:
    """``on_frame`` companion: wall-clock time of every kept frame, for steady-state throughput.

    Frame 0 is logged before the first step; the first chunk (frame 0 -> 1) pays the compilation
    (JAX tracing/XLA, Warp module loads); frames 1..T are the steady state. The time a run spends on
    its outputs in ``on_frame`` (streaming the trajectory, per-frame metrics: ``output(seconds)``) is
    taken out of the throughput and reported as ``output_time_s``.
    """

    def __init__(self):
        self.times: list[float] = []     # wall clock [s]
        self.steps: list[int] = []
        self.times_s: list[float] = []   # simulated time of each kept frame [s]
        self.output_s: list[float] = []  # wall time spent on each frame's outputs [s]

    def __call__(self, frame_index: int, npstate: dict, step: int) -> None:
        self.times.append(time.perf_counter())
        self.steps.append(int(step))
        self.times_s.append(float(npstate.get("time", np.nan)))

    @property
    def count(self) -> int:
        return len(self.steps)

    def output(self, seconds: float) -> None:
        """The wall time the outputs of the frame just stamped took."""
        self.output_s.append(float(seconds))

    def _stepping(self) -> np.ndarray:
        """Wall times of the stamps with the outputs of earlier frames taken out."""
        t = np.asarray(self.times, dtype=np.float64)
        out = np.zeros(len(t))
        o = np.asarray(self.output_s[: len(t)], dtype=np.float64)
        out[1: len(o) + 1] = np.cumsum(o)[: len(t) - 1]
        return t - out

    def timing(self, particles: int) -> dict:
        wall, s = np.asarray(self.times), np.asarray(self.steps)
        t = self._stepping()
        out: dict[str, Any] = {"rollout_time_s": float(wall[-1] - wall[0]) if len(wall) > 1 else 0.0,
                               "output_time_s": float(np.sum(self.output_s))}
        if len(t) >= 3 and s[-1] > s[1]:
            per_step = (t[-1] - t[1]) / (s[-1] - s[1])
            out["steady_steps"] = int(s[-1] - s[1])
            out["steady_time_s"] = float(t[-1] - t[1])
            out["seconds_per_step"] = float(per_step)
            out["particle_steps_per_second"] = float(particles / per_step) if per_step > 0 else None
            out["compile_time_s"] = float(max(0.0, (t[1] - t[0]) - per_step * (s[1] - s[0])))
            out["throughput_includes_compile"] = False
        elif len(t) >= 2 and s[-1] > 0:
            # one chunk only: compilation cannot be separated from stepping
            out["steady_steps"] = 0
            out["seconds_per_step"] = float((t[-1] - t[0]) / s[-1])
            out["particle_steps_per_second"] = float(particles * s[-1] / (t[-1] - t[0])) if t[-1] > t[0] else None
            out["compile_time_s"] = None
            out["throughput_includes_compile"] = True
        else:
            out.update(steady_steps=0, seconds_per_step=None, particle_steps_per_second=None,
                       compile_time_s=None, throughput_includes_compile=True)
        return out

    def step_time_per_frame(self) -> np.ndarray:
        """Mean wall time per step [s] of the chunk ending at each frame (NaN at frame 0; outputs not
        counted)."""
        t, s = self._stepping(), np.asarray(self.steps)
        out = np.full(len(t), np.nan)
        if len(t) > 1:
            ds = np.diff(s)
            out[1:] = np.where(ds > 0, np.diff(t) / np.maximum(ds, 1), np.nan)
        return out


def drift(metrics: dict, time_s: np.ndarray, gravity: Any) -> dict:
    """Mass and momentum drift between the first and last frame.

    ``momentum_drift`` is the change of total linear momentum not explained by gravity,
    p(T) - p(0) - M g T [kg m/s]; walls and other boundaries legitimately exchange momentum, so it is
    a diagnostic, exactly zero only for a free body. ``*_rel`` divide by M and by the largest particle
    speed scale seen (max over frames of |p|/M and |g| T).
    """
    if not metrics or len(metrics.get("mass", [])) == 0:
        return {}
    m = np.asarray(metrics["mass"], float)
    p = np.asarray(metrics["linear_momentum"], float)
    T = float(time_s[-1] - time_s[0]) if len(time_s) else 0.0
    g = np.zeros(p.shape[-1]) if gravity is None else np.asarray(gravity, float)
    M = float(m[0])
    dp = p[-1] - p[0] - M * g * T
    scale = max(float(np.max(np.linalg.norm(p, axis=-1))) / M if M else 0.0, float(np.linalg.norm(g)) * T, 1e-12)
    return {
        "mass_drift_rel": float((m[-1] - m[0]) / m[0]) if m[0] else 0.0,
        "momentum_drift": dp.tolist(),
        "momentum_drift_rel": float(np.linalg.norm(dp) / (M * scale)) if M else 0.0,
    }


def energy_series(metrics: dict) -> dict[str, np.ndarray]:
    """Kinetic, gravitational (relative to frame 0), elastic and total energy per frame [J; J/m in 2D,
    where masses are per unit depth]."""
    out = {}
    if "kinetic_energy" in metrics:
        out["kinetic"] = np.asarray(metrics["kinetic_energy"], float)
    if "gravity_potential_energy" in metrics:
        g = np.asarray(metrics["gravity_potential_energy"], float)
        out["gravitational (rel. to t=0)"] = g - g[0]
    if "elastic_energy" in metrics:
        out["elastic"] = np.asarray(metrics["elastic_energy"], float)
    if out:
        out["total"] = np.sum(np.stack(list(out.values())), axis=0)
    return out


def plot_energy(path: Path, time_s: np.ndarray, metrics: dict, title: str, overwrite: bool = False,
                dim: int = 3) -> Path | None:
    """Energy over time as a PNG (matplotlib, Agg backend), written atomically; in 2D the energies are
    per unit depth (J/m)."""
    series = energy_series(metrics)
    if not series or len(time_s) == 0:
        return None
    from matplotlib.figure import Figure  # no pyplot: no GUI backend, no global state (Agg canvas)

    from ..io.files import write_atomically

    fig = Figure(figsize=(7, 4), dpi=110)
    ax = fig.subplots()
    for name, y in series.items():
        ax.plot(time_s, y, label=name, lw=2.2 if name == "total" else 1.4, color="k" if name == "total" else None)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("energy per unit depth [J/m]" if dim == 2 else "energy [J]")
    ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    # the title also as PNG metadata (tEXt "Title"): readable without looking at the picture
    return write_atomically(path, lambda tmp: fig.savefig(tmp, format="png", metadata={"Title": title}), overwrite)


def save_figure(fig, path: Path, title: str = "") -> Path:
    """A matplotlib figure as a PNG, written atomically (the title also as PNG metadata), then closed."""
    import matplotlib.pyplot as plt

    from ..io.files import write_atomically

    try:
        return write_atomically(path, lambda tmp: fig.savefig(tmp, format="png", dpi=110,
                                                              metadata={"Title": title} if title else None),
                                overwrite=True)
    finally:
        plt.close(fig)


def fmt_rate(x: float | None) -> str:
    return "n/a" if x is None or not math.isfinite(x) else f"{x:.3g}"
