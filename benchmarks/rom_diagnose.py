"""Why a trained deformation-map ROM's online error exceeds its reconstruction error (benchmarks/rom.md,
"Why the online error is 7x the reconstruction error"): the numbers of that section, from a training of
``benchmarks/rom.py`` and its snapshots.

    python benchmarks/rom_diagnose.py --tag torsion_grip_l7_s02 reconstruction v1w1,v3w3,v5w1,v0w2
    python benchmarks/rom_diagnose.py --tag torsion_grip_l7_s02 rollout v5w0,v5w1,v1w1 [--dt-scale 0.5]
        [--start encoder] [--rcond 1e-3] [--boundary-weight 10]
    python benchmarks/rom_diagnose.py --tag torsion_grip_l7_s02 profile v5w0
    python benchmarks/rom_diagnose.py --tag torsion_grip_l7_s02 one-interval v5w1
    python benchmarks/rom_diagnose.py --tag gravity_l4_s02 equilibrium g21,g26 [--hold 0.1]
    python benchmarks/rom_diagnose.py --tag gravity_l4_s02 consistency g02,g21,g26
    python benchmarks/rom_diagnose.py --tag gravity_l4_s02 swing g26   # also: energy, attachment
    python benchmarks/rom_diagnose.py --tag gravity_l4_s02 damping g26 [--transfers pic,apic,pic:2]
    python benchmarks/rom_diagnose.py --tag gravity_lf100_p480_e85 accounting g26 [--tangent current] [--dt-scale 0.5]
    python benchmarks/rom_diagnose.py --tag poke_l6_p480_e85 poke k01 [--samples 50,all] [--hold 0.5]
        [--forced deepest] [--constrain-kinematic] [--no-poke] [--rcond 1e-2]

* ``reconstruction``: encoder + g on every snapshot of a run: E, E_displacement, E_F (relative to F - I)
  and E_v of the manifold's own tangent velocities, from the encoder's latents (finite differences in time)
  and from the best latent velocity (least squares of the true velocity).
* ``rollout``: the reduced model (Lagrangian quadrature, all points, linear projection unless
  ``--projection``) from Eq. 19's initial state or the encoder's (``--start encoder``), at the full-order
  dt times ``--dt-scale``, with the least squares optionally truncated (``--rcond``) or with the held
  points' rows weighted (``--boundary-weight``, linear projection): E, E_disp, E_v, E_F.
* ``profile``: the mean displacement along the bar in eight bins, full-order against reduced, per snapshot.
* ``one-interval``: from an encoded snapshot, one snapshot interval of reduced steps, against the next
  snapshot and its reconstruction (mm rms).
* ``equilibrium``: from the last snapshot (``--frame``), ``--hold`` seconds of three runs against the
  full-order model started from that snapshot: the full-order model started from the manifold's state
  (g, dg/dx_hat v_hat and F = dg/dX at the encoded latent), and the reduced model from the encoded latent.
  Where the body has come to rest, the first isolates what dg/dX's error in F does to the equilibrium,
  the second adds the restriction to the manifold (mm rms, and the mean displacement along gravity).
* ``swing``: the mean sag of the bar's free tenth per snapshot: full-order, reconstruction, reduced (phase
  and amplitude of the first swings).
* ``energy``: kinetic, elastic (fixed corotated) and gravity's work per snapshot, full-order (its stored
  x, v, F) against reduced (g, dg/dx_hat x_hat_dot and dg/dX along its rollout): where each loses energy.
* ``damping``: the full-order model alone, by transfer and resolution (``--transfers pic,apic,pic:2``):
  the mean sag of the bar's free tenth per snapshot (is the snapshots' slow creep physics or PIC's?).
* ``attachment``: the rms displacement of the points a particle_velocity boundary holds (zero in the
  full-order model) and of the two layers after them, reduced against full-order, per snapshot.
* ``accounting``: the exact energy balance of each reduced step (Lagrangian quadrature, all points, linear
  projection, ``--tangent``), cumulative over the first 60 ms: E_{n+1} - E_n (kinetic + elastic - gravity's
  work, of every material point) is the sum of the MPM step's change of each (the trial x, v and the
  grid's F = (I + dt grad v) F_n), the kinetic energy the velocity fit removes (v_trial onto the tangent
  at x_hat_n), the kinetic energy's change from evaluating v_hat_{n+1} in the tangent at x_hat_{n+1}
  instead, and the elastic and gravity energies' change from the trial state to the manifold's (F = dg/dX,
  g). With the paper's tangent the fourth term is a gain no force makes (benchmarks/rom.md).
* ``poke``: the poke study (benchmarks/rom.md, "Why the poke's reduced model misses the poke"). The
  points initially inside the poke's grid box: their mean displacement in the full-order run, the
  manifold's error there (the encoder's latent, and the best latent, Gauss-Newton on all points) and the
  body's rms error, at the snapshots of the poke; then reduced rollouts (Lagrangian + linear, each
  ``--samples``) over ``--hold`` seconds: the poked points' mean displacement against the full-order one.
  Also the latent's largest excursion from its start, beside the encoder's on the full-order snapshots
  (``--rcond``: the velocity least squares truncated there). ``--forced deepest`` forces the 5 points deepest inside the box instead of the 5 lowest indices;
  ``--constrain-kinematic`` fits the forced samples' rows first while their boundary acts (a
  lexicographic least squares: the free rows only in the forced rows' null space, SVD truncated at
  ``--rcond``, default 1e-3). Both are studies, not options of the stepper.
* ``consistency``: can one map fit both the positions and F of the snapshots? Per particle, the affine
  least-squares fit A of x over its neighbours in X (within 1.8 lattice spacings) is the snapshot's own
  displacement gradient. E_F relative to F - I of: the stored F against A, dg/dX against A, dg/dX against
  the stored F, and (the stencil's own error) dg/dX against the same fit of g's positions; interior
  particles (a full neighbourhood) and all, pooled over the run's snapshots after the first.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
RES = ROOT / "benchmarks" / "results" / "rom"


def setup(tag: str, eval_file: str = "eval.json"):
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    from mpmlab.rom import networks as N
    from mpmlab.rom.snapshots import load_snapshots, study

    ev = json.loads((RES / tag / eval_file).read_text())
    w = N.load(RES / tag / "train" / "rom_weights.safetensors")
    s = study(ev["study"])
    snap = load_snapshots(ev["data"], s, split=None)
    return w, N.to_jax(w.params, jnp.float64), N.to_jax(w.norm, jnp.float64), snap


def truncate_least_squares(rcond):
    """Make the reduced model's least squares (``mpmlab.rom.manifold._lstsq``) drop singular values below
    ``rcond`` of the largest (a study, not an option of the stepper)."""
    import jax.numpy as jnp

    from mpmlab.rom import manifold as Mf

    def truncated(J, r):
        U, S, Vt = jnp.linalg.svd(J, full_matrices=False)
        return Vt.T @ (jnp.where(S > rcond * S[0], 1.0 / S, 0.0) * (U.T @ r))
    Mf._lstsq = truncated


def free_tenth(X):
    """Boolean [N]: the tenth of the points farthest along the body's long axis (the free end)."""
    along = X[:, int(np.argmax(np.ptp(X, 0)))]
    return along > np.percentile(along, 90)


