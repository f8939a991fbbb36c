"""mpmlab.io.containment: particles beyond wall faces / inside obstacles / outside the domain interior."""
import dataclasses
import json

import numpy as np
import pytest

import mpmlab
from mpmlab.boundaries import BoxObstacle, FrictionWalls, Plane, Walls
from mpmlab.io.containment import WallPenetration, trajectory_penetration, wall_faces


def water(lo, hi, ppc=1, **kw):
    return mpmlab.Body(shape={"kind": "box", "lo": lo, "hi": hi}, material="newtonian_fluid",
                       params={"sound_speed": 10.0, "viscosity": 0.0}, particles_per_cell=ppc, **kw)


def box_scene(boundaries, dx=0.1, pad=0.1):
    """A [0, 1]^2 tank padded by one cell (domain [-0.1, 1.1]^2, 12 cells)."""
    return mpmlab.Scene(dim=2, dx=dx, domain=([-pad, -pad], [1.0 + pad, 1.0 + pad]),
                        bodies=[water([0.2, 0.2], [0.4, 0.4])], boundaries=boundaries, dt=1e-3)


def test_wall_faces_are_the_innermost_constrained_nodes():
    s = box_scene([Walls(default="slip", faces={"x+": "none"}, thickness=2)])
    f = wall_faces(s)
    assert list(f) == ["x-", "y-", "y+"]                          # x+ is open
    assert f["x-"]["position"] == pytest.approx(0.0)             # origin + (2 - 1) dx
    assert f["y+"]["position"] == pytest.approx(1.0)             # origin + (12 - 2 + 1) dx
    # a thicker friction wall on the floor moves that face inwards; the thinner walls face is replaced
    s = box_scene([Walls(default="slip", thickness=2), FrictionWalls(face="y-", mu=[0.1], thickness=3)])
    f = wall_faces(s)
    assert f["y-"]["position"] == pytest.approx(0.1) and f["y-"]["kind"] == "friction"
    assert f["x-"]["position"] == pytest.approx(0.0)


def test_synthetic_depths_counts_and_faces():
    s = box_scene([Walls(default="slip", thickness=2)])
    acc = WallPenetration(s)
    x = np.full((6, 2), 0.5)
    x[1, 1] = -0.03       # 0.03 m below the floor (y- at 0)
    x[2, 0] = 1.05        # 0.05 m beyond x+ (at 1.0): the deepest
    x[3] = [-0.01, -0.02]  # beyond two faces: its deeper one (y-, 0.02) counts, once
    x[4, 1] = 0.0         # on the face: not beyond
    x[5, 1] = np.nan      # non-finite: not counted (the stability guard's business)
    assert acc.update(x, 7) == 3
    s1 = acc.summary()
    assert s1["particles_beyond_walls"] == s1["particles_beyond_walls_final"] == s1["particles_beyond_walls_ever"] == 3
    assert s1["worst_depth_m"] == pytest.approx(0.05) and s1["worst_depth_dx"] == pytest.approx(0.5)
    assert (s1["worst_step"], s1["worst_particle"], s1["worst_face"]) == (7, 2, "x+")
    assert s1["depth_by_face_dx"] == pytest.approx({"y-": 0.3, "x+": 0.5})
    assert s1["particles_beyond_interior"] == 1                 # x+ 1.05 >= inner hi = 1.1 - 0.05
    assert s1["particles_in_obstacles"] == 0
    # a later frame with one particle beyond: max stays, final and final depth follow the frame
    x2 = np.full((6, 2), 0.5)
    x2[0, 1] = -0.01
    assert acc.update(x2.astype(np.float32), 8) == 1
    s2 = acc.summary()
    counts = (s2["particles_beyond_walls"], s2["particles_beyond_walls_final"], s2["particles_beyond_walls_ever"])
    assert counts == (3, 1, 4)
    assert s2["final_depth_dx"] == pytest.approx(0.1, rel=1e-6) and s2["worst_step"] == 7
    assert s2["particles_beyond_interior_final"] == 0 and s2["frames"] == 2 and s2["last_step"] == 8
    json.dumps(s2)   # plain Python types only


def test_nothing_crossed_gives_zeros():
    s = box_scene([Walls(default="slip", thickness=2)])
    acc = WallPenetration(s)
    acc.update(s.particles().x, 0)
    out = acc.summary()
    assert out["particles_beyond_walls"] == 0 and out["worst_depth_m"] == 0.0 and out["worst_depth_dx"] == 0.0
    assert out["worst_face"] is None and out["worst_step"] is None and out["particles_beyond_interior"] == 0


def test_no_walls_scene_counts_only_the_domain_interior():
    s = box_scene([])
    acc = WallPenetration(s)
    assert acc.faces == {}
    x = np.array([[0.5, -0.05], [0.5, -0.06], [1.05, 0.5], [-0.2, 0.5]])  # inner bounds [-0.05, 1.05)
    assert acc.update(x, 0) == 0
    out = acc.summary()
    assert out["particles_beyond_walls"] == 0 and out["worst_face"] is None and out["wall_faces"] == {}
    assert out["particles_beyond_interior"] == out["particles_beyond_interior_final"] == 3


