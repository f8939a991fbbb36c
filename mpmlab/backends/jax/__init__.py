"""JAX backend: pure jitted steps, lax.scan rollouts, differentiable end to end."""
from __future__ import annotations

from ...core.interfaces import AbstractBackend


class JaxBackend(AbstractBackend):
    name = "jax"
    #: the differentiable workflows' seam to this backend's arrays (mpmlab.core.autodiff)
    autodiff_adapter = "mpmlab.backends.jax.adapter:JaxAdapter"
    #: the options ``build`` takes beyond the precision (task=simulate refuses ``backend.device`` here);
    #: ``devices``: shard one simulation's particles over that many devices (backends/jax/sharding.py)
    build_options = ("check_every", "devices")
    device_note = "JAX picks its device itself (JAX_PLATFORMS=cpu|cuda)."

    @staticmethod
    def check_devices(devices, group_sizes=()) -> int:
        """``devices`` if this machine has that many JAX devices, else ``ConfigError`` (one line);
        ``group_sizes``: the particles per material group (on forced host devices they size XLA's CPU
        thread pool, ``sharding.cpu_threads_needed``)."""
        from .sharding import check_devices

        return check_devices(devices, group_sizes)

    def build(self, scene, transfer, precision="fp32", devices=None, **options):
        if devices is not None and devices != 1:
            from .sharding import ShardedJaxStepper

            return ShardedJaxStepper(scene, transfer, precision, devices=devices, **options)
        from .stepper import JaxStepper

        return JaxStepper(scene, transfer, precision, **options)
