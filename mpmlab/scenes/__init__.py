"""Ready-made scenes (benchmarks, validation cases): plain functions returning a ``Scene``."""
