"""Warp implementations of the built-in boundaries (``mpmlab.boundaries``).

Domain walls are fused into the grid-update kernel (their face kinds are kernel arguments); the
others are small kernels launched only when the scene has them. Node sets and normals come from the
same NumPy code as the JAX side (``mpmlab.backends.boundary_geometry``).

Each factory returns the fast, in-place implementation and, as ``tape()``, its tape-safe one for
the differentiable path (``grad.py``), which asks every boundary for it instead of knowing them by
name (a plugin boundary is differentiable on Warp when its factory gives a ``tape``). The protocol,
``TapeBoundary`` (a namespace), by ``stage``:

* every stage: ``params`` ``{name: numpy array}``, the boundary's differentiable data (its entry of
  ``controls()["boundary"]``), and ``param_kinds`` ``{name: "scalar" | "vec"}`` (a ``vec`` entry is
  one D-vector, passed as a ``[1]`` array of vectors);
* ``"walls"``: ``codes`` and ``thickness``, fused into the grid update;
* ``"grid"``: ``grid(grid_v, out, p, t)`` writes every node of ``out`` (out of place: the tape never
  sees an overwrite); ``p`` holds the Warp arrays of ``params``, ``t`` is the step's start time;
* ``"particle_velocity"``: ``particles(x_in, x, v, p, t_end, dt, x_out, v_out) -> bool`` (False:
  inactive at this time, nothing written);
* ``"particle_force"``: ``force(ext, p, t, ctl, x)`` adds (atomically) into the external forces;
  ``ctl`` gives the differentiable controls (``ctl.mass``, ...), ``x`` the particles' positions at
  the start of the step (a force of the current position reads them: ``body_force``). The fast
  path's ``add_force(ext, t, x)`` gets the same ``x``.
"""

from functools import lru_cache
from types import SimpleNamespace

import numpy as np
import warp as wp

from ..boundary_geometry import box_obstacle_normals, friction_node_mu_index, wall_masks
from .kernels import WALL_CODES
from .types import warp_types


@lru_cache(maxsize=None)
def _coulomb_func(dim, precision):
    T = warp_types(dim, precision)
    scalar, vec = T.scalar, T.vec

    @wp.func
    def coulomb(v: vec, n: vec, mu: scalar):
        """JAX-MPM Eqs. 35-36 against outward normal n (into the obstacle); identity unless v.n > 0."""
        vn = wp.dot(v, n)
        out = v
        if vn > scalar(0.0):
            vt = v - vn * n
            vt_norm = wp.length(vt)
            if vt_norm <= mu * vn:
                out = vec()
            else:
                out = vt * (scalar(1.0) - mu * vn / vt_norm)
        return out

    return coulomb


@lru_cache(maxsize=None)
def _node_funcs(dim, precision):
    """The per-node velocity maps of planes and obstacles, shared by the fast kernels below and the
    tape-safe kernels (``_tape_kernels``). They build new vectors (no component overwrite),
    so Warp's adjoint is right."""
    T = warp_types(dim, precision)
    scalar, vec = T.scalar, T.vec
    coulomb = _coulomb_func(dim, precision)

    @wp.func
    def plane_velocity(v: vec, n_in: vec, kind: int, mu: scalar):
        out = v
        if kind == 1:
            out = vec()
        elif kind == 2:
            out = v - wp.dot(v, n_in) * n_in
        else:
            out = coulomb(v, -n_in, mu)
        return out

    @wp.func
    def obstacle_velocity(v: vec, n: vec):
        out = v
        vn = wp.dot(v, n)
        if vn < scalar(0.0):
            out = v - vn * n   # JAX-MPM Eq. 33, only into the box
        return out

    return SimpleNamespace(plane=plane_velocity, obstacle=obstacle_velocity)


