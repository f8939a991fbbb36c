"""Abstract interfaces of mpmlab's plugin kinds.

Concrete classes are final (diffrax pattern): subclass an ``Abstract*`` class, never a concrete one.
Each plugin declares its ``implementations``: backend name -> ``"module:attr"`` of the backend-side
factory, imported only when a stepper for that backend is built. A missing entry is a visible gap in
the capability table (``mpmlab.capabilities.capabilities()``), never a silent fallback.
"""
from __future__ import annotations

import math
from abc import ABC, abstractmethod
import dataclasses
from dataclasses import dataclass
from typing import Any, ClassVar, Mapping, NamedTuple, Protocol, runtime_checkable

import numpy as np

from .errors import ConfigError, InvalidParameterError, MissingImplementationError
from .registry import load_object


@dataclass(frozen=True)
class StateField:
    """One per-particle law state field, declared by the law (like Newton's custom attributes).

    ``shape`` is per particle: ``()`` a scalar, ``("D",)`` a vector, ``("D", "D")`` a matrix; ``"D"``
    stands for the scene's dimension and integers are fixed sizes (``(3,)``, ``("D", 4)``). ``init`` is
    the value every particle starts from: a number (filled) or ``"identity"`` (square matrices).
    ``check``: what the divergence guard tests besides finiteness: ``"positive"`` (a scalar > 0, e.g.
    J) or ``"positive_det"`` (a matrix with det > 0, e.g. F); reported as field ``J``.

    The steppers, the gradient paths, ``trajectory.h5``, ``output.fields``/``output.color_by`` and the
    Warp structs are all built from these declarations: a law adds a field without editing mpmlab.
    """

    name: str
    shape: tuple = ()
    init: float | str = 0.0
    unit: str = "-"
    doc: str = ""
    check: str | None = None

    def __post_init__(self):
        if not self.name.isidentifier() or self.name in ("x", "v", "C", "t", "tau"):
            raise ConfigError(f"state field '{self.name}': the name must be a Python identifier other than "
                              f"x, v, C, t and tau (those are the stepper's own).")
        if any(not (d == "D" or (isinstance(d, int) and d > 0)) for d in self.shape) or len(self.shape) > 2:
            raise ConfigError(f"state field '{self.name}': shape {self.shape!r} must be (), (n,) or (n, m) with "
                              f"each n a positive int or 'D' (the dimension).")
        if self.init == "identity" and (len(self.shape) != 2 or self.shape[0] != self.shape[1]):
            raise ConfigError(f"state field '{self.name}': init 'identity' needs a square matrix shape.")
        if self.check not in (None, "positive", "positive_det"):
            raise ConfigError(f"state field '{self.name}': check {self.check!r} must be None, 'positive' or "
                              f"'positive_det'.")

    def resolved_shape(self, dim: int) -> tuple[int, ...]:
        return tuple(dim if d == "D" else int(d) for d in self.shape)

    def size(self, dim: int) -> int:
        """Scalars per particle."""
        return int(np.prod(self.resolved_shape(dim), dtype=int))

    def initial(self, n: int, dim: int) -> np.ndarray:
        shape = self.resolved_shape(dim)
        if self.init == "identity":
            return np.repeat(np.eye(shape[0])[None], n, axis=0)
        return np.full((n,) + shape, float(self.init))


@dataclass(frozen=True)
class ParamSpec:
    """One physical parameter: name, unit, default and valid range (bounds may be open)."""

    name: str
    unit: str
    default: float | None
    low: float = -math.inf
    high: float = math.inf
    low_open: bool = False
    high_open: bool = False
    doc: str = ""

    def check(self, value: float, where: str) -> float:
        try:
            v = float(value)
        except (TypeError, ValueError):
            raise InvalidParameterError(f"{where}: parameter '{self.name}' must be a number, got {value!r}.") from None
        too_low = v <= self.low if self.low_open else v < self.low
        too_high = v >= self.high if self.high_open else v > self.high
        if not math.isfinite(v) or too_low or too_high:
            lo = "(" if self.low_open else "["
            hi = ")" if self.high_open else "]"
            raise InvalidParameterError(
                f"{where}: {self.doc or self.name} '{self.name}' = {v:g}{'' if self.unit == '-' else ' ' + self.unit} "
                f"is outside its valid range "
                f"{lo}{self.low:g}, {self.high:g}{hi}; set it inside that range."
            )
        return v


