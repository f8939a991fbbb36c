"""NumPy float64 reference of the ``phase_change`` switch (the conformance oracle): the active law's
own reference on its share of the state, parameters and weights (``mpmlab.laws.phase_change``)."""
from __future__ import annotations

import numpy as np


def _active(state, prm) -> str:
    return "after" if float(state["clock"]) >= float(prm["switch_time"]) else "before"


def _side(law, side, state, prm, w, dim):
    sub = dict(law.sides())[side]
    return (sub, {f.name: state[f.name] for f in sub.state}, law.side_params(side, prm),
            law.side_weights(side, w, dim))


def _dim(state, law, dim):
    if dim is not None:
        return dim
    for f in law.state:
        if len(f.shape) == 2:
            return int(np.shape(state[f.name])[0])
    raise ValueError("phase_change reference: pass dim= (the state has no matrix field to read it from).")


def kirchhoff(state, prm, w, law=None, dim=None):
    from ...testing.evaluate import ref_kirchhoff

    d = _dim(state, law, dim)
    sub, s, p, ws = _side(law, _active(state, prm), state, prm, w, d)
    return ref_kirchhoff(sub, s, p, d, weights=ws)


def update(state, grad_v, dt, prm, w, law=None):
    from ...testing.evaluate import ref_update

    d = int(np.shape(grad_v)[0])
    sub, s, p, ws = _side(law, _active(state, prm), state, prm, w, d)
    new = dict(state)
    new.update(ref_update(sub, s, grad_v, dt, p, d, weights=ws))
    new["clock"] = float(state["clock"]) + float(dt)
    return new
