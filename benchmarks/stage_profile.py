"""Where a step's time goes, per stage, on both backends (issue #5 item 5).

Stages: law stress, P2G, grid update, boundaries, G2P (+ the law update), guards, output. The scenes
are those of ``throughput.py``: Taichi mpm3d's fluid (``mpm3d``, weakly compressible, MLS) and the
fixed-corotated elastic cube (``cube``, MLS; its law needs an SVD per particle per step).

How each backend is split:

* **Warp**: the step is a sequence of kernel launches (P2G, grid update with the domain walls, the
  other grid boundaries, G2P fused with each group's law update, which also computes the next step's
  Kirchhoff stress) plus host work (the grid's bounding box, launch parameters). CPU launches run
  synchronously in the calling thread, so the script times each call of ``_run_static`` /
  ``_run_dynamic`` / boundary ``apply`` / ``_sort_into`` inside ``_step_into`` with ``perf_counter``;
  "host" is the rest of ``_step_into``.
* **JAX**: the step is one XLA program. The script runs it under ``jax.profiler.trace`` and attributes
  every executed XLA thunk (the ``hlo_op`` of the trace events) to the source line it was traced from
  (the compiled HLO's stack frames), then to the ``step_fn`` section that line lies in -- the sections
  are the comment headers of ``mpmlab/backends/jax/stepper.py::step_fn`` -- or to "boundaries" when
  the frame chain passes through a boundary module. XLA CPU runs independent thunks concurrently, so
  the per-stage times are shares of the summed thunk time, scaled to the measured wall time per step.
* **Guards and output** (both backends): the guard reduction is timed per call (it runs once per
  ``check_every`` steps, default = once per output frame), output = ``to_numpy`` of a frame + appending
  it to an HDF5 file; both are reported per step for one frame every ``--every`` steps.

    python benchmarks/stage_profile.py                      # mpm3d + cube, 3D n_grid 32, both backends, fp32
    python benchmarks/stage_profile.py --n-grid 64 --steps 100 --backends warp
    python benchmarks/stage_profile.py --render             # the README section again from results/profile.json

Writes ``benchmarks/results/profile.json``, ``benchmarks/figures/profile.png`` and the "Profiles"
section of ``benchmarks/README.md``.
"""
from __future__ import annotations

import gzip
import inspect
import json
import re
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

import _harness as H
from _harness import machine_info, write_readme_section

HERE = H.HERE
RESULT = H.RESULTS / "profile.json"
FIGURE = H.FIGURES / "profile.png"
STAGES = ("law (stress)", "P2G", "grid update", "boundaries", "G2P", "law (update)", "host / loop", "guards",
          "output")


# ---- scenes ------------------------------------------------------------------------------------------------
def make_scene(name: str, dim: int, n_grid: int):
    """``mpm3d`` or ``cube``: the scenes of ``throughput.py`` (``_harness.throughput_scene``)."""
    return H.throughput_scene(name, dim, n_grid)


# ---- guards and output, both backends ----------------------------------------------------------------------
def guards_and_output(st, state, reps: int = 5) -> dict:
    """Seconds per call of the guard reduction and of one output frame (to_numpy + HDF5 append)."""
    import h5py

    st._is_bad(state)
    t_guard = []
    for _ in range(reps):
        t0 = time.perf_counter()
        st._is_bad(state)
        t_guard.append(time.perf_counter() - t0)
    t_out = []
    with tempfile.TemporaryDirectory() as d, h5py.File(Path(d) / "frames.h5", "w") as f:
        n = st.particles.count
        dsx = f.create_dataset("x", (0, n, st.dim), maxshape=(None, n, st.dim), dtype="f4", chunks=(1, n, st.dim))
        dsv = f.create_dataset("v", (0, n, st.dim), maxshape=(None, n, st.dim), dtype="f4", chunks=(1, n, st.dim))
        for k in range(reps):
            t0 = time.perf_counter()
            npst = st.to_numpy(state)
            for ds, a in ((dsx, npst["x"]), (dsv, npst["v"])):
                ds.resize(k + 1, axis=0)
                ds[k] = a
            f.flush()
            t_out.append(time.perf_counter() - t0)
    return {"guard_s": float(np.median(t_guard)), "frame_s": float(np.median(t_out))}


