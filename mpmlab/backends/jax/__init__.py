"""JAX backend: pure jitted steps, lax.scan rollouts, differentiable end to end."""
from __future__ import annotations

from ...core.interfaces import AbstractBackend


class JaxBackend(AbstractBackend):
    name = "jax"
    #: the differentiable workflows' seam to this backend's arrays (mpmlab.core.autodiff)
    autodiff_adapter = "mpmlab.backends.jax.adapter:JaxAdapter"
    #: the options ``build`` takes beyond the precision (task=simulate refuses ``backend.device`` here)
    build_options = ("check_every",)
    device_note = "JAX picks its device itself (JAX_PLATFORMS=cpu|cuda)."

    def build(self, scene, transfer, precision="fp32", **options):
        from .stepper import JaxStepper

        return JaxStepper(scene, transfer, precision, **options)