def held_box(fom, X):
    """The reference bounding box [2, d] of the attachment's material points (slightly padded)."""
    Xh = X[held_points(fom)]
    return np.stack([Xh.min(0) - 1e-9, Xh.max(0) + 1e-9])


def held_points(fom):
    """Boolean [N]: the material points of the scene's particle_velocity boundaries (the attachment)."""
    held = np.zeros(len(fom.particles.x), bool)
    for b in fom.scene.boundaries:
        if getattr(b, "stage", "") == "particle_velocity":
            held[np.asarray(b.select(fom.particles.x))] = True
    return held


def weight_held_rows(box, weight):
    """Make the velocity projection (Eqs. 21/23) a weighted least squares: the rows of sample points whose
    reference position lies in ``box`` [2, d] (``held_box``) count ``weight`` times (a study, not an
    option of the stepper: benchmarks/rom.md, "What the gravity online error is made of")."""
    import jax.numpy as jnp

    from mpmlab.rom import manifold as Mf
    from mpmlab.rom import networks as N

    def project_velocity(params, norm, X, z, v):
        _, _, dxdz = N.g_jacobians(params, norm, X, z[None, :])
        wt = jnp.where(jnp.all((X >= box[0]) & (X <= box[1]), -1), weight, 1.0)[:, None]
        return Mf._lstsq((wt[..., None] * dxdz).reshape(-1, dxdz.shape[-1]), (wt * v).reshape(-1))
    Mf.project_velocity = project_velocity


def encoded(params, norm, x):
    import jax.numpy as jnp

    from mpmlab.rom import networks as N

    return np.asarray(N.encode(params, norm, jnp.swapaxes(jnp.asarray(x), 1, 2)))


def reconstruction(a, w, params, norm, snap):
    import jax.numpy as jnp

    from mpmlab.rom import networks as N

    dt = float(snap.time[1] - snap.time[0])
    for run in a.runs:
        k = list(snap.names).index(run)
        X, x, v, F = snap.x[k, 0], snap.x[k], snap.v[k], snap.F[k]
        z = encoded(params, norm, x)
        xg, Fg, dz = (np.asarray(t) for t in N.g_jacobians(params, norm, jnp.asarray(X)[None], jnp.asarray(z)[:, None, :]))
        c = X.mean(0)
        vfd = np.einsum("tpdk,tk->tpd", dz[1:], (z[1:] - z[:-1]) / dt)
        vls = np.stack([(J.reshape(-1, J.shape[-1]) @ np.linalg.lstsq(J.reshape(-1, J.shape[-1]), vt.reshape(-1),
                                                                      rcond=None)[0]).reshape(vt.shape)
                        for J, vt in zip(dz[1:], v[1:])])
        rel = lambda e, ref: float(np.sqrt(np.sum(e ** 2) / np.sum(ref ** 2)))   # noqa: E731
        print(f"{run}: E {rel(xg - x, x - c):.2%}, E_disp {rel(xg - x, x - X):.2%}, E_F {rel(Fg - F, F - np.eye(3)):.1%}, "
              f"E_v from encoder latents {rel(vfd - v[1:], v[1:]):.1%}, best tangent velocity {rel(vls - v[1:], v[1:]):.1%}")


