"""Post-processing of particle states (NumPy only, no backend): :mod:`mpmlab.analysis.runout` measures
the run-out, the height at the wall and the deposit profile of a granular flow, and decides when a
deposit has come to rest."""
