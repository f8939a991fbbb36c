"""The Python API's entry point: build a stepper for a scene on a backend, roll it out."""
from __future__ import annotations

from typing import Any

import numpy as np

from .core import registry
from .core.errors import ConfigError, MissingImplementationError
from .core.interfaces import AbstractTransfer
from .core.scene import Scene
from .transfers import make_transfer


def check_capabilities(scene: Scene, backend: str, transfer: AbstractTransfer) -> None:
    """Fail before anything runs if a law, transfer or boundary has no implementation for ``backend``."""
    registry.backends.get(backend)  # unknown backend -> UnknownPluginError listing the known ones
    for law in scene.body_laws():    # the configured instances (their class may follow the options)
        if backend not in law.implementations:
            raise MissingImplementationError("law", law.name, backend, list(law.implementations))
    if backend not in transfer.implementations:
        raise MissingImplementationError("transfer", transfer.name, backend, list(transfer.implementations))
    for b in scene.boundaries:
        if backend not in b.implementations:
            raise MissingImplementationError("boundary", b.name, backend, list(b.implementations))


def check_representable(scene: Scene, precision: str) -> None:
    """Refuse, before anything runs, a material parameter or shared weight that ``precision`` cannot hold
    (fp32: magnitudes above 3.4e38 become inf, and the first step returns NaN far from the cause)."""
    if precision != "fp32":
        return
    big = float(np.finfo(np.float32).max)
    for g in scene.particles().groups:
        prm = np.asarray(g.params, float)                       # [n, P], the law's declared order
        bad = np.argwhere(np.abs(prm) > big)
        if len(bad):
            i, j = bad[0]
            raise ConfigError(f"law '{g.law.name}': parameter {g.law.param_names()[j]} = {prm[i, j]:.3g} exceeds fp32's "
                              f"largest value ({big:.3g}); use precision=fp64 or rescale the units.")
        for name, w in (g.weights or {}).items():
            w = np.asarray(w, float)
            if w.size and np.max(np.abs(w)) > big:
                raise ConfigError(f"law '{g.law.name}': weight array '{name}' holds {np.max(np.abs(w)):.3g}, beyond "
                                  f"fp32's largest value ({big:.3g}); use precision=fp64.")


def check_devices_option(backend: str, devices) -> None:
    """Refuse ``devices`` > 1 on a backend that does not shard one simulation (``ConfigError``, one line)."""
    if devices is None or devices == 1:
        return
    if "devices" not in getattr(registry.backends.get(backend), "build_options", ()):
        takes = [n for n in registry.backends.names() if "devices" in getattr(registry.backends.get(n), "build_options", ())]
        raise ConfigError(f"backend.devices = {devices}: the {backend} backend does not shard one simulation over "
                          f"several devices; use backend={'|'.join(takes) or 'jax'} backend.devices={devices}, or "
                          f"backend.devices=1.")


def build_stepper(scene: Scene, backend: str = "jax", transfer: Any = "mls", precision: str = "fp32", **options):
    """Build a compiled stepper.

    Args:
        scene: the ``Scene``.
        backend: registered backend name (``jax`` or ``warp``).
        transfer: a registered transfer name (``pic``, ``flip``, ``apic``, ``mls``, ``tpic``) or a transfer object.
        precision: ``fp32`` or ``fp64``.
        **options: backend options (``check_every``: guard cadence in steps; JAX ``devices``: shard the
            particles of one simulation over that many devices, ``mpmlab.backends.jax.sharding``).
    """
    if isinstance(transfer, str):
        transfer = make_transfer(transfer)
    if precision not in ("fp32", "fp64"):
        raise ConfigError(f"precision '{precision}' unknown; use 'fp32' or 'fp64'.")
    transfer = transfer.for_scene(scene)     # e.g. FLIP's pic_time resolved at the scene's dt
    transfer.check()     # an inconsistent (plugin) transfer is refused here, not during tracing
    check_capabilities(scene, backend, transfer)
    check_representable(scene, precision)
    if "devices" in options:
        check_devices_option(backend, options["devices"])
        if options["devices"] in (None, 1) and "devices" not in getattr(registry.backends.get(backend), "build_options", ()):
            options.pop("devices")      # one device is every backend's default
    return registry.backends.get(backend)().build(scene, transfer, precision, **options)


def simulate(scene: Scene, steps: int, every: int | None = None, backend: str = "jax", transfer: Any = "mls",
             precision: str = "fp32", fields: tuple[str, ...] = (), **options):
    """Build and roll out in one call, keeping every ``every``-th step (default: the scene's
    ``substeps`` per frame); returns a ``Trajectory``."""
    stepper = build_stepper(scene, backend, transfer, precision, **options)
    return stepper.rollout(steps=steps, every=every, fields=fields)
