"""The inverse workflow's adapter for the reduced model (``mpmlab.core.autodiff``): the JAX adapter, with
the rollout observed through ``ReducedStepper.observe`` instead of the full-order JAX path, so
``mpmlab.inverse.Fit`` fits a problem's unknowns in the reduced space (issue 16, item 7)."""
from __future__ import annotations

from ..backends.jax.adapter import JaxAdapter
from ..core.errors import GradientError


class ReducedJaxAdapter(JaxAdapter):
    def observe(self, stepper, controls, observation, steps, segment=None):
        return stepper.observe(controls, observation, steps, segment, health=True)

    def tracking_value_and_grad(self, stepper, controls, observations, weights, segment=None, grad=True):
        raise GradientError("the reduced model has no teacher-forced tracking loss (NCLaw's); fit observations "
                            "with Fit (observe) instead.")

    def locate_nan_gradient(self, stepper, controls, observation, steps, data_loss, segment=None):
        raise GradientError("the gradient through the reduced rollout is not finite; the step-by-step replay that "
                            "locates it exists for the full-order model only: fit there to find the step.")