@lru_cache(maxsize=None)
def _node_kernels(dim, precision):
    T = warp_types(dim, precision)
    scalar, vec = T.scalar, T.vec
    coulomb = _coulomb_func(dim, precision)
    F = _node_funcs(dim, precision)

    @wp.kernel(module="unique")
    def friction(grid_v: wp.array(dtype=vec), nodes: wp.array(dtype=int), mu_index: wp.array(dtype=int),
                 mu: wp.array(dtype=scalar), n: vec, out: wp.array(dtype=vec)):
        k = wp.tid()
        i = nodes[k]
        out[i] = coulomb(grid_v[i], n, mu[mu_index[k]])

    @wp.kernel(module="unique")
    def plane(grid_v: wp.array(dtype=vec), nodes: wp.array(dtype=int), n_in: vec, kind: int,
              friction: wp.array(dtype=scalar), out: wp.array(dtype=vec)):
        k = wp.tid()
        i = nodes[k]
        out[i] = F.plane(grid_v[i], n_in, kind, friction[0])

    @wp.kernel(module="unique")
    def obstacle(grid_v: wp.array(dtype=vec), nodes: wp.array(dtype=int), normals: wp.array(dtype=vec),
                 out: wp.array(dtype=vec)):
        k = wp.tid()
        i = nodes[k]
        out[i] = F.obstacle(grid_v[i], normals[k])

    @wp.kernel(module="unique")
    def set_velocity(v: wp.array(dtype=vec), x_in: wp.array(dtype=vec), x: wp.array(dtype=vec),
                     idx: wp.array(dtype=int), target: wp.array(dtype=vec), dt: scalar):
        k = wp.tid()
        p = idx[k]
        v[p] = target[0]
        x[p] = x_in[p] + dt * target[0]   # a prescribed particle also moves with its velocity

    @wp.kernel(module="unique")
    def add_force(ext: wp.array(dtype=vec), idx: wp.array(dtype=int), share: wp.array(dtype=scalar),
                  force: wp.array(dtype=vec)):
        k = wp.tid()
        ext[idx[k]] = ext[idx[k]] + share[k] * force[0]

    return SimpleNamespace(friction=friction, plane=plane, obstacle=obstacle, set_velocity=set_velocity,
                           add_force=add_force)


class _GridBC:
    """A grid boundary acting on a node subset; ``apply(grid_v, t)`` updates grid_v."""

    def __init__(self, stepper, nodes):
        self.stepper = stepper
        self.nodes = wp.array(np.asarray(nodes, dtype=np.int32), dtype=int, device=stepper.device)
        self.K = _node_kernels(stepper.dim, stepper.precision)


@lru_cache(maxsize=None)
def _tape_kernels(dim: int, precision: str):
    """Out-of-place versions of ``_node_kernels`` over every node / particle (a node or particle outside
    the boundary's set is copied), so the tape never sees an overwrite."""
    T = warp_types(dim, precision)
    scalar, vec = T.scalar, T.vec
    coulomb = _coulomb_func(dim, precision)
    F = _node_funcs(dim, precision)

    @wp.kernel(module="unique")
    def friction(grid_v: wp.array(dtype=vec), mu_index: wp.array(dtype=int), mu: wp.array(dtype=scalar), n: vec,
                 out: wp.array(dtype=vec)):
        i = wp.tid()
        v = grid_v[i]
        k = mu_index[i]
        if k >= 0:
            v = coulomb(v, n, mu[k])                  # JAX-MPM Eqs. 35-36
        out[i] = v

    @wp.kernel(module="unique")
    def plane(grid_v: wp.array(dtype=vec), behind: wp.array(dtype=int), n_in: vec, kind: int,
              friction: wp.array(dtype=scalar), out: wp.array(dtype=vec)):
        i = wp.tid()
        v = grid_v[i]
        if behind[i] != 0:
            v = F.plane(v, n_in, kind, friction[0])
        out[i] = v

    @wp.kernel(module="unique")
    def obstacle(grid_v: wp.array(dtype=vec), normal_index: wp.array(dtype=int), normals: wp.array(dtype=vec),
                 out: wp.array(dtype=vec)):
        i = wp.tid()
        v = grid_v[i]
        k = normal_index[i]
        if k >= 0:
            v = F.obstacle(v, normals[k])
        out[i] = v

    @wp.kernel(module="unique")
    def set_velocity(x_in: wp.array(dtype=vec), x: wp.array(dtype=vec), v: wp.array(dtype=vec),
                     selected: wp.array(dtype=int), target: wp.array(dtype=vec), dt: scalar,
                     x_out: wp.array(dtype=vec), v_out: wp.array(dtype=vec)):
        p = wp.tid()
        if selected[p] != 0:
            v_out[p] = target[0]
            x_out[p] = x_in[p] + dt * target[0]       # a prescribed particle moves with its velocity
        else:
            v_out[p] = v[p]
            x_out[p] = x[p]

    @wp.kernel(module="unique")
    def add_force(ext: wp.array(dtype=vec), idx: wp.array(dtype=int), share: wp.array(dtype=scalar),
                  force: wp.array(dtype=vec)):
        k = wp.tid()
        wp.atomic_add(ext, idx[k], share[k] * force[0])

    return SimpleNamespace(friction=friction, plane=plane, obstacle=obstacle, set_velocity=set_velocity,
                           add_force=add_force)