def rollout(a, w, params, norm, snap):
    import jax.numpy as jnp

    from mpmlab.core.errors import SimulationDiverged
    from mpmlab.rom import manifold as Mf
    from mpmlab.rom.evaluate import _sums, build_full_order, errors_of, run_config
    from mpmlab.rom.stepper import reduced_stepper

    if a.rcond:
        truncate_least_squares(a.rcond)
    T = snap.x.shape[1]
    interval = float(snap.time[1] - snap.time[0])
    for run in a.runs:
        k = list(snap.names).index(run)
        _, fom0 = build_full_order(run_config(snap, k), "fp64")
        _, fom = build_full_order(run_config(snap, k), "fp64", float(fom0.dt) * a.dt_scale)
        if a.boundary_weight != 1.0:
            weight_held_rows(held_box(fom, snap.x[k, 0]), a.boundary_weight)
        rom = reduced_stepper(fom, w, samples=len(snap.x[k, 0]), quadrature="lagrangian", projection=a.projection)
        s = rom.init()
        if a.start == "encoder":
            z = jnp.asarray(encoded(params, norm, snap.x[k, :1])[0])
            s = s._replace(z=z, z_prev=z, zdot=Mf.project_velocity(params, norm, rom.X, z, jnp.asarray(fom.particles.v)))
        every = int(round(interval / float(fom.dt)))
        try:
            out = rom.rollout(s, steps=every * (T - 1), every=every)
        except SimulationDiverged as e:
            print(f"{run} (dt x {a.dt_scale:g}): diverged at step {e.step}")
            continue
        _, sums = _sums(params, norm, snap.x[k, 0], out["z"], out["zdot"], snap.x[k], snap.v[k], snap.F[k],
                        snap.x[k, 0].mean(0))
        e = errors_of(sums)
        print(f"{run} (dt x {a.dt_scale:g}, start {a.start}, {a.projection}, held rows x {a.boundary_weight:g}): "
              f"E {e['E']:.2%}, E_disp {e['E_displacement']:.1%}, "
              f"E_v {e['E_v']:.1%}, E_F {e['E_F']:.1%}, latent range [{out['z'].min():.2f}, {out['z'].max():.2f}]")


def profile(a, w, params, norm, snap):
    import jax.numpy as jnp

    from mpmlab.rom import networks as N
    from mpmlab.rom.evaluate import build_full_order, run_config
    from mpmlab.rom.stepper import reduced_stepper

    run = a.runs[0]
    k = list(snap.names).index(run)
    X = snap.x[k, 0]
    _, fom = build_full_order(run_config(snap, k), "fp64")
    rom = reduced_stepper(fom, w, samples=len(X), quadrature="lagrangian", projection="linear")
    every = int(round(float(snap.time[1] - snap.time[0]) / float(fom.dt)))
    out = rom.rollout(steps=every * (snap.x.shape[1] - 1), every=every)
    xr = np.asarray(N.g_apply(params, norm, jnp.asarray(X)[None], jnp.asarray(out["z"])[:, None, :]))
    ax = int(np.argmax(np.ptp(X, 0)))
    bins = np.digitize(X[:, ax], np.linspace(X[:, ax].min(), X[:, ax].max(), 9)[1:-1])
    for t in range(0, snap.x.shape[1], 2):
        row = lambda x: " ".join(f"{1e3 * (x[bins == b, ax] - X[bins == b, ax]).mean():6.2f}" for b in range(8))   # noqa: E731
        print(f"t = {snap.time[t] * 1e3:5.2f} ms  full-order {row(snap.x[k, t])}   reduced {row(xr[t])}  [mm]")


def reduced_rollout(w, snap, k, projection="linear"):
    """(scene, full-order stepper, rollout): run ``k``'s reduced model (Lagrangian quadrature, all points)
    from Eq. 19's state over the snapshots, kept at each snapshot."""
    from mpmlab.rom.evaluate import build_full_order, run_config
    from mpmlab.rom.stepper import reduced_stepper

    scene, fom = build_full_order(run_config(snap, k), "fp64")
    rom = reduced_stepper(fom, w, samples=len(snap.x[k, 0]), quadrature="lagrangian", projection=projection)
    every = int(round(float(snap.time[1] - snap.time[0]) / float(fom.dt)))
    return scene, fom, rom.rollout(steps=every * (snap.x.shape[1] - 1), every=every)


def swing(a, w, params, norm, snap):
    import jax.numpy as jnp

    from mpmlab.rom import networks as N

    for run in a.runs:
        k = list(snap.names).index(run)
        X = snap.x[k, 0]
        scene, _, out = reduced_rollout(w, snap, k, a.projection)
        gdir = np.asarray(scene.gravity) / np.linalg.norm(scene.gravity)
        xr = np.asarray(N.g_apply(params, norm, jnp.asarray(X)[None], jnp.asarray(out["z"])[:, None, :]))
        ze = encoded(params, norm, snap.x[k])
        xe = np.asarray(N.g_apply(params, norm, jnp.asarray(X)[None], jnp.asarray(ze)[:, None, :]))
        sag = lambda x: 1e3 * (x - X) @ gdir                                          # noqa: E731
        tip = free_tenth(X)
        print(f"{run}: mean sag [mm] of the free tenth of the bar over time: full-order / reconstruction / reduced")
        for t in range(snap.x.shape[1]):
            f, e, r = (float(sag(y[t])[tip].mean()) for y in (snap.x[k], xe, xr))
            print(f"  t = {snap.time[t] * 1e3:5.1f} ms  {f:7.3f} {e:7.3f} {r:7.3f}")


def energy(a, w, params, norm, snap):
    import jax.numpy as jnp

    from mpmlab.laws.fixed_corotated.reference import energy as psi
    from mpmlab.rom import networks as N
    from mpmlab.rom.evaluate import run_config

    for run in a.runs:
        k = list(snap.names).index(run)
        X = snap.x[k, 0]
        scene, fom, out = reduced_rollout(w, snap, k, a.projection)
        mat = run_config(snap, k).material
        m, V0 = np.asarray(fom.particles.mass), np.asarray(fom.particles.volume)
        g = np.asarray(scene.gravity)
        xr, Fr, vr = (np.asarray(q) for q in N.g_state(params, norm, jnp.asarray(X)[None], jnp.asarray(out["z"])[:, None, :],
                                                        jnp.asarray(out["zdot"])[:, None, :]))
        total = lambda x, v, F: (0.5 * np.sum(m[:, None] * v ** 2, (-1, -2)),                  # noqa: E731
                                 np.sum(V0 * psi(F, dict(mat.params)), -1), -np.sum(m[:, None] * (x - X) * g, (-1, -2)))
        print(f"{run}: energy [mJ] (kinetic + elastic - gravity work = total), full-order | reduced")
        fo, re = total(snap.x[k], snap.v[k], snap.F[k]), total(xr, vr, Fr)
        for t in range(snap.x.shape[1]):
            row = lambda e: (" + ".join(f"{1e3 * q[t]:7.4f}" for q in e[:2])             # noqa: E731
                             + f" - {-1e3 * e[2][t]:7.4f} = {1e3 * sum(e)[t]:8.4f}")
            print(f"  t = {snap.time[t] * 1e3:5.1f} ms  {row(fo)} | {row(re)}")