# ---- Warp: time the launches of _step_into -------------------------------------------------------------------
def profile_warp(st, steps: int) -> dict:
    state = st._advance(st.init(), 5)
    st._block(state)
    times = defaultdict(float)
    order = {"i": 0}
    clock = time.perf_counter

    def timed(fn, stage_of):
        def run(*a, **k):
            t0 = clock()
            out = fn(*a, **k)
            times[stage_of()] += clock() - t0
            return out
        return run

    dynamic_stage = lambda: ("grid update", "G2P")[min(order["i"], 1)]

    def after_dynamic():
        s = dynamic_stage()
        order["i"] += 1
        return s

    orig = {"static": st._run_static, "dynamic": st._run_dynamic, "step": st._step_into, "sort": st._sort_into}
    st._run_static = timed(orig["static"], lambda: "P2G")
    st._run_dynamic = timed(orig["dynamic"], after_dynamic)
    st._sort_into = timed(orig["sort"], lambda: "host / loop")
    bcs = [(bc, "apply") for bc in st.grid_bcs] + [(bc, "apply_particles") for bc in st.particle_bcs] + \
          [(bc, "add_force") for bc in st.force_bcs]
    saved = [(bc, m, getattr(bc, m)) for bc, m in bcs]
    for bc, m, fn in saved:
        setattr(bc, m, timed(fn, lambda: "boundaries"))

    def step(s, o):
        order["i"] = 0
        t0 = clock()
        orig["step"](s, o)
        times["_step_into"] += clock() - t0
    st._step_into = step
    try:
        t0 = clock()
        state = st._advance(state, steps)
        st._block(state)
        wall = clock() - t0
    finally:
        st._run_static, st._run_dynamic, st._step_into, st._sort_into = (orig["static"], orig["dynamic"], orig["step"],
                                                                         orig["sort"])
        for bc, m, fn in saved:
            setattr(bc, m, fn)
    inner = sum(v for k, v in times.items() if k not in ("_step_into", "host / loop"))
    per = {k: v / steps for k, v in times.items() if k != "_step_into"}
    per["host / loop"] = per.get("host / loop", 0.0) + (wall - inner - times.get("host / loop", 0.0)) / steps
    # the fused G2P kernel also runs the law update and the next stress: reported as "G2P" (+ law)
    return {"wall_per_step_s": wall / steps, "stages": per, "state": state,
            "note": "G2P includes the fused law update and the next step's Kirchhoff stress"}


# ---- JAX: attribute XLA thunks to step_fn sections -------------------------------------------------------------
_INSTR = re.compile(r"^\s*(?:ROOT\s+)?%?([\w.\-]+) = (\(.*?\)|\S+) ([\w\-]+)\((.*)$")
_FRAME_TABLE = re.compile(r"^(\d+) \{(.*)\}$")


def _hlo_tables(text: str):
    """Instruction -> (opcode, stack frame id or None, called computations), computation roots, frames."""
    instr, roots, comp = {}, {}, None
    files, funcs, locs, frames = {}, {}, {}, {}
    section = None
    for line in text.splitlines():
        s = line.strip()
        if s in ("FileNames", "FunctionNames", "FileLocations", "StackFrames"):
            section = s
            continue
        if section is not None:
            m = re.match(r'^(\d+) (.*)$', s)
            if not m:
                section = None if s else section
                continue
            k, body = int(m.group(1)), m.group(2)
            if section == "FileNames":
                files[k] = body.strip('"')
            elif section == "FunctionNames":
                funcs[k] = body.strip('"')
            else:
                kv = dict(re.findall(r"(\w+)=(-?\d+)", body))
                (locs if section == "FileLocations" else frames)[k] = {a: int(b) for a, b in kv.items()}
            continue
        if s.endswith("{") and ("(" in s) and not s.startswith("ROOT") and " = " not in s.split("(")[0]:
            comp = s.split(" ")[0].lstrip("%")
            continue
        m = _INSTR.match(line)
        if not m:
            continue
        name, _, opcode, rest = m.groups()
        fid = re.search(r"stack_frame_id=(\d+)", rest)
        calls = re.findall(r"(?:calls|body|condition|branch_computations|to_apply)=\{?%?([\w.\-, %]+)\}?", rest)
        called = [c.strip().lstrip("%") for group in calls for c in group.split(",")]
        instr[name] = (opcode, int(fid.group(1)) if fid else None, called)
        if s.startswith("ROOT") and comp is not None:
            roots[comp] = name
    return instr, roots, files, funcs, locs, frames


def _frame_chain(fid, files, funcs, locs, frames):
    out = []
    seen = set()
    while fid in frames and fid not in seen:
        seen.add(fid)
        fr = frames[fid]
        loc = locs.get(fr.get("file_location_id"), {})
        out.append((files.get(loc.get("file_name_id"), "?"), funcs.get(loc.get("function_name_id"), "?"),
                    loc.get("line", -1)))
        parent = fr.get("parent_frame_id")
        if parent is None or parent == fid:
            break
        fid = parent
    return out          # innermost first


