"""The README's viewer screenshots, made the way a user sees them: run the workflow, open its
recording in the rerun desktop viewer, screenshot it. Nothing here is drawn by hand.

    python benchmarks/screenshots.py                    # all four, into benchmarks/figures/viewer/
    python benchmarks/screenshots.py --only dam_break_2d --keep /tmp/shots

Each entry runs its `mpmlab` command in a fresh run directory, renders that run's ``recording.rrd``
with ``rerun --screenshot-to`` (2560 x 1600 pixels, a 1280 x 800 window at 2x) and stores it scaled
to 1280 x 800 as ``benchmarks/figures/viewer/<name>.png``; ``screenshots.json`` beside them records the
commands, the rerun version and the time taken. Needs a display: without ``$DISPLAY`` an Xvfb is
started (``apt-get install xvfb mesa-vulkan-drivers``, as ``.ci/run`` does; software Vulkan is enough).
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _harness as H  # noqa: E402

ROOT = H.ROOT
OUT = H.FIGURES / "viewer"
WINDOW = "1280x800"

#: name -> (what it shows, the mpmlab arguments)
SHOTS = {
    "default": ("the default experiment, `mpmlab` (NCLaw's jelly cube thrown into a box)", []),
    "dam_break_2d": ("a 2D dam break coloured by speed",
                     ["scene=dam_break_2d", "scene.resolution=tiny", "output.color_by=speed"]),
    "multi_material": ("a multi-material scene: a jelly ball dropped into a water pool",
                       ["scene=jelly_pool_drop", "scene.resolution=tiny"]),
    "inverse_fit": ("an inverse fit: the initial velocity of a dam break from every particle's track",
                    ["task=inverse", "experiment=jaxmpm_velocity_constant", "scene.resolution=tiny",
                     "task.supervision=lagrangian_full", "task.epochs=60"]),
}


def _mpmlab() -> list[str]:
    exe = shutil.which("mpmlab")
    return [exe] if exe else [sys.executable, "-m", "mpmlab"]


def _rerun() -> str:
    here = Path(sys.executable).parent / "rerun"
    exe = str(here) if here.exists() else shutil.which("rerun")
    if exe is None:
        sys.exit("screenshots: the rerun CLI (pip install rerun-sdk) is not on PATH")
    return exe


def start_display(runtime_dir: Path) -> tuple[subprocess.Popen | None, dict]:
    """An environment with a display: ``$DISPLAY`` if set, else a fresh Xvfb (stopped by the caller).
    A log level (``RUST_LOG``) would show the viewer's start-up warnings as toasts over the views."""
    env = {k: v for k, v in os.environ.items() if k not in ("RUST_LOG", "WAYLAND_DISPLAY")}
    if not env.get("XDG_RUNTIME_DIR"):
        runtime_dir.mkdir(mode=0o700, parents=True, exist_ok=True)
        env["XDG_RUNTIME_DIR"] = str(runtime_dir)
    if os.environ.get("DISPLAY"):
        return None, env
    exe = shutil.which("Xvfb")
    if exe is None:
        sys.exit("screenshots: no $DISPLAY and no Xvfb (apt-get install xvfb mesa-vulkan-drivers)")
    r, w = os.pipe()
    # a screen much larger than the window: the pointer (at its centre) hovers nothing;
    # -extension Composite: the viewer's window stays opaque
    proc = subprocess.Popen([exe, "-displayfd", str(w), "-screen", "0", "5200x3300x24", "-extension", "Composite",
                             "-nolisten", "tcp"], pass_fds=(w,), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    os.close(w)
    with os.fdopen(r) as f:
        num = f.readline().strip()
    if not num:
        proc.kill()
        sys.exit("screenshots: Xvfb did not start")
    env["DISPLAY"] = f":{num}"
    return proc, env


def render(rrd: Path, png: Path, env: dict, timeout: float = 300) -> None:
    log = png.with_suffix(".log")
    with open(log, "wb") as f:
        rc = subprocess.run([_rerun(), "--window-size", WINDOW, "--screenshot-to", str(png), str(rrd)], env=env,
                            stdout=f, stderr=subprocess.STDOUT, timeout=timeout).returncode
    if rc != 0 or not png.exists():
        sys.exit(f"screenshots: the viewer did not render {rrd} (exit {rc}); see {log}")


def shrink(src: Path, dst: Path) -> None:
    """2560 x 1600 -> 1280 x 800 (the window's own size), written atomically."""
    from PIL import Image

    img = Image.open(src).convert("RGB")
    w, h = WINDOW.split("x")
    img = img.resize((int(w), int(h)), Image.LANCZOS)
    tmp = dst.with_name(f".{dst.name}.tmp")
    img.save(tmp, format="PNG", optimize=True)
    os.replace(tmp, dst)


def main(argv=None) -> int:
    ap = H.parser(__doc__.splitlines()[0])
    ap.add_argument("--only", nargs="*", choices=sorted(SHOTS), help="make only these")
    ap.add_argument("--out", type=Path, default=OUT, help=f"where the PNGs go (default {OUT.relative_to(ROOT)})")
    ap.add_argument("--keep", type=Path, help="keep the runs (recordings, full-size screenshots) here")
    args = ap.parse_args(argv)
    names = args.only or list(SHOTS)
    args.out.mkdir(parents=True, exist_ok=True)
    work = args.keep or Path(tempfile.mkdtemp(prefix="mpmlab-shots-"))
    work.mkdir(parents=True, exist_ok=True)
    manifest_path = args.out / "screenshots.json"
    manifest = H.read_json(manifest_path, {})
    proc, env = start_display(work / "xdg")
    import rerun

    try:
        for name in names:
            what, overrides = SHOTS[name]
            run = work / name
            if run.exists():
                shutil.rmtree(run)
            t0 = time.perf_counter()
            cmd = _mpmlab() + overrides + [f"hydra.run.dir={run}"]
            p = subprocess.run(cmd, cwd=work, capture_output=True, text=True, env={**os.environ, "MPLBACKEND": "Agg"})
            if p.returncode != 0:
                sys.exit(f"screenshots: `{' '.join(cmd)}` failed:\n{p.stderr[-2000:]}")
            t_run = time.perf_counter() - t0
            full = work / f"{name}.full.png"
            render(run / "recording.rrd", full, env)
            shrink(full, args.out / f"{name}.png")
            manifest[name] = {"shows": what, "command": " ".join(["mpmlab", *overrides]),
                              "run_s": round(t_run, 1), "render_s": round(time.perf_counter() - t0 - t_run, 1),
                              "rerun": rerun.__version__, "window": WINDOW}
            dst = args.out / f"{name}.png"
            print(f"screenshots: {name}: {manifest[name]['command']} ({t_run:.0f} s) -> "
                  f"{dst.relative_to(ROOT) if dst.is_relative_to(ROOT) else dst}", flush=True)
    finally:
        if proc is not None:
            proc.terminate()
            proc.wait(10)
        if args.keep is None:
            shutil.rmtree(work, ignore_errors=True)
    H.write_json(manifest_path, {k: manifest[k] for k in sorted(manifest)}, indent=2, newline=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