def damping(a, w, params, norm, snap):
    import jax

    from mpmlab.build import build_scene
    from mpmlab.rom.evaluate import run_config
    from mpmlab.simulator import build_stepper

    for run in a.runs:
        cfg = run_config(snap, list(snap.names).index(run))
        print(f"{run}: mean sag [mm] of the free tenth of the bar per snapshot, full-order model by transfer and dx")
        for spec in a.transfers:
            transfer, refine = (spec.split(":") + ["1"])[:2]
            refine = int(refine)
            c = cfg.copy()
            c.scene.dx, c.scene.dt = float(c.scene.dx) / refine, float(c.scene.dt) / refine   # same CFL number
            scene = build_scene(c)
            fom = build_stepper(scene, "jax", transfer, "fp64")
            s = fom.init()
            X = np.asarray(s["x"])
            tip = free_tenth(X)
            gdir = np.asarray(scene.gravity) / np.linalg.norm(scene.gravity)
            every = int(round(float(snap.time[1] - snap.time[0]) / float(scene.dt)))
            prm = fom.params
            advance = jax.jit(lambda q: jax.lax.scan(lambda c_, _: (fom.step_fn(c_, prm), None), q, None, length=every)[0])
            sag = []
            for _ in range(snap.x.shape[1]):
                sag.append(1e3 * float(((np.asarray(s["x"]) - X) @ gdir)[tip].mean()))
                s = advance(s)
            print(f"  {transfer}, dx/{refine} ({len(X)} particles): " + " ".join(f"{q:.2f}" for q in sag), flush=True)


def attachment(a, w, params, norm, snap):
    import jax.numpy as jnp

    from mpmlab.rom import networks as N

    for run in a.runs:
        k = list(snap.names).index(run)
        X = snap.x[k, 0]
        _, fom, out = reduced_rollout(w, snap, k, a.projection)
        held = held_points(fom)
        ax = int(np.argmax(np.ptp(X, 0)))                                                  # the long axis
        h = np.ptp(X[held, ax]) / max(1, len(np.unique(np.round(X[held, ax], 9))) - 1)     # layer spacing
        nxt = ~held & (X[:, ax] <= X[held, ax].max() + 2.01 * h)                          # the next two layers
        xr = np.asarray(N.g_apply(params, norm, jnp.asarray(X)[None], jnp.asarray(out["z"])[:, None, :]))
        rms = lambda y, m: 1e3 * np.sqrt(np.mean(np.sum((y - X)[:, m] ** 2, -1), -1))   # noqa: E731
        print(f"{run}: rms displacement [mm] of the {int(held.sum())} held points (full-order: 0) and of the next "
              f"{int(nxt.sum())} (two layers), reduced | full-order")
        for t in range(snap.x.shape[1]):
            print(f"  t = {snap.time[t] * 1e3:5.1f} ms  held {rms(xr, held)[t]:6.3f}   next {rms(xr, nxt)[t]:6.3f} | "
                  f"{rms(snap.x[k], nxt)[t]:6.3f}")


def one_interval(a, w, params, norm, snap):
    import jax.numpy as jnp

    from mpmlab.rom import manifold as Mf
    from mpmlab.rom import networks as N
    from mpmlab.rom.evaluate import build_full_order, run_config
    from mpmlab.rom.stepper import reduced_stepper

    run = a.runs[0]
    k = list(snap.names).index(run)
    _, fom = build_full_order(run_config(snap, k), "fp64")
    rom = reduced_stepper(fom, w, samples=len(snap.x[k, 0]), quadrature="lagrangian", projection="linear")
    every = int(round(float(snap.time[1] - snap.time[0]) / float(fom.dt)))
    z_all = encoded(params, norm, snap.x[k])
    s0 = rom.init()
    g = lambda z: np.asarray(N.g_apply(params, norm, rom.X, jnp.asarray(z)[None]))   # noqa: E731
    rms = lambda e: 1e3 * float(np.sqrt(np.mean(e ** 2)))   # noqa: E731
    print("snapshot: motion to the next | next's reconstruction error | reduced interval's error [mm rms]")
    for t in (0, 1, 2, 4, 8, 12, 20):
        z = jnp.asarray(z_all[t])
        s = s0._replace(z=z, z_prev=jnp.asarray(z_all[max(t - 1, 0)]), t=jnp.asarray(snap.time[t]),
                        zdot=Mf.project_velocity(params, norm, rom.X, z, jnp.asarray(snap.v[k, t])))
        for _ in range(every):
            s = rom.step(s)
        x1 = snap.x[k, t + 1]
        print(f"{t:3d}: {rms(x1 - snap.x[k, t]):.3f} | {rms(g(z_all[t + 1]) - x1):.3f} | {rms(g(s.z) - x1):.3f}")


