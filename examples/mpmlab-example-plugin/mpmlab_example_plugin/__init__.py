"""Example mpmlab plugin: a compressible Neo-Hookean law (``neo_hookean``) and its configs."""
__version__ = "0.1.0"