class _Pluggable:
    name: ClassVar[str]
    implementations: ClassVar[Mapping[str, str]] = {}

    @classmethod
    def implementation(cls, backend: str, kind: str) -> Any:
        if backend not in cls.implementations:
            raise MissingImplementationError(kind, cls.name, backend, list(cls.implementations))
        return load_object(cls.implementations[backend])


@runtime_checkable
class LawFunctions(Protocol):
    """What a law's backend factory returns, on every backend (``make(law, dim)`` on JAX,
    ``make(law, dim, precision)`` on Warp, and the ``reference`` module itself):

    * ``kirchhoff(state, prm, w) -> tau [D, D]``
    * ``update(state, grad_v [D, D], dt, prm, w) -> state``

    ``state``: the declared fields (JAX/NumPy: a dict of one particle's arrays; Warp: the generated
    ``LawState`` struct); ``prm``: the parameters by name (JAX/NumPy: a mapping of scalars; Warp: the
    generated ``Params`` struct); ``w``: the shared weights (JAX/NumPy: a dict of arrays, un-batched;
    Warp: the generated ``Weights`` struct of ``wp.array``s)."""

    def kirchhoff(self, state, prm, w): ...

    def update(self, state, grad_v, dt, prm, w): ...


class AbstractConstitutiveLaw(_Pluggable, ABC):
    """A material's response: a law *instance*, built from its material config, with two pure
    per-particle functions on every backend (one contract, three spellings):

    * ``kirchhoff(state, params, weights) -> tau``: Kirchhoff stress tau = P F^T = J sigma, for P2G.
    * ``update(state, grad_v, dt, params, weights) -> state``: advance the law state over dt given the
      particle velocity gradient (elastic predictor + return map for hyperelastic laws, NCLaw Alg. 1;
      stress-rate integration for hypo-elastic laws, JAX-MPM Eq. 21).

    What the law declares, and what each backend passes:

    * ``params``: per-particle physical parameters (``ParamSpec``: units, ranges). Law code reads them
      **by name**: ``params["E"]`` on JAX and in the NumPy reference (a mapping name -> scalar per
      particle), ``prm.E`` on Warp (a generated ``wp.struct``). Gradients reach them on both backends.
    * ``weight_shapes(dim)`` / ``initial_weights(dim)``: group-level (shared) arrays, e.g. a network's
      weights, a ``{name: array}`` dict. JAX passes the dict un-batched (``vmap(in_axes=None)``); Warp
      passes a generated ``wp.struct`` of ``wp.array`` members as one kernel argument, whose adjoints
      accumulate over particles. They are ``controls()["law_weights"][group]`` on both backends, with
      memory O(weights), not O(particles x weights).
    * ``state``: the per-particle state fields (``StateField``: name, shape, initial value). Everything
      downstream is built from it: ``initial_state``, the Warp ``LawState`` struct, the stored fields.

    Backend factories (``implementations``: ``{"jax": "pkg.mod:make", "warp": "pkg.mod:make"}``):

    * JAX: ``make(law, dim) -> namespace(kirchhoff, update)`` of plain functions on one particle; the
      stepper vmaps them over the group. ``state`` is a dict of arrays, ``weights`` a dict.
    * Warp: ``make(law, dim, precision) -> namespace(kirchhoff, update)`` of ``@wp.func``s with
      ``(s: LawState, [grad_v: mat, dt: scalar,] prm: Params, w: Weights)``, the types from
      ``mpmlab.backends.warp.law_types(law, dim, precision)``; ``update`` returns a ``LawState``.
    * ``reference``: a NumPy float64 module with the same two functions (``state`` a dict of arrays,
      ``params`` a dict of floats): the conformance oracle of ``mpmlab.testing``.

    A law's configuration (network widths, a weights file, ablation switches) is the instance's
    fields: subclasses are frozen dataclasses, ``material.options`` in the config fills them, two
    bodies may use two instances of one law. Instances compare and hash by class and fields, so a
    backend compiles one kernel per distinct configuration.
    """

    params: ClassVar[tuple[ParamSpec, ...]] = ()
    state: ClassVar[tuple[StateField, ...]]
    #: the declared state's names (derived from ``state``)
    state_fields: ClassVar[tuple[str, ...]] = ()
    plastic: ClassVar[bool] = False
    reference: ClassVar[Any] = None
    #: the smallest stable CFL factor C* measured for this law over the transfers and both backends
    #: (``benchmarks/stress.py --full``), where it is below the library-wide safety margin; ``dt: auto``
    #: then uses at most C*/2 for scenes with this law (``Scene.effective_cfl``). None: no extra limit.
    stable_cfl: ClassVar[float | None] = None
    #: parameters (and options) that make this law deform and, if plastic, yield within 50 steps of
    #: the ``mpmlab.testing`` scenes; the conformance kit takes its test cases from here
    test_params: ClassVar[Mapping[str, float]] = {}
    test_options: ClassVar[Mapping[str, Any]] = {}
    #: the transfers the exhaustive test suites (every law x transfer x dimension) pair this law with;
    #: None: all. A law whose fused kernels are costly to compile (a neural law) names a few, or none
    #: (``()``: its own tests run the conformance kit on it).
    test_transfers: ClassVar[tuple[str, ...] | None] = None
    #: False for a law whose Kirchhoff stress is not symmetric in general (NCLaw's tau = R T F^T, as
    #: released): the conformance kit then does not require tau = tau^T (angular momentum is then not
    #: conserved exactly by the stress).
    symmetric_stress: ClassVar[bool] = True
    #: state fields that count time (advanced by dt in every update, whatever the motion): the
    #: conformance kit's rest-state check expects them to move by exactly dt (``phase_change``'s clock)
    clock_fields: ClassVar[tuple[str, ...]] = ()

    def __init_subclass__(cls, **kw):
        super().__init_subclass__(**kw)
        if "state" in cls.__dict__:
            names = [f.name for f in cls.state]
            if len(set(names)) != len(names):
                raise ConfigError(f"law '{getattr(cls, 'name', cls.__name__)}': state field names {names} repeat.")
            cls.state_fields = tuple(names)

    # ---- instances ----------------------------------------------------------------------------
    @classmethod
    def from_config(cls, options: Mapping[str, Any] | None, where: str) -> "AbstractConstitutiveLaw":
        """The law instance a material's ``options`` describe (unknown options: a clear error)."""
        options = dict(options or {})
        known = [f.name for f in dataclasses.fields(cls)] if dataclasses.is_dataclass(cls) else []
        unknown = sorted(set(options) - set(known))
        if unknown:
            raise ConfigError(
                f"{where}: law '{cls.name}' has no option(s) {', '.join(unknown)}; "
                + (f"its options are {', '.join(known)}." if known else "it takes no options."))
        try:
            return cls(**options)
        except (TypeError, ValueError) as e:
            raise ConfigError(f"{where}: law '{cls.name}' options {options}: {e}") from None

    def __eq__(self, other):
        return type(other) is type(self) and other._config_key() == self._config_key()

    def __hash__(self):
        return hash((type(self), self._config_key()))

    def code_key(self) -> tuple:
        """The part of the configuration that changes a backend's generated code (the Warp struct and
        kernel names are derived from it, so equal keys share compiled kernels across processes); by
        default every field. A law whose options also hold data (a weights file, a seed) leaves those
        out, so a new weights file does not recompile its kernels."""
        return self._config_key()

    def _config_key(self) -> tuple:
        if not dataclasses.is_dataclass(self):
            return ()
        return tuple((f.name, _frozen(getattr(self, f.name))) for f in dataclasses.fields(self))

    def __repr__(self):
        body = ", ".join(f"{k}={v!r}" for k, v in self._config_key())
        return f"{type(self).__name__}({body})"

    # ---- parameters ---------------------------------------------------------------------------
    @classmethod
    def param_names(cls) -> tuple[str, ...]:
        return tuple(p.name for p in cls.params)

    @classmethod
    def resolve_params(cls, given: Mapping[str, Any], where: str, density: float | None = None) -> dict[str, float]:
        """Fill defaults, reject unknown names, check ranges; returns ``{name: float}`` in declared order."""
        known = cls.param_names()
        unknown = sorted(set(given) - set(known))
        if unknown:
            raise InvalidParameterError(
                f"{where}: law '{cls.name}' has no parameter(s) {', '.join(unknown)}; its parameters are "
                f"{', '.join(known) or '(none)'}."
            )
        out = {}
        for spec in cls.params:
            value = given.get(spec.name, spec.default)
            if value is None:
                value = cls.default_from_density(spec.name, density)
            if value is None:
                raise InvalidParameterError(f"{where}: law '{cls.name}' needs parameter '{spec.name}' [{spec.unit}].")
            out[spec.name] = spec.check(value, where)
        cls.check_consistency(out, where)
        return out

    def particle_params(self, params: np.ndarray, x: np.ndarray) -> np.ndarray:
        """Per-particle parameter values that depend on where the particles start, e.g. a switch time
        by height (``phase_change``): ``params`` ``[n, P]`` in declared order for one material group,
        ``x`` ``[n, D]`` its initial positions; returns the ``[n, P]`` rows. Unchanged by default."""
        return params

    @classmethod
    def default_from_density(cls, name: str, density: float | None) -> float | None:
        """Defaults that depend on the body (e.g. a fluid's rest density); None if there is none."""
        return None

    @classmethod
    def check_consistency(cls, params: Mapping[str, float], where: str) -> None:
        """Cross-parameter checks (override where needed)."""

    @classmethod
    @abstractmethod
    def wave_speed(cls, params: Mapping[str, float], density: float) -> float:
        """Largest elastic wave speed [m/s] (P-wave or sound speed) for the CFL bound."""

    def instance_wave_speed(self, params: Mapping[str, float], density: float, dim: int,
                            weights: Mapping[str, Any]) -> float:
        """The wave speed of this configured instance with its shared ``weights`` (what ``dt: auto``
        uses: ``Scene.wave_speed``); by default the class's ``wave_speed(params, density)``. A law whose
        stiffness lives in its weights (a neural law) overrides it."""
        return self.wave_speed(params, density)

    # ---- state and shared weights ---------------------------------------------------------------
    @classmethod
    def state_spec(cls, name: str) -> StateField:
        for f in cls.state:
            if f.name == name:
                return f
        raise KeyError(name)

    @classmethod
    def initial_state(cls, n: int, dim: int) -> dict[str, np.ndarray]:
        return {f.name: f.initial(n, dim) for f in cls.state}

    def weight_shapes(self, dim: int) -> dict[str, tuple[int, ...]]:
        """Shapes of the group-level (shared) arrays; none by default."""
        return {}

    def weight_views(self, dim: int) -> dict[str, tuple[str, str]]:
        """Read-only re-laid copies of shared arrays that the Warp kernels read as vectors, ``{view:
        (source, how)}``: ``how`` = ``"cols"`` (a 2D [r, c] source as c vectors of length r, view[j] =
        source[:, j]), ``"rows"`` (r vectors of length c) or ``"whole"`` (a 1D source as one vector). They
        are members of the Warp ``Weights`` struct next to the sources, rebuilt whenever the struct is
        built from arrays, and take no gradient (the law's adjoint writes the sources'). ``"grad_rows"``
        is no copy: the 2D source's *gradient* array as r row vectors of length c (an alias, empty when the
        source takes no gradient), which a hand-written adjoint accumulates into a row at a time (one
        vector add instead of c scalar ones). None by default."""
        return {}

    def initial_weights(self, dim: int) -> dict[str, np.ndarray]:
        """The shared arrays' starting values (float64; e.g. loaded from a weights file)."""
        return {k: np.zeros(s) for k, s in self.weight_shapes(dim).items()}

    def weights_metadata(self, dim: int) -> dict[str, str]:
        """String metadata written into a weights file of this instance (safetensors ``metadata``), e.g.
        the configuration its arrays belong to; none by default."""
        return {}

    def check_weights(self, weights: Mapping[str, Any], dim: int, where: str) -> None:
        """Refuse weights whose names or shapes differ from ``weight_shapes`` (one line, names the law)."""
        want = self.weight_shapes(dim)
        if set(weights) != set(want):
            raise ConfigError(f"{where}: law '{self.name}' declares weights {sorted(want)}, got {sorted(weights)}.")
        for k, shape in want.items():
            got = tuple(np.shape(weights[k]))
            if got != tuple(shape):
                raise ConfigError(f"{where}: law '{self.name}' weight '{k}' has shape {got}; it declares {tuple(shape)}.")

    # ---- diagnosis -----------------------------------------------------------------------------
    def divergence_note(self, fields: Mapping[str, np.ndarray], particle: int) -> str | None:
        """A clause the divergence diagnosis (``mpmlab.core.diagnosis``) adds about this law's state when a
        run fails: ``fields`` are this law group's state arrays one step before the failure (name ->
        [n, ...], host float64), ``particle`` the failing particle's index in them (-1: it is in another
        group). None (the default): nothing to add. A learned law says here whether the run took it
        outside the states it was trained on."""
        return None