def walls(b, scene, stepper):
    codes = [WALL_CODES[k] for k in b.face_kinds(scene.dim)]
    return SimpleNamespace(kind="walls", codes=codes, thickness=b.thickness, params={},
                           tape=lambda: SimpleNamespace(stage="walls", params={}, param_kinds={}, codes=codes,
                                                        thickness=int(b.thickness)))


def friction_walls(b, scene, stepper):
    T = stepper.T
    mask = wall_masks(scene, b.thickness)[b.face]
    nodes = np.nonzero(mask)[0]
    bc = _GridBC(stepper, nodes)
    bc.mu_index = wp.array(friction_node_mu_index(b, scene)[nodes].astype(np.int32), dtype=int, device=stepper.device)
    n = np.zeros(scene.dim); n[b.axis] = b.side
    bc.n = T.vec(*n)
    bc.params = {"mu": wp.array(np.asarray(b.mu, float), dtype=T.scalar, device=stepper.device, requires_grad=False)}

    def apply(grid_v, t):
        wp.launch(bc.K.friction, dim=len(nodes), inputs=[grid_v, bc.nodes, bc.mu_index, bc.params["mu"], bc.n, grid_v],
                  device=stepper.device)

    def tape():
        idx = np.where(mask, friction_node_mu_index(b, scene), -1).astype(np.int32)
        index = wp.array(idx, dtype=int, device=stepper.device)
        K = _tape_kernels(stepper.dim, stepper.precision)

        def grid(grid_v, out, p, t):
            wp.launch(K.friction, dim=len(idx), inputs=[grid_v, index, p["mu"], bc.n, out], device=stepper.device)

        return SimpleNamespace(stage="grid", params={"mu": np.asarray(b.mu, float)}, param_kinds={"mu": "scalar"},
                               grid=grid)

    bc.apply = apply
    bc.tape = tape
    bc.kind = "grid"
    return bc


def plane(b, scene, stepper):
    from ..boundary_geometry import node_positions

    T = stepper.T
    n_in = b.unit_normal()
    behind = (node_positions(scene) - np.asarray(b.point, float)) @ n_in < 0
    nodes = np.nonzero(behind)[0]
    bc = _GridBC(stepper, nodes)
    kind = {"sticky": 1, "slip": 2, "separate": 3}[b.condition]
    bc.params = {"friction": wp.array([b.friction], dtype=T.scalar, device=stepper.device)}

    def apply(grid_v, t):
        if len(nodes):
            wp.launch(bc.K.plane, dim=len(nodes), inputs=[grid_v, bc.nodes, T.vec(*n_in), kind, bc.params["friction"], grid_v],
                      device=stepper.device)

    def tape():
        index = wp.array(behind.astype(np.int32), dtype=int, device=stepper.device)
        K = _tape_kernels(stepper.dim, stepper.precision)

        def grid(grid_v, out, p, t):
            wp.launch(K.plane, dim=len(behind), inputs=[grid_v, index, T.vec(*n_in), kind, p["friction"], out],
                      device=stepper.device)

        return SimpleNamespace(stage="grid", params={"friction": np.asarray(b.friction, float)},
                               param_kinds={"friction": "scalar"}, grid=grid)

    bc.apply = apply
    bc.tape = tape
    bc.kind = "grid"
    return bc


