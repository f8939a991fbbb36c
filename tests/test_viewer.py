"""Recordings as a person sees them: rendered by the real rerun viewer and checked pixel by pixel.

The desktop viewer (``rerun --screenshot-to``, the CLI that comes with rerun-sdk) draws each recording
in an Xvfb display with a software Vulkan driver (Mesa's lavapipe); ``.ci/run`` installs both
(``apt-get install xvfb mesa-vulkan-drivers``). ``-extension Composite`` keeps the viewer's window
opaque (it asks for a transparent one, which Xvfb's compositor would otherwise make black). The screen
is larger than the window, so the pointer (at the screen's centre) does not hover anything.

Where the machine cannot render (no Xvfb, no Vulkan driver, no rerun CLI, a viewer that draws nothing),
every test here skips and says why.
"""
from __future__ import annotations

import glob
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from mpmlab.core.state import Trajectory
from mpmlab.io import rerun as mrr

pytestmark = pytest.mark.slow

WINDOW = (1280, 800)              # logical points; the screenshot has 2x as many pixels
SCREEN = "5200x3300x24"           # the pointer (at its centre) lies outside the window
ORANGE = mrr.PALETTE[1]           # body 1's colour: nowhere in the viewer's own UI below the top bar


# ---- the viewer ---------------------------------------------------------------------------------
def _rerun_cli() -> str | None:
    here = Path(sys.executable).parent / "rerun"
    return str(here) if here.exists() else shutil.which("rerun")


def _start_xvfb() -> tuple[subprocess.Popen | None, str]:
    """(process, display) of a fresh Xvfb, or (None, why not)."""
    exe = shutil.which("Xvfb")
    if exe is None:
        return None, "Xvfb is not installed (apt-get install xvfb mesa-vulkan-drivers, as .ci/run does)"
    r, w = os.pipe()
    proc = subprocess.Popen([exe, "-displayfd", str(w), "-screen", "0", SCREEN, "-extension", "Composite",
                             "-nolisten", "tcp"], pass_fds=(w,), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    os.close(w)
    deadline = time.monotonic() + 20
    num = b""
    os.set_blocking(r, False)
    while time.monotonic() < deadline and proc.poll() is None and not num.endswith(b"\n"):
        try:
            num += os.read(r, 16)
        except BlockingIOError:
            time.sleep(0.05)
    os.close(r)
    if not num.strip():
        err = proc.stderr.read().decode(errors="replace")[-300:] if proc.poll() is not None else "no display number"
        proc.kill()
        return None, f"Xvfb did not start: {err.strip()}"
    return proc, f":{int(num)}"


class Viewer:
    def __init__(self, cli: str, env: dict):
        self.cli, self.env = cli, env

    def screenshot(self, rrd: Path, png: Path, timeout: float = 180) -> tuple[bool, str]:
        """Render ``rrd`` in the desktop viewer; (a PNG was written, the viewer's log tail)."""
        log = png.with_suffix(".log")
        t0 = time.perf_counter()
        with open(log, "wb") as f:
            try:
                rc = subprocess.run([self.cli, "--window-size", "x".join(map(str, WINDOW)), "--screenshot-to",
                                     str(png), str(rrd)], env=self.env, stdout=f, stderr=subprocess.STDOUT,
                                    timeout=timeout).returncode
            except subprocess.TimeoutExpired:
                rc = "timeout"
        ok = rc == 0 and png.exists() and png.stat().st_size > 0
        return ok, f"exit {rc} after {time.perf_counter() - t0:.0f} s: {_why(log.read_text(errors='replace'))}"


def _why(log: str) -> str:
    """The viewer's error lines (ANSI colours removed), else the end of its log."""
    import re

    lines = [re.sub(r"\x1b\[[0-9;]*m", "", ln) for ln in log.splitlines()]
    errors = [ln for ln in lines if "ERROR" in ln or ln.startswith("Error")]
    return errors[-1][-600:] if errors else " | ".join(lines[-3:])[-600:]


@pytest.fixture(scope="module")
def viewer():
    cli = _rerun_cli()
    if cli is None:
        pytest.skip("the rerun CLI (rerun-sdk) is not on PATH")
    if not glob.glob("/usr/share/vulkan/icd.d/*.json") and not os.environ.get("VK_ICD_FILENAMES"):
        pytest.skip("no Vulkan driver to render with (apt-get install mesa-vulkan-drivers, as .ci/run does)")
    proc, display = _start_xvfb()
    if proc is None:
        pytest.skip(display)
    home = Path(os.environ.get("PYTEST_VIEWER_HOME", "/tmp")) / f"mpmlab-viewer-{os.getpid()}"
    home.mkdir(parents=True, exist_ok=True)
    # scale factor 1: the window is 1280 x 800 pixels, the pointer (at the screen's centre) outside it
    env = {**os.environ, "DISPLAY": display, "XDG_RUNTIME_DIR": str(home), "WINIT_X11_SCALE_FACTOR": "1"}
    env.pop("WAYLAND_DISPLAY", None)     # winit would prefer a Wayland compositor over our Xvfb
    env.pop("RUST_LOG", None)            # a log level shows the viewer's warnings as toasts over the views
    try:
        yield Viewer(cli, env)
    finally:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
        shutil.rmtree(home, ignore_errors=True)


@pytest.fixture(scope="module")
def shots(viewer, tmp_path_factory):
    """The two screenshots the tests look at (each costs ~10 s of software rendering)."""
    d = tmp_path_factory.mktemp("viewer")
    out = {}
    for name, traj in (("floor_2d", _floor_2d()), ("block_3d", _block_3d())):
        rrd = mrr.write_recording(d / f"{name}.rrd", traj, color_by="body", metrics=None)
        ok, log = viewer.screenshot(rrd, d / f"{name}.png")
        if not ok and not out:    # can this machine render at all? A recording of one point says
            ok_probe, log_probe = viewer.screenshot(_probe(d / "probe.rrd"), d / "probe.png")
            if not ok_probe:
                pytest.skip(f"the rerun viewer cannot render here: {log_probe}")
        assert ok, f"the viewer renders a plain recording but not mpmlab's {name}: {log}"
        out[name] = _load(d / f"{name}.png")
    return out


def _probe(path: Path) -> Path:
    import rerun as rr

    rec = rr.RecordingStream("mpmlab-probe")
    rec.save(path)
    rec.log("point", rr.Points3D([[0.0, 0.0, 0.0]]))
    rec.flush()
    rec.disconnect()
    return path


def _load(png: Path) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(png).convert("RGB")).astype(np.int32)


