"""What every check of the kit shares: resolving a law given by name, class or instance; its test
parameters and options; the error measure; and the one-line failure."""
from __future__ import annotations

import dataclasses
from typing import Any, Mapping

import numpy as np

#: the density of every kit scene and of the parameter defaults that depend on it (a fluid's rest density)
DENSITY = 1000.0


class ConformanceError(AssertionError):
    """A failed conformance check: one line naming the law, the backend, the quantity and the error
    against its tolerance. An ``AssertionError``, so pytest reports it as a plain failure."""


def fail(msg: str):
    raise ConformanceError(" ".join(str(msg).split()))


class Report:
    """The report of a group of checks (``check_law``, ``check_transfer``): ``run(label, check, ...)``
    runs one check and keeps what it measured, or its one-line failure; a plugin that cannot even run a
    check fails it, saying why. ``finish`` raises the failures as one ``ConformanceError``."""

    def __init__(self, kind: str, name: str):
        import time

        self._time = time.perf_counter
        self.kind, self.name = kind, name
        self.data = {kind: name, "checks": {}, "failures": [], "seconds": {}}

    def run(self, label: str, fn, *a, **kw) -> None:
        t0 = self._time()
        try:
            self.data["checks"][label] = fn(*a, **kw)
        except AssertionError as e:
            self.data["checks"][label] = None
            self.data["failures"].append(str(e))
        except Exception as e:  # noqa: BLE001 -- the plugin's failure: say which check and why
            self.data["checks"][label] = None
            first = str(e).splitlines()[0] if str(e) else ""
            self.data["failures"].append(f"{self.kind} '{self.name}' {label}: {type(e).__name__}: {first}")
        self.data["seconds"][label] = round(self._time() - t0, 3)

    def finish(self, raise_on_failure: bool) -> dict:
        fails = self.data["failures"]
        if fails and raise_on_failure:
            raise ConformanceError(f"{self.kind} '{self.name}': {len(fails)} of {len(self.data['checks'])} checks "
                                   f"failed: " + " | ".join(fails))
        return self.data


def law_class(law) -> type:
    """The law class of a registered name, a class or an instance."""
    if isinstance(law, str):
        from ..core import registry

        return registry.laws.get(law)
    return law if isinstance(law, type) else type(law)


def law_instance(law):
    """The law instance the kit tests: an instance as given; a name or class built from its
    ``test_options`` (``Law.from_config``)."""
    if isinstance(law, str) or isinstance(law, type):
        cls = law_class(law)
        return cls.from_config(dict(cls.test_options), f"mpmlab.testing: law '{cls.name}' test_options")
    return law


def law_name(law) -> str:
    return law_class(law).name


def params_of(law) -> dict[str, float]:
    """The law's ``test_params`` (parameters that make it deform, and yield if plastic, within 50 steps
    of the kit's scenes), as a plain dict. Laws that declare none are tested at their defaults."""
    return dict(law_class(law).test_params)


def options_of(law) -> dict[str, Any]:
    """The material options (``Body.options``) a law instance is built from: an instance's own fields,
    or ``test_options`` for a name or class."""
    if isinstance(law, str) or isinstance(law, type):
        return dict(law_class(law).test_options)
    if dataclasses.is_dataclass(law):
        return {f.name: getattr(law, f.name) for f in dataclasses.fields(law)}
    return {}


def resolve_params(law, params=None) -> dict[str, float]:
    """Parameters by name, every declared one filled in (``AbstractConstitutiveLaw.resolve_params``).

    ``params``: None -- the law's ``test_params``; ``"defaults"`` -- the declared defaults (the
    ``test_params`` value only where a parameter has no default); a mapping -- those values."""
    cls = law_class(law)
    if params is None:
        given = params_of(cls)
    elif isinstance(params, str):
        if params != "defaults":
            raise ValueError(f"params={params!r}: use None (test_params), 'defaults' or a mapping.")
        given = {p.name: cls.test_params[p.name] for p in cls.params
                 if p.default is None and p.name in cls.test_params}
    else:
        given = dict(params)
    return cls.resolve_params(given, f"mpmlab.testing: law '{cls.name}'", density=DENSITY)


def param_row(law, prm: Mapping[str, float]) -> np.ndarray:
    """Parameters in declared order (the steppers' per-particle layout)."""
    return np.array([float(prm[k]) for k in law_class(law).param_names()])


def rel_err(a, b) -> float:
    """max |a - b| / max |b| (the denominator floored at 1e-300)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    return float(np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-300))


def ensure_registered(law) -> str:
    """The registry name of ``law``; a class (or instance of one) that is not registered is registered
    under its ``name`` (provenance ``mpmlab.testing``) so scenes can use it. A name taken by another
    class is refused."""
    from ..core import registry

    if isinstance(law, str):
        registry.laws.get(law)
        return law
    cls = law_class(law)
    if cls.name in registry.laws.names():
        held = registry.laws.get(cls.name)
        # a law whose configuration picks its class (phase_change's pair classes) subclasses the registered one
        if held is not cls and not issubclass(cls, held):
            fail(f"law class {cls.__module__}.{cls.__qualname__} is named '{cls.name}', but the registry holds "
                 f"another law of that name; give the class its own name.")
    else:
        registry.laws.register(cls.name, cls, provenance="mpmlab.testing")
    return cls.name