def equilibrium(a, w, params, norm, snap):
    import jax
    import jax.numpy as jnp

    from mpmlab.rom import manifold as Mf
    from mpmlab.rom import networks as N
    from mpmlab.rom.evaluate import build_full_order, run_config
    from mpmlab.rom.stepper import reduced_stepper

    rms = lambda e: 1e3 * float(np.sqrt(np.mean(np.sum(e ** 2, -1))))   # noqa: E731
    for run in a.runs:
        k = list(snap.names).index(run)
        t = a.frame % snap.x.shape[1]
        X, x, v, F = snap.x[k, 0], snap.x[k, t], snap.v[k, t], snap.F[k, t]
        _, fom = build_full_order(run_config(snap, k), "fp64")
        steps = int(round(a.hold / float(fom.dt)))
        gdir = np.asarray(fom.scene.gravity) / np.linalg.norm(fom.scene.gravity)
        prm = fom.params
        advance = jax.jit(lambda s: jax.lax.scan(lambda c, _: (fom.step_fn(c, prm), None), s, None, length=steps)[0])
        state = lambda x_, v_, F_: {"x": jnp.asarray(x_), "v": jnp.asarray(v_), "law": ({"F": jnp.asarray(F_)},),   # noqa: E731
                                    "t": jnp.asarray(float(snap.time[t]))}
        z = jnp.asarray(encoded(params, norm, snap.x[k, t:t + 1])[0])
        zdot = Mf.project_velocity(params, norm, jnp.asarray(X), z, jnp.asarray(v))
        xg, Fg, vg = (np.asarray(q)[0] for q in N.g_state(params, norm, jnp.asarray(X)[None], z[None, None],
                                                              zdot[None, None]))
        ref = np.asarray(advance(state(x, v, F))["x"])
        fom_g = np.asarray(advance(state(xg, vg, Fg))["x"])
        rom = reduced_stepper(fom, w, samples=len(X), quadrature="lagrangian", projection="linear")
        s = rom.init()._replace(z=z, z_prev=z, zdot=zdot, t=jnp.asarray(float(snap.time[t])))
        zr = rom.rollout(s, steps=steps, every=steps)["z"][-1]
        xr = np.asarray(N.g_apply(params, norm, jnp.asarray(X)[None], jnp.asarray(zr)[None]))[0]
        sag = lambda y: 1e3 * float(np.mean((y - X) @ gdir))   # noqa: E731
        print(f"{run}, t = {snap.time[t]:.2f} s + {a.hold:g} s: full-order moves {rms(ref - x):.3f} mm; "
              f"E_F of dg/dX {np.sqrt(np.sum((Fg - F) ** 2) / np.sum((F - np.eye(3)) ** 2)):.1%}; "
              f"from the manifold's state (x {rms(xg - x):.3f} mm off) the full-order model ends "
              f"{rms(fom_g - ref):.3f} mm away, the reduced model {rms(xr - ref):.3f} mm; "
              f"mean sag full-order {sag(ref):.3f}, full-order from the manifold {sag(fom_g):.3f}, reduced {sag(xr):.3f} mm")


def accounting(a, w, params, norm, snap):
    import jax
    import jax.numpy as jnp

    from mpmlab.laws.fixed_corotated.reference import energy as psi
    from mpmlab.rom import manifold as Mf
    from mpmlab.rom import networks as N
    from mpmlab.rom.evaluate import build_full_order, run_config
    from mpmlab.rom.stepper import ReducedState, ReducedStepper

    names = ("MPM kinetic", "MPM elastic", "MPM gravity", "velocity fit", "tangent at n+1", "elastic to g",
             "gravity to g")
    for run in a.runs:
        k = list(snap.names).index(run)
        cfg = run_config(snap, k)
        _, fom0 = build_full_order(cfg, "fp64")
        scene, fom = build_full_order(cfg, "fp64", float(fom0.dt) * a.dt_scale)
        rom = ReducedStepper(fom, w, samples=fom.particles.count, quadrature="lagrangian", projection="linear",
                             tangent=a.tangent)
        X, m, V0 = rom.X, np.asarray(fom.particles.mass), np.asarray(fom.particles.volume)
        g, mat = np.asarray(scene.gravity), dict(cfg.material.params)

        @jax.jit
        def step(s):
            key, sub = jax.random.split(s.key)
            M = rom._sample(sub)
            x, v, law, prm, rows, _ = rom._lagrangian_points(s, M)
            new = fom.step_fn({"x": x, "v": v, "law": law, "t": s.t}, prm)          # the grid's F updated
            z, vhat = rom._project(Mf, X[M], s.z, s.z_prev, new["x"][rows], new["v"][rows])
            fit = Mf.project_velocity(rom.params, rom.norm, X[M], s.z, new["v"][rows])
            _, v_fit = N.g_velocity(rom.params, rom.norm, X, s.z[None, :], fit[None, :])   # tangent at n
            _, v_old = N.g_velocity(rom.params, rom.norm, X, s.z[None, :], vhat[None, :])
            x1, F1, v1 = N.g_state(rom.params, rom.norm, X, z[None, :], vhat[None, :])
            return (ReducedState(z, vhat, s.z, s.t + rom.dt, key, s.outside, s.unconverged, s.overflow),
                    (x, v, law[0]["F"]), (new["x"], new["v"], new["law"][0]["F"]), v_fit, v_old, (x1, v1, F1))

        def parts(x, v, F):
            return (0.5 * np.sum(m[:, None] * v ** 2), float(np.sum(V0 * psi(np.asarray(F), mat))),
                    -float(np.sum(m[:, None] * (np.asarray(x) - np.asarray(X)) * g)))

        ke = lambda v: 0.5 * float(np.sum(m[:, None] * np.asarray(v) ** 2))               # noqa: E731
        s, acc = rom.init(), np.zeros(len(names))
        every = max(1, int(round(0.005 / float(fom.dt))))
        print(f"{run} (tangent {a.tangent}, dt x {a.dt_scale:g}): energy [mJ] and its changes summed from t = 0")
        for n in range(1, 12 * every + 1):
            s, e0, et, v_fit, v_old, e1 = step(s)
            p0, pt, p1 = parts(*e0), parts(*et), parts(*e1)
            # the fit's loss, then (tangent next) the refit at n+1 against the fit at n, then n -> n+1
            acc += 1e3 * np.array([pt[0] - p0[0], pt[1] - p0[1], pt[2] - p0[2], ke(v_fit) - pt[0],
                                   ke(v_old) - ke(v_fit) + p1[0] - ke(v_old), p1[1] - pt[1], p1[2] - pt[2]])
            if n % every == 0:
                print(f"  t {1e3 * n * float(fom.dt):5.1f} ms  E {1e3 * sum(p1):8.4f}  |  "
                      + ", ".join(f"{q} {c:+.4f}" for q, c in zip(names, acc)), flush=True)