# ---- recordings -------------------------------------------------------------------------------------
def _traj(x: np.ndarray, dx: float, shape: list[int], gravity: list[float], volume: float) -> Trajectory:
    T, N, D = x.shape
    rng = np.random.default_rng(0)
    return Trajectory(
        x=x, v=0.05 * rng.standard_normal(x.shape), time=np.arange(T) * 1e-3, step=np.arange(T), mass=np.ones(N),
        volume=np.full(N, volume), material_id=np.zeros(N, np.int64), body_id=np.ones(N, np.int64),
        materials=[{"law": "fixed_corotated", "param_names": ["E", "nu"], "start": 0, "stop": N}],
        params=np.tile([1e5, 0.3], (N, 1)), meta={"dim": D, "dx": dx, "grid_origin": [0.0] * D, "grid_shape": shape,
                                                   "gravity": gravity, "scene": "viewer_test", "dt": 1e-3})


def _floor_2d() -> Trajectory:
    """A 1 m x 1 m tank whose particles all lie in a layer 2..10 cm above the floor."""
    gx, gy = np.meshgrid(np.arange(0.05, 0.951, 0.02), np.arange(0.02, 0.101, 0.02), indexing="ij")
    x = np.stack([gx.ravel(), gy.ravel()], -1)
    return _traj(np.stack([x, x]), 0.05, [21, 21], [0.0, -9.8], 0.02 ** 2)


def _block_3d() -> Trajectory:
    """A block of particles in the middle of a 1 m cube (the domain box is drawn around it)."""
    g = np.arange(0.35, 0.651, 0.03)
    x = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    return _traj(np.stack([x, x]), 0.05, [21, 21, 21], [0.0, -9.8, 0.0], 0.03 ** 3)


