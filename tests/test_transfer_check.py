"""A transfer scheme whose pieces are inconsistent is refused when the stepper is built, in one line
naming the scheme and what is wrong -- its declarations (AbstractTransfer.check), its JAX functions
against them (backends/jax/transfers.py, a shape-only trace) and its Warp functions (built then) --
not a KeyError while tracing or a silently absent term (review-interfaces.md 5.4)."""
from dataclasses import dataclass
from types import SimpleNamespace
from typing import ClassVar

import pytest

import mpmlab
from mpmlab.core.errors import ConfigError
from mpmlab.core.interfaces import AbstractTransfer, G2PResult, P2GTerms
from mpmlab.transfers import BUILTIN
from mpmlab.transfers.apic import jax as apic_jax

SCENE = mpmlab.Scene(dim=2, dx=0.1, domain=([0, 0], [1, 1]), dt=1e-3, bodies=[
    mpmlab.Body(shape={"kind": "box", "lo": [0.3, 0.3], "hi": [0.5, 0.5]}, material="fixed_corotated")])

APIC = {"jax": "mpmlab.transfers.apic.jax:make", "warp": "mpmlab.transfers.apic.warp:make"}


def transfer(impl=None, **decl):
    """An APIC-like plugin scheme with the given declarations and implementations."""
    @dataclass(frozen=True)
    class Plugin(AbstractTransfer):
        name: ClassVar[str] = "plugin_transfer"
        implementations: ClassVar[dict] = impl or APIC
        carries_C: ClassVar[bool] = True
        momentum_terms: ClassVar[frozenset] = frozenset({"affine", "gradient"})
        moments: ClassVar[frozenset] = frozenset({"first", "gradient"})
    for k, v in decl.items():
        setattr(Plugin, k, v)
    return Plugin()


@pytest.mark.parametrize("backend", ["jax", "warp"])
@pytest.mark.parametrize("decl, message", [
    ({"moments": frozenset({"polypic"})}, r"moments has \['polypic'\], not among"),
    ({"force_terms": frozenset({"gradient"})}, "force_terms = .* needs split_force = True"),
    ({"momentum_terms": frozenset()}, "declares no force term"),
])
def test_inconsistent_declarations_are_refused_at_build(backend, decl, message):
    with pytest.raises(ConfigError, match=f"transfer 'plugin_transfer' .*{message}"):
        mpmlab.build_stepper(SCENE, backend, transfer(**decl))


# JAX functions that do not fit the (APIC) declarations
def _p2g_without_gradient(p):
    t = apic_jax.p2g(p)
    return P2GTerms(q=t.q, A=t.A)


def _g2p_without_C(g):
    return G2PResult(v=g.v_pic, C=None, grad_v=g.grad)


def _g2p_reading_v_old(g):
    return G2PResult(v=g.v_old + 0.0, C=g.first, grad_v=g.grad)      # v_old is None: no split_force


def _make(p2g=apic_jax.p2g, g2p=apic_jax.g2p):
    return lambda transfer, dim: SimpleNamespace(p2g=p2g, g2p=g2p)


no_gradient = _make(p2g=_p2g_without_gradient)
no_C = _make(g2p=_g2p_without_C)
v_old = _make(g2p=_g2p_reading_v_old)


def no_g2p(transfer, dim):
    return SimpleNamespace(p2g=apic_jax.p2g)


@pytest.mark.parametrize("which, message", [
    ("no_gradient", "JAX p2g returns no G, but the scheme declares it"),
    ("no_C", "JAX g2p returns no C, but the scheme declares carries_C = True"),
    ("v_old", r"its JAX g2p fails on the declared moments \['first', 'gradient'\]: TypeError"),
    ("no_g2p", r"its JAX factory gives no g2p\(...\)"),
])
def test_jax_functions_that_do_not_fit_the_declarations_are_refused_at_build(which, message):
    impl = {"jax": f"tests.test_transfer_check:{which}"}
    with pytest.raises(ConfigError, match=f"transfer 'plugin_transfer' .*{message}"):
        mpmlab.build_stepper(SCENE, "jax", transfer(impl))


def test_jax_p2g_returning_an_undeclared_term_is_refused():
    with pytest.raises(ConfigError, match="JAX p2g returns A, which the scheme does not declare"):
        mpmlab.build_stepper(SCENE, "jax", transfer(momentum_terms=frozenset({"gradient"})))


@pytest.mark.parametrize("factory, message", [
    ("make", r"its Warp functions do not build against its declarations"),
    ("make_without_force", r"its Warp factory gives no p2g_force"),
    ("make_without_dinv", r"its Warp p2g_momentum has no Dinv argument .*add `Dinv: mat` .* before `tp`"),
])
def test_warp_functions_that_do_not_fit_are_refused_at_build(factory, message):
    decl = {"split_force": True, "force_terms": frozenset({"gradient"})} if factory == "make_without_force" else {}
    impl = {"warp": f"tests._warp_wrong_transfer:{factory}"}
    with pytest.raises(ConfigError, match=f"transfer 'plugin_transfer' .*{message}"):
        mpmlab.build_stepper(SCENE, "warp", transfer(impl, **decl))


def test_builtin_transfers_pass_the_check():
    for name, cls in BUILTIN.items():
        assert mpmlab.make_transfer(name).__class__ is cls
        cls().check()