def affine_gradients(X, x, radius):
    """Per particle i, the least-squares A_i with x_j - x_i ~ A_i (X_j - X_i) over its neighbours j in X
    within ``radius``: the displacement gradient the positions x imply. Also the neighbour counts."""
    from scipy.spatial import cKDTree

    nbrs = [[j for j in js if j != i] for i, js in enumerate(cKDTree(X).query_ball_point(X, radius))]
    A = np.stack([np.linalg.lstsq(X[js] - X[i], x[js] - x[i], rcond=None)[0].T for i, js in enumerate(nbrs)])
    return A, np.array([len(js) for js in nbrs])


def consistency(a, w, params, norm, snap):
    import jax.numpy as jnp

    from scipy.spatial import cKDTree

    from mpmlab.rom import networks as N

    h = float(cKDTree(snap.x[0, 0]).query(snap.x[0, 0], 2)[0][:, 1].min())     # the lattice spacing
    I = np.eye(3)
    for run in a.runs:
        k = list(snap.names).index(run)
        X, x, F = snap.x[k, 0], snap.x[k, 1:], snap.F[k, 1:]
        z = encoded(params, norm, snap.x[k])[1:]
        xg, Fg, _ = (np.asarray(t) for t in N.g_jacobians(params, norm, jnp.asarray(X)[None], jnp.asarray(z)[:, None, :]))
        A = np.stack([affine_gradients(X, xt, 1.8 * h)[0] for xt in x])
        Ag = np.stack([affine_gradients(X, xt, 1.8 * h)[0] for xt in xg])
        count = affine_gradients(X, X, 1.8 * h)[1]
        full = count == count.max()
        rel = lambda e, ref, m: float(np.sqrt(np.sum(e[:, m] ** 2) / np.sum((ref[:, m] - I) ** 2)))   # noqa: E731
        for label, m in (("interior", full), ("all", np.ones_like(full))):
            print(f"{run} ({label}, {int(m.sum())} particles): stored F vs affine fit {rel(F - A, A, m):.1%}; "
                  f"dg/dX vs affine fit {rel(Fg - A, A, m):.1%}; dg/dX vs stored F {rel(Fg - F, F, m):.1%}; "
                  f"stencil error (dg/dX vs the fit of g) {rel(Fg - Ag, Fg, m):.1%}")


def poke_box_points(cfg, X):
    """Indices of the points initially inside the scene's ``poke`` box, and each one's depth in it [m]."""
    lo = np.asarray(cfg.scene.boundaries.poke.region.lo, float)
    hi = np.asarray(cfg.scene.boundaries.poke.region.hi, float)
    idx = np.where(np.all((X >= lo) & (X <= hi), axis=1))[0]
    return idx, np.min(np.minimum(X[idx] - lo, hi - X[idx]), axis=1)


def lexicographic(J, r, D, rcond):
    """argmin |J_f y - r_f| over the minimisers of |J_D y - r_D| (D: 1 on the constrained rows, else 0),
    the constrained rows' SVD truncated at ``rcond`` of its largest singular value."""
    import jax.numpy as jnp

    U, s, Vt = jnp.linalg.svd(J * D[:, None], full_matrices=False)
    keep = s > rcond * s[0]
    y0 = Vt.T @ (jnp.where(keep, 1.0 / jnp.where(keep, s, 1.0), 0.0) * (U.T @ (r * D)))
    null = Vt.T * (~keep)[None, :]
    Jf = J * (1.0 - D)[:, None]
    return y0 + null @ jnp.linalg.lstsq(Jf @ null, r * (1.0 - D) - Jf @ y0)[0]


def constrain_kinematic(rom, held, poked, t_end, rcond):
    """Make ``rom``'s linear projection fit its forced samples first (``lexicographic``): the held ones
    always, the poked ones while the poke acts (t < ``t_end``). A study, not an option of the stepper."""
    import jax
    import jax.numpy as jnp

    from mpmlab.rom import networks as N

    cls = type(rom)
    step_impl = cls._step_impl

    def impl(self, s, law=None, fom_params=None):
        self._t_now = s.t
        return step_impl(self, s, law, fom_params)

    def project(self, mf, XM, z, z_prev, x_tr, v_tr, v_step=None):
        d = XM.shape[1]
        on = jnp.concatenate([jnp.ones(held), jnp.where(self._t_now < t_end, 1.0, 0.0) * jnp.ones(poked),
                              jnp.zeros(XM.shape[0] - held - poked)])

        def fit(at):
            _, _, dxdz = N.g_jacobians(self.params, self.norm, XM, at[None, :])
            return lexicographic(dxdz.reshape(-1, dxdz.shape[-1]), v_tr.reshape(-1), jnp.repeat(on, d), rcond)
        vhat = fit(z)
        z1 = z + self.dt * vhat
        return z1, fit(z1)
    rom._step_impl = impl.__get__(rom)
    rom._project = project.__get__(rom)
    rom._step = jax.jit(rom._step_impl)