# ---- pixels -----------------------------------------------------------------------------------------
def _orange(img: np.ndarray) -> np.ndarray:
    """Pixels of the particles' colour (shaded: the hue of PALETTE[1], any brightness), in blobs of
    touching particles (the legend's swatch and a plot's orange legend dot are small and left out)."""
    from scipy import ndimage

    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    mask = (r > 90) & (r > g + 40) & (g > b + 25) & (b < 90)
    mask[: int(0.06 * img.shape[0])] = False    # the top bar (its notification dot is orange)
    labels, n = ndimage.label(ndimage.binary_dilation(mask, iterations=3))
    if n == 0:
        return mask
    sizes = ndimage.sum(mask, labels, index=np.arange(1, n + 1))
    keep = np.isin(labels, 1 + np.nonzero(sizes > 4000)[0])
    return mask & keep


def _domain_grey(img: np.ndarray) -> np.ndarray:
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    return (np.abs(r - 150) < 35) & (np.abs(g - r) < 8) & (np.abs(b - r) < 8)


def test_screenshots_are_not_blank(shots):
    for name, img in shots.items():
        assert img.shape[0] >= WINDOW[1] and img.shape[1] >= WINDOW[0], name
        assert img.std() > 8, f"{name}: a blank screenshot (std {img.std():.1f})"
        colours = len(np.unique(img[::4, ::4].reshape(-1, 3) // 8, axis=0))
        assert colours > 60, f"{name}: only {colours} colours"
        assert _orange(img).sum() > 2000, f"{name}: no particles drawn"


def test_2d_particles_near_the_floor_are_drawn_in_the_lower_part_of_the_view(shots):
    img = shots["floor_2d"]
    H, W = img.shape[:2]
    ys, xs = np.nonzero(_orange(img))
    # the tank floor, y = 0: the longest horizontal grey line of the domain box in the particle view
    grey = _domain_grey(img)
    rows = grey[:, : int(0.98 * W)].sum(axis=1)
    floor = int(np.argmax(np.where(np.arange(H) > int(0.06 * H), rows, 0)))
    assert rows[floor] > 0.3 * W, "the domain box's floor line is not drawn"
    assert ys.max() < floor, f"particles (rows {ys.min()}..{ys.max()}) not above the floor (row {floor}): upside down"
    top = int(0.075 * H)     # below the menu bar and the view's title bar
    centre = ys.mean()
    assert floor - centre < centre - top, (f"particles (centre row {centre:.0f}) are not in the lower part of the view "
                                           f"between row {top} and the floor at row {floor}")
    # framed on the particles: they span most of the view's width, not a sliver of it
    assert xs.max() - xs.min() > 0.6 * W, f"the particles span {xs.max() - xs.min()} of {W} pixels"


def test_3d_particles_are_not_tinted_by_the_domain(shots):
    img = shots["block_3d"]
    H, W = img.shape[:2]
    view = img[int(0.09 * H): int(0.85 * H), : int(0.5 * W)]   # inside the particle view (left column)
    particles = view[_orange(view)]
    assert len(particles) > 5000, f"only {len(particles)} particle pixels"
    mean = particles.mean(axis=0)
    # an opaque or translucent box face over the particles shifts them towards its colour
    assert mean[2] < 60 and mean[0] > 2.0 * mean[2], f"particle colour {mean.round()} is not the palette's orange"
    r, g, b = view[..., 0], view[..., 1], view[..., 2]
    purple = (r - g > 20) & (b - g > 20)
    assert purple.mean() < 0.005, f"{purple.mean():.1%} of the particle view is purple (a filled domain box)"
    # the domain's wireframe is drawn, and the camera sees all of it: no grey line touches the view's edges
    grey = _domain_grey(view)
    assert grey.sum() > 1000, "the domain box is not drawn"
    ys, xs = np.nonzero(grey)
    assert ys.min() > 0.03 * view.shape[0] and ys.max() < 0.97 * view.shape[0], "the domain box is cut off (top/bottom)"
    assert xs.min() > 0.01 * view.shape[1] and xs.max() < 0.97 * view.shape[1], "the domain box is cut off at a side"