def step_fn_sections(stepper_cls) -> list[tuple[int, str]]:
    """(first line, stage) of the comment-headed sections of JaxStepper.step_fn, in file line numbers."""
    src, first = inspect.getsourcelines(stepper_cls.step_fn)
    names = [("# stencil", "P2G"), ("# stress", "law (stress)"), ("# P2G", "P2G"), ("# grid update", "grid update"),
             ("# G2P", "G2P"), ("# law update", "law (update)")]
    out = [(first, "P2G")]
    for i, line in enumerate(src):
        s = line.strip()
        for key, stage in names:
            if s.startswith(key):
                out.append((first + i, stage))
                break
    return out


def profile_jax(st, steps: int) -> dict:
    import jax

    from mpmlab.backends.jax.stepper import JaxStepper

    state = st._advance(st.init(), 5)
    st._block(state)
    dt_arg = getattr(st, "_dt_arg", None)
    text = st._jit_advance.lower(state, st.params, steps, dt_arg).compile().as_text()
    instr, roots, files, funcs, locs, frames = _hlo_tables(text)
    sections = step_fn_sections(JaxStepper)

    src, first = inspect.getsourcelines(JaxStepper.step_fn)
    last = first + len(src) - 1

    def stage_of_frame(fid):
        # JAX keeps only part of the Python stack per op (vmapped law functions lose their caller), so
        # classify by the innermost frame that says something: a boundary module, a line of step_fn
        # (including its local lambdas), a law module (kirchhoff -> stress, else update), or a helper
        chain = _frame_chain(fid, files, funcs, locs, frames)
        if any("/boundaries" in f or "body_force" in f for f, _, _ in chain):
            return "boundaries"
        for f, fn, line in chain:
            if f.endswith("backends/jax/stepper.py"):
                if first <= line <= last:
                    stage = "P2G"
                    for start, name in sections:
                        if line >= start:
                            stage = name
                    return stage
                if fn == "bspline_weights":
                    return "P2G"
                if fn == "per_mass":
                    return "grid update"
            if "/laws/" in f or f.endswith("backends/jax/linalg.py"):
                names = " ".join(n for _, n, _ in chain)
                return "law (stress)" if ("kirchhoff" in names or "stress" in names) else "law (update)"
        return "host / loop"

    def stage_of(name, depth=0):
        opcode, fid, called = instr.get(name, (None, None, []))
        if fid is None and called and depth < 4:
            root = roots.get(called[0])
            if root is not None:
                return stage_of(root, depth + 1)
        return stage_of_frame(fid) if fid is not None else "host / loop"

    containers = {"while", "conditional", "call"}
    st._advance(state, steps)        # warm
    with tempfile.TemporaryDirectory() as d:
        t0 = time.perf_counter()
        with jax.profiler.trace(d, create_perfetto_trace=True):
            out = st._advance(state, steps)
            st._block(out)
        wall_traced = time.perf_counter() - t0
        trace = next(Path(d).rglob("perfetto_trace.json.gz"))
        events = json.load(gzip.open(trace))
    events = events["traceEvents"] if isinstance(events, dict) else events
    thunk, ops = defaultdict(float), defaultdict(set)
    for e in events:
        a = e.get("args") or {}
        if e.get("ph") == "X" and "hlo_op" in a and str(a.get("hlo_module", "")).startswith("jit__advance_impl"):
            op = a["hlo_op"]
            if instr.get(op, ("",))[0] in containers:
                continue
            thunk[stage_of(op)] += e.get("dur", 0.0) * 1e-6
            ops[stage_of(op)].add(op)
    # wall time without the profiler, for scaling the shares
    t0 = time.perf_counter()
    out = st._advance(state, steps)
    st._block(out)
    wall = time.perf_counter() - t0
    total = sum(thunk.values()) or 1.0
    return {"wall_per_step_s": wall / steps, "stages": {k: v / total * wall / steps for k, v in thunk.items()},
            "thunk_s_per_step": {k: v / steps for k, v in thunk.items()}, "traced_wall_s": wall_traced,
            "ops_per_stage": {k: len(v) for k, v in ops.items()},
            "state": out, "note": "shares of XLA thunk time (concurrent thunks overlap), scaled to the wall time"}


