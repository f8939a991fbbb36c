"""A transfer whose choices the kernels cannot carry out is refused when the stepper is built, in one
line naming the scheme (review-interfaces.md 5.4: affine=None, force="mls", grad_v="affine" raised a
KeyError while tracing on JAX and silently froze F on Warp)."""
from dataclasses import dataclass
from typing import ClassVar

import pytest

import mpmlab
from mpmlab.core.errors import ConfigError
from mpmlab.core.interfaces import AbstractTransfer

SCENE = mpmlab.Scene(dim=2, dx=0.1, domain=([0, 0], [1, 1]), dt=1e-3, bodies=[
    mpmlab.Body(shape={"kind": "box", "lo": [0.3, 0.3], "hi": [0.5, 0.5]}, material="fixed_corotated")])


def transfer(affine=None, force="gradient", grad_v="gradient", ratio=None):
    @dataclass(frozen=True)
    class Plugin(AbstractTransfer):
        name: ClassVar[str] = "plugin_transfer"
        implementations: ClassVar[dict] = {"jax": "x", "warp": "x"}
        flip_ratio: float | None = ratio
    Plugin.affine, Plugin.force, Plugin.grad_v = affine, force, grad_v
    return Plugin()


@pytest.mark.parametrize("backend", ["jax", "warp"])
@pytest.mark.parametrize("kw, message", [
    ({"affine": None, "force": "mls", "grad_v": "affine"}, "grad_v = 'affine' feeds the affine field C"),
    ({"affine": "velocity_gradient", "force": "mls"}, "force = 'mls' is the MLS-MPM force of an APIC"),
    ({"affine": "polypic"}, "affine = 'polypic' is not one of"),
    ({"ratio": 1.5}, "flip_ratio = 1.5 must be"),
])
def test_inconsistent_transfer_is_refused_at_build(backend, kw, message):
    with pytest.raises(ConfigError, match=f"transfer 'plugin_transfer'.*{message}"):
        mpmlab.build_stepper(SCENE, backend, transfer(**kw))


def test_builtin_transfers_pass_the_check():
    for name in ("pic", "flip", "apic", "mls", "tpic"):
        mpmlab.make_transfer(name).check()