def poke(a, w, params, norm, snap):
    import jax.numpy as jnp

    from mpmlab.rom import manifold as Mf
    from mpmlab.rom import networks as N
    from mpmlab.rom.evaluate import build_full_order, run_config
    from mpmlab.rom.stepper import reduced_stepper

    if a.rcond and not a.constrain_kinematic:     # the velocity least squares truncated (as ``rollout``)
        truncate_least_squares(a.rcond)
    interval = float(snap.time[1] - snap.time[0])
    for run in a.runs:
        k = list(snap.names).index(run)
        cfg = run_config(snap, k)
        X, x = snap.x[k, 0], snap.x[k]
        pts, depth = poke_box_points(cfg, X)
        t_end = float(cfg.scene.boundaries.poke.t_end)
        frames = int(round(a.hold / interval))
        u = lambda xs: 1e3 * np.linalg.norm(xs[:, pts] - X[pts], axis=-1).mean(1)            # noqa: E731
        rms = lambda e: 1e3 * np.sqrt((e ** 2).sum(-1).mean(-1))                              # noqa: E731
        print(f"{run}: {len(pts)} points inside the poke box (depth {1e3 * depth.min():.2f}-{1e3 * depth.max():.2f} mm)")
        for f in range(0, min(frames, int(round(t_end / interval)) + 1) + 1, 12):
            z = N.encode(params, norm, jnp.asarray(x[f].T))
            zb, _ = Mf.gauss_newton(params, norm, jnp.asarray(X), jnp.asarray(x[f]), z, iterations=20)
            xe, xb = (np.asarray(N.g_apply(params, norm, jnp.asarray(X), q[None, :])) for q in (z, zb))
            print(f"  t {snap.time[f]:.3f} s: poked points moved {u(x[f][None])[0]:.2f} mm; the manifold misses them "
                  f"by {1e3 * np.linalg.norm(xe - x[f], axis=1)[pts].mean():.2f} (encoder) / "
                  f"{1e3 * np.linalg.norm(xb - x[f], axis=1)[pts].mean():.2f} mm (best latent); body rms error "
                  f"{rms(xe - x[f]):.3f} / {rms(xb - x[f]):.3f} mm of {rms(x[f] - X):.3f} mm moved")
        if a.no_poke:                     # the body at rest: the poke's window moved past the rollout
            cfg.scene.boundaries.poke.t_start, cfg.scene.boundaries.poke.t_end = 1e3, 1e3 + 1.0
        _, fom = build_full_order(cfg, "fp64")
        every = int(round(interval / float(fom.dt)))
        for m in a.samples:
            rom = reduced_stepper(fom, w, samples=len(X) if m == "all" else int(m), quadrature="lagrangian",
                                  projection="linear")
            held = [i for i in rom._forced if i not in set(pts.tolist())]
            if a.forced == "deepest":
                forced = np.concatenate([held, pts[np.argsort(-depth, kind="stable")[:5]]]).astype(np.int64)
                free = np.setdiff1d(np.arange(len(X)), forced)
                rom._forced, rom._forced_j, rom._free_np, rom._free = forced, jnp.asarray(forced), free, jnp.asarray(free)
                rom._n_random = rom.samples - len(forced)
            if a.constrain_kinematic:
                constrain_kinematic(rom, len(held), len(rom._forced) - len(held), t_end, a.rcond or 1e-3)
            out = rom.rollout(steps=every * frames, every=every)
            xr = np.stack([rom._positions(np.asarray(z))[0] for z in out["z"]])
            c = X.mean(0)
            e = np.sqrt(np.sum((xr - x[:frames + 1]) ** 2) / np.sum((x[:frames + 1] - c) ** 2))
            zs = np.asarray(out["z"])
            ze = encoded(params, norm, x[:frames + 1])
            far = lambda q: np.linalg.norm(q - q[0], axis=1)                                  # noqa: E731
            print(f"  reduced, M = {m} (forced {a.forced}{', constrained' if a.constrain_kinematic else ''}"
                  f"{f', rcond {a.rcond:g}' if a.rcond and not a.constrain_kinematic else ''}): E {e:.2%} over {a.hold:g} s; "
                  f"latent's largest excursion from its start {far(zs).max():.2f} (the encoder's of the full-order "
                  f"snapshots: {far(ze).max():.2f}), at the end {far(zs)[-1]:.2f} ({far(ze)[-1]:.2f})")
            for f in list(range(0, min(frames, 72) + 1, 12)) + list(range(144, frames + 1, 144)):
                print(f"    t {snap.time[f]:.3f} s: poked points {u(x[f][None])[0]:.2f} mm full-order, "
                      f"{u(xr[f][None])[0]:.2f} mm reduced; body rms error {rms(xr[f] - x[f]):.3f} mm, reduced body "
                      f"moved {rms(xr[f] - X):.3f} mm rms")

def kabsch(P, Q):
    """(R, t) of the rigid motion that best maps points P [N, 3] onto Q (least squares)."""
    cp, cq = P.mean(0), Q.mean(0)
    U, _, Vt = np.linalg.svd((P - cp).T @ (Q - cq))
    S = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ S @ U.T
    return R, cq - R @ cp


