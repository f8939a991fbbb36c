"""Warp backend: kernels generated per scene from closures over the laws' ``@wp.func``s."""

import os
import sys
import tempfile

from ...core.errors import ConfigError
from ...core.interfaces import AbstractBackend

def __getattr__(name):
    # the public law-author API, imported on first use (importing this package must not import warp)
    if name == "law_types":
        from .law_structs import law_types

        return law_types
    raise AttributeError(name)


#: What Warp's native library prints (to the process's stderr, from C) when ``libcuda`` is absent: on
#: a CPU machine that is no news, so ``init_warp`` drops it; a run that asks for a CUDA device is
#: refused by ``check_device`` with a sentence that says so.
DRIVER_MISSING = "Could not find or load the NVIDIA CUDA driver"

#: Set by ``init_warp`` when it dropped the driver line (``check_device`` adds it to its message).
driver_missing = False


def _initialised(wp) -> bool:
    ctx = getattr(getattr(wp, "_src", None), "context", None)
    return getattr(ctx, "runtime", None) is not None


def init_warp():
    """``wp.init()`` with mpmlab's quiet settings (``types.py``) and without the "could not find the
    NVIDIA CUDA driver" line on a CPU machine; Warp's other init output (e.g. a too old driver) is
    passed through. Returns the ``warp`` module."""
    global driver_missing
    import warp as wp

    from . import types  # noqa: F401 - sets wp.config.log_level / quiet before the runtime starts

    if _initialised(wp):
        return wp
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError, AttributeError):  # no usable fd 2 (embedded interpreter): plain init
        wp.init()
        return wp
    with tempfile.TemporaryFile() as tmp:
        try:
            os.dup2(tmp.fileno(), 2)   # the message comes from C (fprintf(stderr)), below sys.stderr
            wp.init()
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            tmp.seek(0)
            text = tmp.read()
            lines = text.decode("utf-8", "replace").splitlines(keepends=True)
            kept = [line for line in lines if DRIVER_MISSING not in line]
            driver_missing = len(kept) < len(lines)
            if kept:
                sys.stderr.write("".join(kept))
                sys.stderr.flush()
    return wp


def warp_devices() -> list[str]:
    """Aliases of the devices Warp sees on this machine (``cpu``, ``cuda:0``, ...)."""
    wp = init_warp()
    return [str(d.alias) for d in wp.get_devices()]


def check_device(device: str, key: str = "backend.device") -> str:
    """Refuse a Warp device this machine does not have (``ConfigError``, one sentence naming ``key``)."""
    wp = init_warp()
    devices = warp_devices()
    ok = True
    try:
        wp.get_device(device)
    except (ValueError, RuntimeError, TypeError):
        ok = False
    if ok:
        return device
    if device.startswith("cuda") and not any(d.startswith("cuda") for d in devices):
        why = "; no NVIDIA CUDA driver found" if driver_missing else ""
        raise ConfigError(f"{key}='{device}' but Warp sees no CUDA device on this machine (devices: "
                          f"{', '.join(devices)}{why}); use {key}=cpu or run on a GPU machine.")
    raise ConfigError(f"{key}='{device}' is not a device Warp sees on this machine (devices: "
                      f"{', '.join(devices)}); use one of those.")


class WarpBackend(AbstractBackend):
    name = "warp"
    #: the differentiable workflows' seam to this backend's arrays (mpmlab.core.autodiff)
    autodiff_adapter = "mpmlab.backends.warp.adapter:WarpAdapter"
    #: the options ``build`` takes beyond the precision
    build_options = ("check_every", "device", "shape")

    @staticmethod
    def debug_output():
        """``debug=true``: show Warp's module compile/load lines (quiet by default, ``types.py``)."""
        import warp

        warp.config.log_level = warp.LOG_INFO

    def build(self, scene, transfer, precision="fp32", **options):
        from .stepper import WarpStepper

        return WarpStepper(scene, transfer, precision, **options)
