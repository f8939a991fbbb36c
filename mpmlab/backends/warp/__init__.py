"""Warp backend: kernels generated per scene from closures over the laws' ``@wp.func``s."""

from ...core.interfaces import AbstractBackend


class WarpBackend(AbstractBackend):
    name = "warp"

    def build(self, scene, transfer, precision="fp32", **options):
        from .stepper import WarpStepper

        return WarpStepper(scene, transfer, precision, **options)