def box_obstacle(b, scene, stepper):
    inside, normals = box_obstacle_normals(b, scene)
    nodes = np.nonzero(inside)[0]
    bc = _GridBC(stepper, nodes)
    bc.normals = wp.array(normals[nodes], dtype=stepper.T.vec, device=stepper.device)
    bc.params = {}

    def apply(grid_v, t):
        if len(nodes):
            wp.launch(bc.K.obstacle, dim=len(nodes), inputs=[grid_v, bc.nodes, bc.normals, grid_v], device=stepper.device)

    def tape():
        idx = np.full(len(inside), -1, np.int32)
        idx[nodes] = np.arange(len(nodes), dtype=np.int32)
        index = wp.array(idx, dtype=int, device=stepper.device)
        normals_ = wp.array(normals[nodes] if len(nodes) else np.zeros((1, scene.dim)), dtype=stepper.T.vec,
                            device=stepper.device)
        K = _tape_kernels(stepper.dim, stepper.precision)

        def grid(grid_v, out, p, t):
            wp.launch(K.obstacle, dim=len(idx), inputs=[grid_v, index, normals_, out], device=stepper.device)

        return SimpleNamespace(stage="grid", params={}, param_kinds={}, grid=grid)

    bc.apply = apply
    bc.tape = tape
    bc.kind = "grid"
    return bc


