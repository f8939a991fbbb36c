"""Output fields synthesised from the state a law carries, so that one dataset layout serves every law.

A run that asks for a field by name (``output.fields: [F, C]``) stores it for every particle whose law
carries it. Some laws carry less: ``weakly_compressible`` (NCLaw's WATER) keeps only ``J = det F``,
because its stress and its return map (NCLaw App. B, Eq. 21: ``F <- J^(1/d) I``) see F only through
J. A neural law trained under teacher forcing needs F on every particle, so for such a law the stored F
is synthesised as ``F = J^(1/d) I`` -- exactly the F the return map would leave.

Only a field named explicitly is synthesised (``output.fields: [all]`` keeps what the laws carry), and
the file says so: the root attribute ``derived_fields`` (JSON, ``{field: {source, formula, reason,
laws, particles: [[start, stop], ...]}}``) and the attributes ``derived_from`` / ``derived_particles``
of the frame dataset (``frames/F``). :func:`plan_derived` decides from the scene, :func:`apply_derived`
adds the field to a rollout's numpy state before the writer sees it.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Iterable, Sequence

import numpy as np


def _f_from_j(J: np.ndarray, dim: int) -> np.ndarray:
    """F = J^(1/d) I (NCLaw App. B, Eq. 21), per particle: [n] -> [n, d, d]."""
    J = np.asarray(J)
    s = np.cbrt(J) if dim == 3 else np.sqrt(J) if dim == 2 else J ** (1.0 / dim)
    return (s[:, None, None] * np.eye(dim, dtype=J.dtype)).astype(J.dtype, copy=False)


@dataclass(frozen=True)
class DerivedRule:
    """How ``field`` is made from ``source`` for a law that carries only ``source``."""

    field: str
    source: str
    fn: Callable[[np.ndarray, int], np.ndarray]
    reason: str

    def formula(self, dim: int) -> str:
        return {2: "F = J^(1/2) I", 3: "F = J^(1/3) I"}.get(dim, "F = J^(1/d) I") if self.field == "F" \
            else f"{self.field} from {self.source}"


#: field -> rule; a law that carries ``source`` but not ``field`` gets ``field`` synthesised
RULES: dict[str, DerivedRule] = {
    "F": DerivedRule("F", "J", _f_from_j,
                     "the law carries only J = det F; F = J^(1/d) I is the F its return map leaves "
                     "(NCLaw App. B, Eq. 21), as a teacher-forcing dataset needs F on every particle"),
}


@dataclass
class DerivedPlan:
    """One synthesised field: its rule and the material groups ``(law name, start, stop)`` it covers."""

    rule: DerivedRule
    groups: list[tuple[str, int, int]] = field(default_factory=list)

    def metadata(self, dim: int) -> dict:
        return {"source": self.rule.source, "formula": self.rule.formula(dim), "reason": self.rule.reason,
                "laws": sorted({g[0] for g in self.groups}), "particles": [[g[1], g[2]] for g in self.groups]}


def plan_derived(requested: Iterable[str], groups: Sequence) -> dict[str, DerivedPlan]:
    """The fields to synthesise: each explicitly ``requested`` field with a rule, for the material
    ``groups`` (``MaterialGroup``s, or anything with ``law``, ``start``, ``stop``) whose law carries the
    rule's source but not the field itself. Empty when every law carries what was asked."""
    out: dict[str, DerivedPlan] = {}
    for name in dict.fromkeys(requested):
        rule = RULES.get(name)
        if rule is None:
            continue
        cover = [(g.law.name, int(g.start), int(g.stop)) for g in groups
                 if name not in g.law.state_fields and rule.source in g.law.state_fields]
        if cover:
            out[name] = DerivedPlan(rule, cover)
    return out


def derived_metadata(plans: dict[str, DerivedPlan], dim: int) -> dict:
    """``{field: {source, formula, reason, laws, particles}}`` for the file's ``derived_fields``."""
    return {k: p.metadata(dim) for k, p in plans.items()}


def apply_derived(npstate: dict, plans: dict[str, DerivedPlan], dim: int) -> dict:
    """``npstate`` (a rollout's numpy state: ``F``/``F_particles``, ``J``/``J_particles``, ...) with each
    planned field added for its groups, merged in particle order with the particles whose law carries
    it (``<field>_particles`` lists them all). The input dict is not changed."""
    if not plans:
        return npstate
    out = dict(npstate)
    for name, plan in plans.items():
        src = np.asarray(npstate[plan.rule.source])
        src_idx = np.asarray(npstate.get(plan.rule.source + "_particles", np.arange(len(src))))
        keep = np.zeros(len(src_idx), bool)
        for _, a, b in plan.groups:
            keep |= (src_idx >= a) & (src_idx < b)
        made, made_idx = plan.rule.fn(src[keep], dim), src_idx[keep]
        if name in npstate:            # the particles whose law carries the field itself
            have = np.asarray(npstate[name])
            have_idx = np.asarray(npstate.get(name + "_particles", np.arange(len(have))))
            made = np.concatenate([have, made.astype(have.dtype, copy=False)])
            made_idx = np.concatenate([have_idx, made_idx])
        order = np.argsort(made_idx, kind="stable")
        out[name], out[name + "_particles"] = made[order], made_idx[order]
    return out
