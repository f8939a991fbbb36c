"""benchmarks/stage_profile.py (issue #5 item 5): the per-stage split of a step accounts for the step's
time on both backends, and the JAX attribution of XLA thunks to step_fn sections finds the main stages."""
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))


@pytest.mark.parametrize("backend", ("jax", "warp"))
def test_stage_split_covers_the_step(backend):
    import stage_profile as P

    import mpmlab

    st = mpmlab.build_stepper(P.make_scene("cube", 2, 16), backend, "mls", "fp32")
    res = (P.profile_jax if backend == "jax" else P.profile_warp)(st, 10)
    stages = res["stages"]
    assert set(stages) <= set(P.STAGES)
    total = sum(stages.values())
    assert total == pytest.approx(res["wall_per_step_s"], rel=0.35)
    for name in ("P2G", "G2P"):
        assert stages.get(name, 0.0) > 0.0, (name, stages)
    if backend == "jax":   # the law's SVD and the walls are found in their modules
        assert stages.get("law (stress)", 0.0) + stages.get("law (update)", 0.0) > 0.0
        assert stages.get("boundaries", 0.0) > 0.0
        # most of the step's XLA ops are attributed to a stage (counted, not timed: one descheduled thunk on
        # a loaded machine once made the unattributed time 54 % of a 0.3 ms step, 3 % when unloaded)
        ops = res["ops_per_stage"]
        assert ops.get("host / loop", 0) < sum(n for k, n in ops.items() if k != "host / loop"), ops
    go = P.guards_and_output(st, res["state"], reps=2)
    assert go["guard_s"] > 0 and go["frame_s"] > 0