def test_box_obstacle_and_plane():
    s = box_scene([Walls(default="slip", thickness=2),
                   BoxObstacle(lo=[0.4, -0.5], hi=[0.6, 0.3]),          # a post standing on (through) the floor
                   Plane(point=[0.0, 0.9], normal=[0.0, -1.0])])        # a lid at y = 0.9, free side below
    acc = WallPenetration(s)
    x = np.array([[0.45, 0.1],    # in the post, 0.05 from x-
                  [0.5, 0.28],    # 0.02 below the post's top
                  [0.5, 0.01],    # 0.1 from x- and x+; the post's bottom face lies below the floor and is not used
                  [0.7, 0.95],    # 0.05 above the lid plane
                  [0.7, 0.5]])
    assert acc.update(x, 3) == 4
    out = acc.summary()
    assert out["particles_in_obstacles"] == 3 and out["particles_beyond_walls"] == 1
    assert out["depth_by_face_dx"] == pytest.approx({"box_obstacle[1]:x-": 1.0, "box_obstacle[1]:y+": 0.2,
                                                     "plane[2]": 0.5})
    assert out["worst_depth_m"] == pytest.approx(0.1)
    assert (out["worst_face"], out["worst_particle"]) == ("box_obstacle[1]:x-", 2)
    only_walls = WallPenetration(s, obstacles=False, planes=False)
    assert only_walls.update(x, 3) == 0


def test_update_checks_shapes():
    acc = WallPenetration(box_scene([Walls()]))
    with pytest.raises(ValueError):
        acc.update(np.zeros((3, 3)), 0)
    acc.update(np.zeros((3, 2)) + 0.5, 0)
    with pytest.raises(ValueError):
        acc.update(np.zeros((4, 2)) + 0.5, 1)


def tiny_dam_break_with_a_sunk_particle():
    """dam_break_2d at resolution tiny (dx = 2 cm) plus one particle 0.3-0.4 dx below the floor at t = 0.

    2 x 2 particles per cell: tiny's 1 per cell puts every particle exactly on a stencil boundary (a
    half-integer grid coordinate), where JAX and Warp round apart by ~1e-7 m within 10 steps."""
    from mpmlab.config import build_scene, compose

    cfg = compose(["scene=dam_break_2d", "scene.resolution=tiny", "scene.resolutions.tiny.ppc=4", "transfer=apic",
                   "precision=fp64"])
    scene = build_scene(cfg)
    dx = scene.dx
    b = scene.bodies[0]
    sunk = mpmlab.Body(shape={"kind": "box", "lo": [0.3, -0.4 * dx], "hi": [0.31, -0.3 * dx]}, material=b.material,
                       params=b.params, density=b.density, sampling="random", count=1,
                       particle_volume=(dx / 2) ** 2, name="sunk")
    return dataclasses.replace(scene, bodies=[*scene.bodies, sunk], name="tiny_dam_break_sunk"), int(cfg.steps)


def test_real_run_jax_and_warp_agree_and_report_a_sunk_particle():
    scene, steps = tiny_dam_break_with_a_sunk_particle()
    steps = min(steps, 300)
    every = 10
    P = scene.particles()
    sunk = int(np.nonzero(P.body_id == 1)[0][0])
    depth0 = -P.x[sunk, 1]
    assert 0.3 * scene.dx <= depth0 <= 0.4 * scene.dx

    # JAX: streamed through rollout's on_frame; Warp: from the returned trajectory
    acc = WallPenetration(scene)
    stepper = mpmlab.build_stepper(scene, "jax", "apic", "fp64")
    traj = stepper.rollout(steps=steps, every=every,
                           on_frame=lambda i, s: acc.update(s["x"], int(s.get("step", i * every))))
    a = acc.summary()
    assert a == trajectory_penetration(scene, traj)
    w = mpmlab.simulate(scene, steps, every, "warp", "apic", "fp64")
    b = trajectory_penetration(scene, w)

    assert a["frames"] == b["frames"] == steps // every + 1
    for k in ("particles_beyond_walls", "particles_beyond_walls_final", "particles_beyond_walls_ever",
              "particles_beyond_interior", "worst_step", "worst_particle", "worst_face"):
        assert a[k] == b[k], k
    for k in ("worst_depth_m", "final_depth_m"):
        assert a[k] == pytest.approx(b[k], rel=1e-9, abs=1e-12), k
    # the sunk particle is reported at t = 0, at its depth, through the floor; nothing leaves the interior
    first = WallPenetration(scene)
    first.update(P.x, 0)
    f = first.summary()
    assert f["particles_beyond_walls"] == 1 and f["worst_particle"] == sunk and f["worst_face"] == "y-"
    assert f["worst_depth_m"] == pytest.approx(depth0)
    assert a["particles_beyond_walls"] >= 1 and a["worst_depth_m"] >= depth0
    assert a["particles_beyond_interior"] == 0 and a["worst_depth_dx"] < 0.5