def settle(a, w, params, norm, snap):
    """Where the reduced body comes to rest after a poke, and what holds it there (benchmarks/rom.md,
    "Tab. 6: the base slid"): the reduced body against the full-order one, split into a rigid motion and
    the rest, how far the held base points moved, and the strain, every twelfth of ``--hold``."""
    import jax.numpy as jnp

    from mpmlab.rom import networks as N
    from mpmlab.rom.evaluate import build_full_order, run_config
    from mpmlab.rom.stepper import reduced_stepper

    interval = float(snap.time[1] - snap.time[0])
    rms = lambda e: 1e3 * float(np.sqrt(np.mean(np.sum(e ** 2, -1))))              # noqa: E731
    for run in a.runs:
        k = list(snap.names).index(run)
        cfg = run_config(snap, k)
        X, xs = snap.x[k, 0], snap.x[k]
        _, fom = build_full_order(cfg, "fp64")
        base = held_points(fom)
        every = int(round(interval / float(fom.dt)))
        frames = int(round(a.hold / interval))
        rom = reduced_stepper(fom, w, samples=int(a.samples[0]), quadrature="lagrangian", projection=a.projection,
                              kinematic=a.kinematic, hold_steps=a.hold_steps)
        out = rom.rollout(steps=every * frames, every=every)
        zs = np.asarray(out["z"])
        c = X.mean(0)
        print(f"{run}: {len(X)} points, {int(base.sum())} held at the base; reduced M = {a.samples[0]}, {a.projection}, "
              f"kinematic {a.kinematic}{f' over {a.hold_steps:g} steps' if a.hold_steps != 1 else ''}, "
              f"{len(rom._forced)} forced samples ({int(base[rom._forced].sum())} of them at the base)")
        for f in range(0, frames + 1, max(1, frames // 12)):
            xr = rom._positions(zs[f])[0]
            xf = xs[f]
            Fr = np.asarray(N.g_jacobians(params, norm, jnp.asarray(X), jnp.asarray(zs[f])[None, :])[1])
            R, t = kabsch(xf, xr)                        # the reduced body against the full-order one, rigidly
            rigid = xf @ R.T + t
            ang = np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1)))
            E = np.sqrt(np.sum((xr - xf) ** 2) / np.sum((xf - c) ** 2))
            print(f"  t {snap.time[f]:6.3f} s: E {E:6.2%}; reduced - full-order {rms(xr - xf):.4f} mm rms, of which "
                  f"non-rigid {rms(xr - rigid):.4f} mm (rigid part: {1e3 * np.linalg.norm(t + (R - np.eye(3)) @ c):.4f} mm "
                  f"at the centroid, {ang:.4f} deg); base points moved {rms(xr[base] - X[base]):.4f} mm (full-order "
                  f"{rms(xf[base] - X[base]):.4f}); |dg/dX - I| {np.sqrt(np.mean(np.sum((Fr - np.eye(3)) ** 2, (1, 2)))):.2e} "
                  f"(full-order |F - I| {np.sqrt(np.mean(np.sum((snap.F[k, f] - np.eye(3)) ** 2, (1, 2)))):.2e}); "
                  f"|x_hat - x_hat(0)| {np.linalg.norm(zs[f] - zs[0]):.3f}")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("what", choices=("reconstruction", "rollout", "profile", "one-interval", "equilibrium",
                                           "consistency", "swing", "energy", "attachment",
                                           "damping", "accounting", "poke", "settle"))
    ap.add_argument("runs", type=lambda s: s.split(","))
    ap.add_argument("--tag", default="torsion_grip_l7_s02")
    ap.add_argument("--dt-scale", dest="dt_scale", type=float, default=1.0)
    ap.add_argument("--start", choices=("eq19", "encoder"), default="eq19")
    ap.add_argument("--rcond", type=float, default=0.0)
    ap.add_argument("--frame", type=int, default=-1, help="equilibrium: the snapshot to start from")
    ap.add_argument("--hold", type=float, default=0.1, help="equilibrium: seconds to run from it; poke: seconds of the rollouts")
    ap.add_argument("--projection", choices=("linear", "nonlinear"), default="linear")
    ap.add_argument("--transfers", type=lambda q: q.split(","), default=["pic", "apic", "pic:2"],
                    help="damping: full-order transfers, each optionally :k for dx/k (and dt/k)")
    ap.add_argument("--tangent", choices=("next", "current"), default="next",
                    help="accounting: where the velocity fit takes dg/dx_hat (mpmlab.rom.stepper)")
    ap.add_argument("--boundary-weight", dest="boundary_weight", type=float, default=1.0,
                    help="rollout: weight of the attachment's rows in the velocity least squares (1: Eqs. 21/23)")
    ap.add_argument("--samples", type=lambda q: q.split(","), default=["50", "all"], help="poke: |M| of the rollouts")
    ap.add_argument("--forced", choices=("lowest", "deepest"), default="lowest",
                    help="poke: which 5 points of the poke box are forced samples (the stepper: the lowest indices)")
    ap.add_argument("--constrain-kinematic", dest="constrain_kinematic", action="store_true",
                    help="poke: fit the forced samples' rows first while their boundary acts (a study)")
    ap.add_argument("--no-poke", dest="no_poke", action="store_true",
                    help="poke: the rollouts without the poke (a body at rest should stay at rest)")
    ap.add_argument("--kinematic", default="position", choices=("position", "velocity"),
                    help="settle: how the reduced model holds particle_velocity points (mpmlab.rom.kinematic)")
    ap.add_argument("--hold-steps", dest="hold_steps", type=float, default=1.0,
                    help="settle: the position-level hold closes a held point's position error over this many steps")
    ap.add_argument("--eval", default="eval.json", help="the evaluation whose study and snapshots to use "
                    "(e.g. eval_continual.json for the continual poking run)")
    a = ap.parse_args()
    w, params, norm, snap = setup(a.tag, a.eval)
    {"reconstruction": reconstruction, "rollout": rollout, "profile": profile,
     "one-interval": one_interval, "equilibrium": equilibrium, "consistency": consistency, "swing": swing,
     "energy": energy, "attachment": attachment, "damping": damping,
     "accounting": accounting, "poke": poke, "settle": settle}[a.what](a, w, params, norm, snap)


if __name__ == "__main__":
    main()
