"""Registries: built-ins by name, clear errors for unknown names and missing backend implementations."""
import pytest

import mpmlab
from mpmlab.core import registry
from mpmlab.core.interfaces import AbstractConstitutiveLaw, ParamSpec, StateField


def test_builtins_registered():
    assert {"fixed_corotated", "hencky_drucker_prager", "hencky_von_mises", "weakly_compressible",
            "newtonian_fluid", "drucker_prager_jaumann"} <= set(registry.laws.names())
    assert set(registry.transfers.names()) >= {"pic", "flip", "apic", "mls", "tpic"}
    assert set(registry.backends.names()) >= {"jax", "warp"}


def test_unknown_name_lists_known_ones():
    with pytest.raises(mpmlab.UnknownPluginError) as err:
        registry.laws.get("neo_hooke")
    assert "fixed_corotated" in str(err.value) and "neo_hooke" in str(err.value)
    with pytest.raises(mpmlab.UnknownPluginError, match="known transfers"):
        mpmlab.make_transfer("sph")


def test_importing_mpmlab_imports_no_backend():
    import subprocess
    import sys

    code = "import sys, mpmlab; mpmlab.registry.laws.get('fixed_corotated'); print('jax' in sys.modules, 'warp' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out == ["False", "False"]


class _JaxOnlyLaw(AbstractConstitutiveLaw):
    name = "jax_only_test_law"
    params = (ParamSpec("E", "Pa", 1.0, low=0.0),)
    state = (StateField("F", ("D", "D"), "identity"),)
    implementations = {"jax": "mpmlab.laws.fixed_corotated.jax:make"}

    @classmethod
    def wave_speed(cls, params, density):
        return 1.0


def test_missing_backend_implementation_is_refused_before_running():
    registry.laws.register("jax_only_test_law", _JaxOnlyLaw, provenance="tests")
    scene = mpmlab.Scene(dim=2, dx=0.1, domain=([0, 0], [1, 1]), bodies=[
        mpmlab.Body(shape={"kind": "box", "lo": [0.3, 0.3], "hi": [0.5, 0.5]}, material="jax_only_test_law")], dt=1e-3)
    with pytest.raises(mpmlab.MissingImplementationError, match="no implementation for backend 'warp'"):
        mpmlab.build_stepper(scene, "warp", "pic")
    with pytest.raises(mpmlab.UnknownPluginError, match="known backends"):
        mpmlab.build_stepper(scene, "cuda_magic", "pic")