@lru_cache(maxsize=None)
def _rigid_kernels(dim: int, precision: str):
    """particle_velocity with an angular velocity (``mpmlab.boundaries.ParticleVelocity``): the step ending
    at t_end moves a particle exactly rigidly, x <- c_end + R(omega dt) (x - c_end + v0 dt), with c_end =
    c0 + v0 (t_end - t_start), and gives it the rigid velocity v0 + omega x (x - c_end). omega is one
    scalar in 2D, one vector in 3D (a [1] array: a differentiable control)."""
    T = warp_types(dim, precision)
    scalar, vec = T.scalar, T.vec
    W = scalar if dim == 2 else vec

    @wp.func
    def rotate(r: vec, a: W):
        """R(a) r: by the angle a in 2D, by Rodrigues' formula for the rotation vector a in 3D."""
        if wp.static(dim == 2):
            ca = wp.cos(a)
            sa = wp.sin(a)
            return vec(ca * r[0] - sa * r[1], sa * r[0] + ca * r[1])
        else:
            th2 = wp.dot(a, a)
            s1 = scalar(1.0) - th2 / scalar(6.0)           # sin t / t and (1 - cos t) / t^2, series near 0
            s2 = scalar(0.5) - th2 / scalar(24.0)
            if th2 > scalar(1.0e-6):
                th = wp.sqrt(th2)
                s1 = wp.sin(th) / th
                s2 = (scalar(1.0) - wp.cos(th)) / th2
            ar = wp.cross(a, r)
            return r + s1 * ar + s2 * wp.cross(a, ar)

    @wp.func
    def spin(w: W, r: vec):
        """omega x r (2D: omega a scalar)."""
        if wp.static(dim == 2):
            return w * vec(-r[1], r[0])
        else:
            return wp.cross(w, r)

    @wp.func
    def motion(xp: vec, v0: vec, w: W, c0: vec, tau: scalar, dt: scalar):
        c_end = c0 + v0 * tau
        r1 = rotate(xp - c_end + v0 * dt, w * dt)
        return c_end + r1, v0 + spin(w, r1)

    @wp.kernel(module="unique")
    def fast(v: wp.array(dtype=vec), x_in: wp.array(dtype=vec), x: wp.array(dtype=vec), idx: wp.array(dtype=int),
             v0: wp.array(dtype=vec), w: wp.array(dtype=W), c0: vec, tau: scalar, dt: scalar):
        p = idx[wp.tid()]
        xe, ve = motion(x_in[p], v0[0], w[0], c0, tau, dt)
        x[p] = xe
        v[p] = ve

    @wp.kernel(module="unique")
    def tape(x_in: wp.array(dtype=vec), x: wp.array(dtype=vec), v: wp.array(dtype=vec), selected: wp.array(dtype=int),
             v0: wp.array(dtype=vec), w: wp.array(dtype=W), c0: vec, tau: scalar, dt: scalar,
             x_out: wp.array(dtype=vec), v_out: wp.array(dtype=vec)):
        p = wp.tid()
        if selected[p] != 0:
            xe, ve = motion(x_in[p], v0[0], w[0], c0, tau, dt)
            x_out[p] = xe
            v_out[p] = ve
        else:
            v_out[p] = v[p]
            x_out[p] = x[p]

    @wp.func
    def node_velocity(v: vec, y: vec, lo: vec, hi: vec, v0: vec, w: W, c0: vec, tau: scalar):
        """grid_velocity at one node y: the rigid velocity when y, carried back to the reference frame (the
        motion placed at time tau), is inside the box [lo, hi]; else v unchanged."""
        r = y - (c0 + v0 * tau)
        ref = c0 + rotate(r, -w * tau)
        inside = int(1)
        for a in range(dim):
            if ref[a] < lo[a] or ref[a] > hi[a]:
                inside = 0
        if inside != 0:
            return v0 + spin(w, r)
        return v

    @wp.kernel(module="unique")
    def grid(grid_v: wp.array(dtype=vec), node_x: wp.array(dtype=vec), lo: vec, hi: vec, v0: wp.array(dtype=vec),
             w: wp.array(dtype=W), c0: vec, tau: scalar, active: int, out: wp.array(dtype=vec)):
        """grid_velocity over every node, out of place (tape-safe; in place when out is grid_v)."""
        i = wp.tid()
        v = grid_v[i]
        if active != 0:
            v = node_velocity(v, node_x[i], lo, hi, v0[0], w[0], c0, tau)
        out[i] = v

    @wp.kernel(module="unique")
    def grid_window(grid_v: wp.array(dtype=vec), node_x: wp.array(dtype=vec), lo: vec, hi: vec,
                    v0: wp.array(dtype=vec), w: wp.array(dtype=W), c0: vec, tau: scalar, first: wp.vec3i,
                    shape: wp.vec3i):
        """grid_velocity in place over a window of nodes (first + tid, in the C-order grid of ``shape``): the
        fast path visits only the nodes the moved box can reach, not the whole grid."""
        a, b, c = wp.tid()
        i = (first[0] + a) * shape[1] + first[1] + b
        if wp.static(dim == 3):
            i = i * shape[2] + first[2] + c
        grid_v[i] = node_velocity(grid_v[i], node_x[i], lo, hi, v0[0], w[0], c0, tau)

    return SimpleNamespace(fast=fast, tape=tape, grid=grid, grid_window=grid_window, W=W)


def particle_velocity(b, scene, stepper):
    if b.rotating:
        return _rigid_particle_velocity(b, scene, stepper)
    idx = b.select(scene.particles().x)
    bc = SimpleNamespace(kind="particle_velocity")
    K = _node_kernels(stepper.dim, stepper.precision)
    ia = wp.array(idx.astype(np.int32), dtype=int, device=stepper.device)
    bc.params = {"velocity": wp.array([b.velocity], dtype=stepper.T.vec, device=stepper.device)}

    def apply_particles(v, x_in, x, t):
        if b.t_start < t <= b.t_end:
            wp.launch(K.set_velocity, dim=len(idx), inputs=[v, x_in, x, ia, bc.params["velocity"], stepper.dt_s],
                      device=stepper.device)

    def tape():
        N = len(scene.particles().x)
        sel = np.zeros(N, np.int32)
        sel[idx] = 1
        selected = wp.array(sel, dtype=int, device=stepper.device)
        TK = _tape_kernels(stepper.dim, stepper.precision)

        def particles(x_in, x, v, p, t_end, dt, x_out, v_out):
            if not b.t_start < t_end <= b.t_end:
                return False
            wp.launch(TK.set_velocity, dim=N, inputs=[x_in, x, v, selected, p["velocity"], dt, x_out, v_out],
                      device=stepper.device)
            return True

        return SimpleNamespace(stage="particle_velocity", params={"velocity": np.asarray(b.velocity, float)},
                               param_kinds={"velocity": "vec"}, particles=particles)

    bc.apply_particles = apply_particles
    bc.tape = tape
    return bc


