"""NCLaw (Ma et al., ICML 2023) workflow around the ``nclaw`` law (:mod:`mpmlab.laws.nclaw`).

- :mod:`mpmlab.nclaw.data`: the teacher-forcing datasets that ``experiment=nclaw_datasets`` writes
  (x, v, C, F at every step) and ``load_dataset`` to read and check one.
- :mod:`mpmlab.nclaw.scenes`: the evaluation scene set of NCLaw Sec. 4 (reconstruction, time,
  velocity, geometry, incline, contact, pool) as Hydra overrides, and the paper's position metric.
"""