# ---- driver ------------------------------------------------------------------------------------------------
def run(backends, scenes, dim, n_grid, precision, steps, every) -> dict:
    import mpmlab

    rows = []
    for name in scenes:
        for backend in backends:
            scene = make_scene(name, dim, n_grid)
            st = mpmlab.build_stepper(scene, backend, "mls", precision)
            print(f"[profile] {name} {dim}D n_grid {n_grid} on {backend}/{precision}: {st.particles.count} particles",
                  flush=True)
            res = profile_warp(st, steps) if backend == "warp" else profile_jax(st, steps)
            go = guards_and_output(st, res.pop("state"))
            stages = dict(res["stages"])
            stages["guards"] = go["guard_s"] / every
            stages["output"] = go["frame_s"] / every
            rows.append({"scene": name, "backend": backend, "precision": precision, "dim": dim, "n_grid": n_grid,
                         "particles": int(st.particles.count), "steps": steps, "frame_every": every,
                         "wall_per_step_s": res["wall_per_step_s"], "stages_s_per_step": stages,
                         "guard_call_s": go["guard_s"], "frame_s": go["frame_s"], "note": res["note"],
                         **({"thunk_s_per_step": res["thunk_s_per_step"]} if "thunk_s_per_step" in res else {})})
            del st
    return {"date": time.strftime("%Y-%m-%d %H:%M"), "machine": machine_info(), "rows": rows}


def render(res: dict) -> str:
    lines = [f"Measured {res['date']} on {res['machine']['cpu']} ({res['machine']['cores']} cores, shared), "
             f"JAX {res['machine'].get('jax')}, Warp {res['machine'].get('warp')}. Regenerate with "
             f"`python benchmarks/stage_profile.py` (method in its docstring). Milliseconds per step; guards and "
             f"output per step at one frame (and one guard check) every {res['rows'][0]['frame_every']} steps.\n",
             *H.md_table(["scene", "backend", "particles", *STAGES, "total", "wall (fast path)"])]
    for r in res["rows"]:
        s = r["stages_s_per_step"]
        tot = sum(s.get(k, 0.0) for k in STAGES)
        cells = []
        for k in STAGES:
            v = s.get(k)
            cells.append("-" if v is None else f"{v * 1e3:.3f} ({v / tot:.0%})")
        lines.append(H.md_row([f"{r['scene']} {r['dim']}D {r['n_grid']}", f"{r['backend']} {r['precision']}",
                               r["particles"], *cells, f"{tot * 1e3:.3f}", f"{r['wall_per_step_s'] * 1e3:.3f}"]))
    lines.append("\nWarp: G2P is fused with the law update and the next step's stress (one kernel), so its "
                 "law columns are empty. JAX: one XLA program per chunk of steps; the split is the share of "
                 "XLA thunk time per `step_fn` section (concurrent thunks overlap), scaled to the wall time.")
    lines.append("\n![profile](figures/profile.png)\n")
    return "\n".join(lines) + "\n"


def plot(res: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = res["rows"]
    fig, ax = plt.subplots(figsize=(9, 0.6 * len(rows) + 1.5))
    labels = [f"{r['scene']} {r['backend']}" for r in rows]
    left = np.zeros(len(rows))
    for i, k in enumerate(STAGES):
        vals = np.array([r["stages_s_per_step"].get(k, 0.0) * 1e3 for r in rows])
        ax.barh(labels, vals, left=left, color=f"C{i}", label=k)
        left += vals
    ax.set_xlabel("ms per step")
    ax.legend(fontsize=7, ncol=3, loc="lower right")
    ax.set_title("Where a step's time goes (benchmarks/stage_profile.py)")
    fig.tight_layout()
    FIGURE.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(FIGURE, dpi=100)
    plt.close(fig)


def main(argv=None) -> int:
    ap = H.parser(__doc__.split("\n\n")[0])
    H.add_backends(ap, as_list=True)
    ap.add_argument("--scenes", nargs="+", default=["mpm3d", "cube"], choices=["mpm3d", "cube"])
    ap.add_argument("--dim", type=int, default=3, choices=[2, 3])
    ap.add_argument("--n-grid", type=int, default=32)
    ap.add_argument("--precision", default="fp32", choices=["fp32", "fp64"])
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--every", type=int, default=10, help="steps per output frame / guard check")
    ap.add_argument("--render", action="store_true", help="only rewrite the README section from results/profile.json")
    args = ap.parse_args(argv)
    if args.render:
        res = json.loads(RESULT.read_text())
    else:
        res = run(args.backends, args.scenes, args.dim, args.n_grid, args.precision, args.steps, args.every)
        H.write_json(RESULT, res)
    plot(res)
    body = render(res)
    write_readme_section(HERE / "README.md", "profile", "Profiles: where a step's time goes", body)
    print(body)
    return 0


if __name__ == "__main__":
    sys.exit(main())