def registered_state_fields() -> dict[str, StateField]:
    """Every state field the registered laws declare, by name (the first declaration of a name wins),
    in registry order. A plugin law that fails to load is left out: it must not hide the others."""
    from . import registry

    out: dict[str, StateField] = {}
    for name in registry.laws.names():
        try:
            for f in registry.laws.get(name).state:
                out.setdefault(f.name, f)
        except Exception:  # noqa: BLE001 -- a broken plugin law
            continue
    return out


def named_params(prm, names) -> Mapping[str, Any]:
    """Law parameters by name: a mapping is returned as is; an array ``[..., P]`` in the declared
    order (the layout of a stepper's per-particle parameters) becomes ``{name: prm[..., i]}``. NumPy
    references call it at their entry points, so their code reads ``prm["E"]`` either way."""
    if isinstance(prm, Mapping):
        return prm
    a = np.asarray(prm, dtype=float)
    return {n: a[..., i] for i, n in enumerate(names)}


def _frozen(v):
    if isinstance(v, Mapping):
        return tuple(sorted((k, _frozen(x)) for k, x in v.items()))
    if isinstance(v, (list, tuple)):
        return tuple(_frozen(x) for x in v)
    return v


class P2GTerms(NamedTuple):
    """What one transfer scheme scatters from each particle p to each node i of its 3^D stencil
    (JAX: arrays with a leading particle axis; ``None`` = the term is absent and never computed).

    With w = w_ip and x_i - x_p = (o - fx) dx, node i receives
      mass      m_p w                                   (always; the kernels add it)
      momentum  w (q_p + A_p (x_i - x_p)) + G_p grad w   (q [D], A [D, D], G [D, D]: impulses, times dt)
      force     w F_p (x_i - x_p) + H_p grad w           (``split_force`` schemes only: kept apart from the
                                                          momentum so that G2P sees the old grid velocity)
    External particle forces (boundaries) are added by the kernels: dt f to q, or f to the force lane.
    """

    q: Any
    A: Any = None
    G: Any = None
    force_A: Any = None
    force_G: Any = None