def _rigid_particle_velocity(b, scene, stepper):
    x0 = scene.particles().x
    idx = b.select(x0)
    T = stepper.T
    R = _rigid_kernels(stepper.dim, stepper.precision)
    dev = stepper.device
    c0 = T.vec(*b.rotation_center(x0))
    w_host = np.asarray(b.angular_velocity, float).reshape(-1)
    bc = SimpleNamespace(kind="particle_velocity")
    ia = wp.array(idx.astype(np.int32), dtype=int, device=dev)
    bc.params = {"velocity": wp.array([b.velocity], dtype=T.vec, device=dev),
                 "angular_velocity": wp.array(w_host if stepper.dim == 2 else [w_host], dtype=R.W, device=dev)}

    def apply_particles(v, x_in, x, t):
        if b.t_start < t <= b.t_end:
            wp.launch(R.fast, dim=len(idx), inputs=[v, x_in, x, ia, bc.params["velocity"], bc.params["angular_velocity"],
                                                    c0, T.scalar(t - b.t_start), stepper.dt_s], device=dev)

    def tape():
        N = len(x0)
        sel = np.zeros(N, np.int32)
        sel[idx] = 1
        selected = wp.array(sel, dtype=int, device=dev)

        def particles(x_in, x, v, p, t_end, dt, x_out, v_out):
            if not b.t_start < t_end <= b.t_end:
                return False
            wp.launch(R.tape, dim=N, inputs=[x_in, x, v, selected, p["velocity"], p["angular_velocity"], c0,
                                             T.scalar(t_end - b.t_start), dt, x_out, v_out], device=dev)
            return True

        return SimpleNamespace(stage="particle_velocity",
                               params={"velocity": np.asarray(b.velocity, float), "angular_velocity": w_host},
                               param_kinds={"velocity": "vec", "angular_velocity": "scalar" if stepper.dim == 2 else "vec"},
                               particles=particles)

    bc.apply_particles = apply_particles
    bc.tape = tape
    return bc


def _rotate_host(r: np.ndarray, a: np.ndarray) -> np.ndarray:
    """R(a) r on the host (rows of r), as the kernels' ``rotate``: an angle in 2D, a rotation vector in 3D."""
    if r.shape[-1] == 2:
        ca, sa = np.cos(a), np.sin(a)
        return np.stack([ca * r[:, 0] - sa * r[:, 1], sa * r[:, 0] + ca * r[:, 1]], -1)
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(a).apply(r)


