"""Constitutive laws: one folder per law.

Each folder holds ``__init__.py`` (the ``Law`` class: parameters with units and ranges, state fields,
wave speed), ``reference.py`` (NumPy float64, the conformance oracle), ``jax.py`` (``make(dim)``) and
``warp.py`` (``make(dim, precision)`` returning ``@wp.func``s). All four expose the same two
functions, ``kirchhoff(state, params)`` and ``update(state, grad_v, dt, params)``: see
``mpmlab.core.interfaces.AbstractConstitutiveLaw``. To add a law, copy ``fixed_corotated/``.
"""