class G2PResult(NamedTuple):
    """What a transfer scheme makes of the gathered grid velocities, per particle: the new velocity
    ``v``, the new affine field ``C`` (``carries_C`` schemes, else None) and the velocity gradient
    ``grad_v`` the law is updated with. The particle moves with the PIC velocity sum w v_i (JAX-MPM
    Eq. 17) whatever the scheme."""

    v: Any
    C: Any
    grad_v: Any


class AbstractTransfer(_Pluggable, ABC):
    """How velocity (and affine / gradient data) goes particle -> grid -> particle.

    A scheme carries its own math, one folder per scheme (``mpmlab/transfers/<name>/``: ``jax.py``,
    ``warp.py``), while the kernels keep one generic stencil decomposition and compile only the terms
    the scheme declares (so PIC pays for no affine term, MLS for no weight gradient):

    * ``carries_C``: the particle stores a D x D affine field ``C`` (state "C", a differentiable control).
    * ``momentum_terms`` / ``force_terms``: which of ``"affine"`` (the A / F term) and ``"gradient"``
      (the G / H term) of :class:`P2GTerms` the scheme's P2G returns; ``force_terms`` only with
      ``split_force`` (the grid keeps the force apart, FLIP).
    * ``moments``: the G2P sums beyond ``v_pic = sum w v_i`` the scheme reads: ``"first"``
      (``B = sum w v_i o^T``, o the node offset in cells: APIC's B, Jiang et al. 2015) and
      ``"gradient"`` (``sum v_i (grad w)^T``, JAX-MPM Eq. 18); with ``split_force`` also
      ``v_old = sum w v_i^old``.
    * ``scalars()``: runtime numbers of the math (the FLIP ratio): kernel arguments on Warp, so
      changing them does not recompile.
    * ``conserves``: what the scheme conserves over a step without external forces
      (``"linear_momentum"``, ``"angular_momentum"`` counting the particles' affine spin, Jiang et al.
      2015 Sec. 5.3); ``mpmlab.testing.check_transfer`` measures each one it declares.

    Backend functions (``implementations[backend]`` is a factory ``make(transfer, dim)`` on JAX,
    ``make(transfer, dim, precision)`` on Warp, returning a namespace; cache it, kernels are keyed
    by it):

    * JAX: ``p2g(p) -> P2GTerms`` and ``g2p(g) -> G2PResult`` on particle-batched arrays; ``p`` has
      ``m, V, v, C, tau, dt, inv_dx, dx, Dinv``; ``g`` has ``v, v_pic, v_old, first, grad, fx, inv_dx,
      dx, Dinv`` (``None`` for what is not declared). ``grad`` and ``G`` are in physical units (1/length).
      ``first`` sums over the shape function's window with o = 0 .. width-1 and ``fx`` is the particle's
      position in cells from the window's lowest node, so B = sum w v_i (x_i - x_p)^T = dx (first - v_pic
      fx^T) for every shape function. ``Dinv`` is D_p^-1 (APIC's inverse inertia, MLS's M^-1; 1/length^2;
      D_p = sum_i w_ip (x_i - x_p)(x_i - x_p)^T, Jiang et al. 2015): a Python float c meaning c I for
      every particle when the shape function's D_p is a constant (B-splines: 4/dx^2 quadratic, 3/dx^2
      cubic), an [N, D, D] array when it varies per particle (uGIMP: diagonal);
      ``mpmlab.transfers._common.jax.times_Dinv(M, Dinv)`` gives M D^-1 for either form. ``p.Dinv`` is
      D_p^-1 at the P2G position x_p; ``g.Dinv`` at the position the particle moves to, x_p + dt v_pic,
      where the next P2G applies the C that ``g2p`` returns (so C D_p there is the B gathered; the same
      for B-splines). A scheme whose C must carry B's angular momentum exactly reads it from C D_p, not
      from C alone, where D_p is not isotropic (the example plugin's RPIC).
    * Warp (``@wp.func``s the kernel factories close over): ``p2g_momentum(m, V, v, C, tau, dt,
      inv_dx, Dinv, tp) -> (q, A, G)``, ``p2g_force(same) -> (F, H)`` (``split_force`` only) and
      ``g2p(v, vp, vo, B, Gv, fx, inv_dx, Dinv, tp) -> (v, C, grad_v)``; ``Dinv`` (a ``mat``, 1/length^2)
      is the particle's D_p^-1 of the shape function (APIC's C = (B - vp fx^T) dx Dinv; in ``g2p`` at
      x_p + dt vp, in the P2G functions at x_p, as on JAX); ``tp`` is the
      array of ``scalars()``; G and H multiply the weight gradient in cell units (dx grad w, the kernels'
      own), ``Gv`` is in physical units. Undeclared outputs are ignored (return zeros).
    """

    carries_C: ClassVar[bool] = False
    split_force: ClassVar[bool] = False
    momentum_terms: ClassVar[frozenset] = frozenset()
    force_terms: ClassVar[frozenset] = frozenset()
    moments: ClassVar[frozenset] = frozenset()
    conserves: ClassVar[frozenset] = frozenset({"linear_momentum"})
    #: the shape functions (``mpmlab.shapes``) this scheme's math is valid for; None = every one (the
    #: scheme reads D^-1 as ``Dinv`` or does not use D). A scheme written before shape functions were a
    #: choice (D = dx^2/4 hard-coded, as in Jiang et al. 2015) keeps the default: quadratic only.
    shapes: ClassVar[frozenset | None] = frozenset({"quadratic"})

    TERMS: ClassVar[frozenset] = frozenset({"affine", "gradient"})
    MOMENTS: ClassVar[frozenset] = frozenset({"first", "gradient"})

    @property
    def needs_affine(self) -> bool:
        return bool(self.carries_C)

    def scalars(self) -> tuple:
        """Runtime numbers of this scheme's math, in the order its Warp functions read ``tp``."""
        return ()

    def for_scene(self, scene) -> "AbstractTransfer":
        """This scheme as it runs on ``scene`` (``build_stepper`` calls it): the same instance unless an
        option depends on the scene, e.g. FLIP's ``pic_time``, resolved to a per-step ratio at its dt."""
        return self

    def describe(self) -> str:
        return f"transfer '{getattr(self, 'name', type(self).__name__)}' ({type(self).__module__})"

    def check(self) -> None:
        """Refuse declarations the kernels cannot carry out, in one line naming the scheme (called when a
        stepper is built; each backend then checks the scheme's functions against them)."""
        where = self.describe()
        for attr, allowed in (("momentum_terms", self.TERMS), ("force_terms", self.TERMS),
                              ("moments", self.MOMENTS)):
            bad = set(getattr(self, attr)) - allowed
            if bad:
                raise ConfigError(f"{where}: {attr} has {sorted(bad)}, not among {sorted(allowed)}.")
        if self.force_terms and not self.split_force:
            raise ConfigError(f"{where}: force_terms = {sorted(self.force_terms)} needs split_force = True "
                              f"(without it the force is part of the momentum: declare it in momentum_terms).")
        if not (self.momentum_terms or self.force_terms):
            raise ConfigError(f"{where}: declares no force term (momentum_terms and force_terms are empty): "
                              f"the material's stress would never reach the grid.")
        for k, value in enumerate(self.scalars()):
            if not isinstance(value, (int, float)) or not math.isfinite(float(value)):
                raise ConfigError(f"{where}: scalars()[{k}] = {value!r} is not a finite number.")

    def options(self) -> dict[str, Any]:
        """The scheme's configured options (its dataclass fields), as recorded in run metadata."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)} if dataclasses.is_dataclass(self) else {}


class AbstractShape(_Pluggable, ABC):
    """A grid shape function, the second choice of a transfer (``transfer: {name: apic, shape: cubic}``):
    the weights w_ip a particle gives its nodes and their gradients (issue 19; Steffen et al. 2008 for
    B-splines, Bardenhagen & Kober 2004 for GIMP, Sadeghirad et al. 2011 for CPDI).

    ``kind = "separable"``: w_ip = prod_d N(x_p,d - x_i,d), so a particle reaches one window of
    ``width``^D nodes whose lowest node is ``floor(x/dx - offset)``; the kernels keep their windowed
    P2G / G2P and only the 1-D weights change. The backend functions (``implementations[backend]``,
    a factory ``make(shape, dim)`` on JAX, ``make(shape, dim, precision)`` on Warp, cached):

    * JAX: ``weights(fx, lp) -> (w, dw)``, ``fx = x/dx - base`` [N, D], ``lp`` [N] the particle's half
      width in cells; ``w``, ``dw`` are [N, width, D], ``dw = dN/dx_p`` in cell units.
    * Warp: ``@wp.func weights(fx: vec, lp: scalar) -> (W, DW)``, two ``width x D`` matrices, and
      ``hessian(fx, lp) -> DDW`` (d2N/dx_p^2 in cell units, ``width x D``: the hand-written adjoints'
      derivative of the weight gradient).
    * The NumPy ``reference.weights_1d(fx, lp)`` (fp64, [N] -> [N, width] twice) is what the tests
      check partition of unity and linear completeness on.

    ``kind = "corners"`` (CPDI, ``mpmlab/shapes/cpdi/reference.py``): w_ip = 2^-D sum_c N_i(x_c) over the
    corners x_c = x_p + R s_c of the particle's domain R (transfer state ``"domain"`` [N, D, D], declared in
    ``state``), N_i the linear hat: the kernels run P2G / G2P over 2^D corner pseudo-particles with the
    ``width`` = 2, ``offset`` = 0 window of ``weights`` (the hat), the gradient as 2^-D N_i(x_c) R^-T s_c.

    ``inv_D_cells``: D_p = sum_i w_ip (x_i - x_p)(x_i - x_p)^T (Jiang et al. 2015, APIC's inertia) is
    dx^2 / inv_D_cells I for B-splines (4 quadratic, 3 cubic); None means it varies per particle and
    the backends compute it from the particle's own weights (GIMP). Schemes read D^-1 as ``Dinv``.
    ``uses_particle_size``: the weights depend on ``lp`` (half the particle's initial width, from its
    initial volume: lp = V0^(1/D) / (2 dx)); ``max_particle_size``: the largest lp in cells the window
    holds (a larger particle is refused when the stepper is built).
    """

    kind: ClassVar[str] = "separable"
    #: per-particle state the shape function carries beyond x (names; ``"domain"``: CPDI's R [D, D])
    state: ClassVar[tuple] = ()
    width: ClassVar[int] = 3
    offset: ClassVar[float] = 0.5
    inv_D_cells: ClassVar[float | None] = None
    uses_particle_size: ClassVar[bool] = False
    max_particle_size: ClassVar[float] = math.inf

    def describe(self) -> str:
        return f"shape function '{getattr(self, 'name', type(self).__name__)}' ({type(self).__module__})"

    def check(self) -> None:
        """Refuse declarations the kernels cannot carry out, in one line naming the shape function."""
        where = self.describe()
        if self.kind not in ("separable", "corners"):
            raise ConfigError(f"{where}: kind '{self.kind}' is not one the kernels carry: 'separable' (a window "
                              f"of 1-D weights) or 'corners' (CPDI's domain corners with the linear hat).")
        if self.kind == "corners" and (self.width != 2 or float(self.offset) != 0.0 or tuple(self.state) != ("domain",)):
            raise ConfigError(f"{where}: kind 'corners' runs the linear hat at each corner of the particle's "
                              f"domain: declare width = 2, offset = 0 and state = ('domain',).")
        if not (isinstance(self.width, int) and 2 <= self.width <= 4):
            raise ConfigError(f"{where}: width = {self.width!r} must be 2, 3 or 4 nodes per axis.")

    def options(self) -> dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)} if dataclasses.is_dataclass(self) else {}


class AbstractBoundary(_Pluggable, ABC):
    """A grid post-process step (walls, friction, planes, obstacles) or a particle-set constraint/load.

    ``stage`` says where the step acts: ``"grid"`` (after the grid velocity update, before G2P),
    ``"particle_velocity"`` (overrides particle velocities after G2P) or ``"particle_force"`` (adds a
    force to particles in P2G). Backends look up ``implementations[backend]`` to build it.
    """

    stage: ClassVar[str] = "grid"
    #: backends whose differentiable path runs through this boundary (the capability table's gradient
    #: columns). JAX differentiates its (pure) implementation; on Warp the factory's result must give
    #: ``tape()``, a tape-safe implementation (``mpmlab/backends/warp/boundaries.py``).
    gradients: ClassVar[tuple] = ("jax",)
    #: True where the boundary prescribes the motion of the material it holds (a Dirichlet condition on
    #: particles or on grid nodes). Such a boundary also gives ``select(x) -> indices`` of the material
    #: points it holds at t = 0: the reduced model samples at least five of them (ROM paper Sec. 3.3).
    kinematic: ClassVar[bool] = False

    @abstractmethod
    def validate(self, scene) -> None:
        """Raise ConfigError if this boundary does not fit the scene (dimension, extents)."""


class AbstractObservation(_Pluggable, ABC):
    """Maps a state to what an instrument sees (JAX-MPM Eqs. 26-27)."""

    #: backends on which gradients flow through it (its Warp implementation records on the tape)
    gradients: ClassVar[tuple] = ("jax",)


class AbstractStepper(ABC):
    """A compiled simulator for one scene and option set, built by a backend.

    ``init() -> state``; ``step(state) -> state``; ``rollout(state, steps, every) -> Trajectory``.
    Backend arrays stay inside; ``to_numpy(state)`` gives a dict of numpy arrays.
    """

    @abstractmethod
    def init(self):
        ...

    @abstractmethod
    def step(self, state):
        ...

    @abstractmethod
    def rollout(self, state, steps: int, every: int = 1, **kw):
        ...

    @abstractmethod
    def to_numpy(self, state) -> dict[str, np.ndarray]:
        ...

    # ---- differentiable entry points (issue #4) ------------------------------------------------
    # Both backends expose the same two calls; arrays are the backend's differentiable arrays (JAX:
    # jax arrays under jax.grad; Warp: torch tensors through a torch.autograd.Function).
    #
    # ``controls()`` -> dict, scene (not storage) order:
    #   x [N, D], v [N, D]    initial particle positions and velocities
    #   law                   tuple, one [count, P] array per material group (law.param_names() order)
    #   boundary              tuple, one dict per scene boundary (e.g. friction_walls {"mu": [S]})
    #   gravity [D], mass [N], volume [N]
    # ``observe(controls, observation, steps, segment=...)`` -> [T, L, d]: the observation operator
    #   applied to the state after each step in ``steps`` (sorted; 0 = initial state), the rollout
    #   run from ``controls``; gradients are recomputed per segment of ``segment`` steps so memory is
    #   O(steps / segment + segment) states. A non-finite gradient raises ``GradientError``.
    def controls(self) -> dict:
        raise NotImplementedError(f"{type(self).__name__} has no differentiable entry points.")

    def observe(self, controls: dict, observation, steps, segment: int | None = None):
        raise NotImplementedError(f"{type(self).__name__} has no differentiable entry points.")


class AbstractBackend(ABC):
    """A registered backend: builds steppers and converts arrays."""

    name: ClassVar[str]

    @abstractmethod
    def build(self, scene, transfer: AbstractTransfer, precision: str = "fp32", **options) -> AbstractStepper:
        ...