def grid_velocity(b, scene, stepper):
    """``mpmlab.boundaries.GridVelocity``: in place over the nodes the moved box can reach (the fast path),
    over every node out of place on the tape."""
    from ..boundary_geometry import node_positions

    T, dev = stepper.T, stepper.device
    R = _rigid_kernels(stepper.dim, stepper.precision)
    x0 = scene.particles().x
    c0_host = b.rotation_center(x0)
    c0 = T.vec(*c0_host)
    lo, hi = (T.vec(*a) for a in b.box(scene.dim))
    node_x = wp.array(node_positions(scene), dtype=T.vec, device=dev)
    G = node_x.shape[0]
    zero_w = np.zeros(()) if stepper.dim == 2 else np.zeros(3)
    w_host = np.asarray(b.angular_velocity, float).reshape(zero_w.shape) if b.rotating else zero_w
    wrap_w = lambda w: wp.array(w.reshape(-1) if stepper.dim == 2 else [w], dtype=R.W, device=dev)
    bc = SimpleNamespace(kind="grid")
    bc.params = {"velocity": wp.array([b.velocity], dtype=T.vec, device=dev)}
    if b.rotating:
        bc.params["angular_velocity"] = wrap_w(w_host)
    still = wrap_w(zero_w)        # a translation: omega = 0, not a control

    def launch(grid_v, out, p, t):
        on = int(b.t_start <= t < b.t_end)
        wp.launch(R.grid, dim=G, inputs=[grid_v, node_x, lo, hi, p["velocity"], p.get("angular_velocity", still), c0,
                                         T.scalar(t - b.t_start), on, out], device=dev)

    box_corners = np.stack(np.meshgrid(*zip(*(np.asarray(a, float) for a in b.box(scene.dim))), indexing="ij"),
                           -1).reshape(-1, scene.dim)
    shape = np.asarray(scene.grid_shape)

    def window(p, t):
        """(first node, extent) of the grid's nodes within one cell of the moved box's bounding box at t."""
        tau = t - b.t_start
        v0 = p["velocity"].numpy()[0].astype(float)
        w = p["angular_velocity"].numpy().reshape(w_host.shape).astype(float) if b.rotating else zero_w
        y = _rotate_host(box_corners - c0_host, w * tau) + c0_host + v0 * tau
        first = np.clip(np.floor((y.min(0) - scene.origin) / scene.dx).astype(int) - 1, 0, shape - 1)
        last = np.clip(np.ceil((y.max(0) - scene.origin) / scene.dx).astype(int) + 1, 0, shape - 1)
        return first, last - first + 1

    def apply(grid_v, t):
        """In place over the window the box can reach (the same node test as ``launch``, on fewer nodes:
        a thin grip on a tall body no longer costs a pass over the whole grid)."""
        if not b.t_start <= t < b.t_end:
            return
        p = bc.params
        first, extent = window(p, t)
        pad = lambda a, fill: wp.vec3i(*(list(a) + [fill] * (3 - len(a))))
        wp.launch(R.grid_window, dim=tuple(int(n) for n in extent), inputs=[
            grid_v, node_x, lo, hi, p["velocity"], p.get("angular_velocity", still), c0, T.scalar(t - b.t_start),
            pad(first, 0), pad(shape, 1)], device=dev)

    def tape():
        params = {"velocity": np.asarray(b.velocity, float)}
        kinds = {"velocity": "vec"}
        if b.rotating:
            params["angular_velocity"], kinds["angular_velocity"] = w_host, "scalar" if stepper.dim == 2 else "vec"
        return SimpleNamespace(stage="grid", params=params, param_kinds=kinds, grid=launch)

    bc.apply = apply
    bc.tape = tape
    return bc


def particle_load(b, scene, stepper):
    P = scene.particles()
    idx, part = b.shares(P)
    bc = SimpleNamespace(kind="particle_force")
    K = _node_kernels(stepper.dim, stepper.precision)
    ia = wp.array(idx.astype(np.int32), dtype=int, device=stepper.device)
    share = wp.array(part, dtype=stepper.T.scalar, device=stepper.device)
    bc.params = {"force": wp.array([b.force], dtype=stepper.T.vec, device=stepper.device)}

    def add_force(ext, t, x=None):
        if b.t_start <= t < b.t_end:
            wp.launch(K.add_force, dim=len(idx), inputs=[ext, ia, share, bc.params["force"]], device=stepper.device)
            return True
        return False

    def tape():
        TK = _tape_kernels(stepper.dim, stepper.precision)

        def force(ext, p, t, ctl, x=None):
            if b.t_start <= t < b.t_end and len(idx):
                wp.launch(TK.add_force, dim=len(idx), inputs=[ext, ia, share, p["force"]], device=stepper.device)

        return SimpleNamespace(stage="particle_force", params={"force": np.asarray(b.force, float)},
                               param_kinds={"force": "vec"}, force=force)

    bc.add_force = add_force
    bc.tape = tape
    return bc
