"""JAX implementations of the built-in boundaries (``mpmlab.boundaries``).

Each factory takes (boundary, scene, dtype) and returns an object with ``params`` (a pytree the
stepper passes back, differentiable: e.g. friction coefficients) and one of ``apply`` (grid),
``apply_particles`` (particle velocity) or ``particle_force`` (particle load). Node masks are
computed once in NumPy from the static scene, so the compiled step only touches arrays it needs.

A grid boundary's ``apply(v, node_x, m, t, params, node_ids=None)`` acts on every node of the scene's grid
(``node_ids`` None) or on a compact node set (``node_ids``: each node's flat index in the scene's grid, -1
outside it; ``backends/jax/node_windows.py``), whose per-node masks it reads at those indices.
"""
from __future__ import annotations

from types import SimpleNamespace

import jax.numpy as jnp
import numpy as np

from ...boundaries import _faces
from ..boundary_geometry import box_obstacle_normals, friction_node_mu_index, wall_masks


def _safe_norm(a):
    sq = jnp.sum(a * a, axis=-1)
    pos = sq > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, sq, 1.0)), 0.0)


def coulomb(v, n, mu):
    """Coulomb friction against a surface with outward normal n (into the obstacle), JAX-MPM Eqs. 35-36.

    Applies where the node moves into the surface (v.n > 0): the normal part is removed and the tangential
    speed reduced by mu v_n, sticking when |v_t| <= mu v_n. Elsewhere v is returned unchanged.
    """
    vn = jnp.sum(v * n, axis=-1)
    vt = v - vn[..., None] * n
    vt_norm = _safe_norm(vt)
    scale = jnp.where(vt_norm > mu * vn, 1.0 - mu * vn / jnp.where(vt_norm > 0, vt_norm, 1.0), 0.0)
    return jnp.where((vn > 0)[..., None], vt * scale[..., None], v)


def _at(mask, node_ids):
    """A per-node array of the scene's grid read at a compact node set (nodes outside the grid: False / 0)."""
    if node_ids is None:
        return mask
    return jnp.where((node_ids >= 0).reshape((-1,) + (1,) * (mask.ndim - 1)), mask[jnp.maximum(node_ids, 0)],
                     jnp.zeros((), mask.dtype))


def walls(b, scene, dtype):
    kinds = b.face_kinds(scene.dim)
    masks = wall_masks(scene, b.thickness)  # per face: bool [G]
    faces = _faces(scene.dim)
    active = [(f, k, jnp.asarray(masks[f])) for f, k in zip(faces, kinds) if k != "none"]

    def apply(v, node_x, m, t, params, node_ids=None):
        for face, kind, mask in active:
            mask = _at(mask, node_ids)
            a = "xyz".index(face[0])
            side = -1.0 if face[1] == "-" else 1.0
            if kind == "sticky":
                v = jnp.where(mask[:, None], 0.0, v)
                continue
            into = side * v[:, a] > 0
            hit = mask & (into if kind == "separate" else True)
            v = v.at[:, a].set(jnp.where(hit, 0.0, v[:, a]))
        return v

    return SimpleNamespace(params={}, apply=apply)


def friction_walls(b, scene, dtype):
    mask = jnp.asarray(wall_masks(scene, b.thickness)[b.face])
    mu_index = jnp.asarray(friction_node_mu_index(b, scene))
    n = np.zeros(scene.dim); n[b.axis] = b.side
    n = jnp.asarray(n, dtype)

    def apply(v, node_x, m, t, params, node_ids=None):
        mu = params["mu"][_at(mu_index, node_ids)]
        return jnp.where(_at(mask, node_ids)[:, None], coulomb(v, n, mu), v)

    return SimpleNamespace(params={"mu": jnp.asarray(b.mu, dtype)}, apply=apply)


def plane(b, scene, dtype):
    n_in = jnp.asarray(b.unit_normal(), dtype)   # into the free side
    p0 = jnp.asarray(b.point, dtype)

    def apply(v, node_x, m, t, params, node_ids=None):
        behind = jnp.sum((node_x - p0) * n_in, axis=-1) < 0
        if b.condition == "sticky":
            return jnp.where(behind[:, None], 0.0, v)
        vn = jnp.sum(v * n_in, axis=-1)
        if b.condition == "slip":
            out = v - vn[:, None] * n_in
        else:
            out = coulomb(v, -n_in, params["friction"])
        return jnp.where(behind[:, None], out, v)

    return SimpleNamespace(params={"friction": jnp.asarray(b.friction, dtype)}, apply=apply)


def box_obstacle(b, scene, dtype):
    inside, normals = box_obstacle_normals(b, scene)
    inside = jnp.asarray(inside)
    normals = jnp.asarray(normals, dtype)

    def apply(v, node_x, m, t, params, node_ids=None):
        inside_, normals_ = _at(inside, node_ids), _at(normals, node_ids)
        vn = jnp.sum(v * normals_, axis=-1)
        # JAX-MPM Eq. 33: remove the normal component (only when it points into the box, so fluid may leave)
        out = v - jnp.minimum(vn, 0.0)[:, None] * normals_
        return jnp.where(inside_[:, None], out, v)

    return SimpleNamespace(params={}, apply=apply)


def _rotation(w_dt, dim):
    """R(omega dt): a 2D rotation by the angle ``w_dt``, or Rodrigues' formula for the 3-vector ``w_dt``
    (sin t / t and (1 - cos t) / t^2 as sincs: smooth at t = 0)."""
    if dim == 2:
        c, s = jnp.cos(w_dt), jnp.sin(w_dt)
        return jnp.array([[c, -s], [s, c]])
    th = jnp.sqrt(jnp.sum(w_dt * w_dt) + jnp.finfo(w_dt.dtype).tiny)
    K = jnp.array([[0.0, -w_dt[2], w_dt[1]], [w_dt[2], 0.0, -w_dt[0]], [-w_dt[1], w_dt[0], 0.0]], w_dt.dtype)
    return jnp.eye(3, dtype=w_dt.dtype) + jnp.sinc(th / jnp.pi) * K + 0.5 * jnp.sinc(th / (2 * jnp.pi)) ** 2 * (K @ K)


def _cross(w, r, dim):
    """omega x r per row (2D: omega a scalar)."""
    if dim == 2:
        return w * jnp.stack([-r[:, 1], r[:, 0]], axis=1)
    return jnp.cross(w[None, :], r)


def particle_velocity(b, scene, dtype):
    """``apply_particles(x, v_p, v_pic, t_end, dt, params, rows=None) -> (v_p, v_pic)``: the particle
    velocity and the velocity that moves the particles over the step that ends at ``t_end`` (x: positions
    at its start). ``rows``: x, v_p and v_pic are those of the scene's particles ``rows`` only (a reduced
    model's samples), not of all of them."""
    x0 = scene.particles().x
    sel = b.select(x0)
    idx = jnp.asarray(sel)
    member = jnp.asarray(np.isin(np.arange(len(x0)), sel))
    params = {"velocity": jnp.asarray(b.velocity, dtype)}
    dim = scene.dim
    if b.rotating:
        params["angular_velocity"] = jnp.asarray(b.angular_velocity, dtype)
        c0 = jnp.asarray(b.rotation_center(x0), dtype)

    def motion(xs, t_end, dt, params):
        """(particle velocity, moving velocity) of the prescribed motion for particles at xs."""
        v0 = params["velocity"]
        if not b.rotating:
            return v0, v0
        w = params["angular_velocity"]
        c_end = c0 + v0 * (t_end - b.t_start)            # the centre moves with the translation
        x_end = c_end + (xs - (c_end - v0 * dt)) @ _rotation(w * dt, dim).T   # exactly rigid over the step
        return v0 + _cross(w, x_end - c_end, dim), (x_end - xs) / dt   # rigid velocity at the new position

    def apply_particles(x, v_p, v_pic, t_end, dt, params, rows=None):
        on = (t_end > b.t_start) & (t_end <= b.t_end)
        if rows is not None:
            rigid, move = motion(x, t_end, dt, params)
            hit = (member[rows] & on)[:, None]
            return jnp.where(hit, rigid, v_p), jnp.where(hit, move, v_pic)
        rigid, move = motion(x[idx], t_end, dt, params)
        return v_p.at[idx].set(jnp.where(on, rigid, v_p[idx])), v_pic.at[idx].set(jnp.where(on, move, v_pic[idx]))

    return SimpleNamespace(params=params, apply_particles=apply_particles)


def grid_velocity(b, scene, dtype):
    """Nodes inside the moving box take the rigid velocity (``mpmlab.boundaries.GridVelocity``); the box
    is placed at the step's start time t."""
    dim = scene.dim
    c0 = jnp.asarray(b.rotation_center(scene.particles().x), dtype)
    lo, hi = (jnp.asarray(a, dtype) for a in b.box(dim))
    params = {"velocity": jnp.asarray(b.velocity, dtype)}
    if b.rotating:
        params["angular_velocity"] = jnp.asarray(b.angular_velocity, dtype)

    def apply(v, node_x, m, t, params, node_ids=None):
        tau = t - b.t_start
        v0 = params["velocity"]
        r = node_x - (c0 + v0 * tau)
        if b.rotating:
            w = params["angular_velocity"]
            ref = c0 + r @ _rotation(w * tau, dim)            # R^T r, row-wise: back to the reference frame
            target = v0 + _cross(w, r, dim)
        else:
            ref, target = c0 + r, jnp.broadcast_to(v0, v.shape)
        inside = jnp.all((ref >= lo) & (ref <= hi), axis=-1) & (t >= b.t_start) & (t < b.t_end)
        return jnp.where(inside[:, None], target, v)

    return SimpleNamespace(params=params, apply=apply)


def particle_load(b, scene, dtype):
    P = scene.particles()
    idx, part = b.shares(P)
    share = np.zeros(P.count)
    share[idx] = part
    share = jnp.asarray(share, dtype)

    def particle_force(x, mass, t, params):
        on = (t >= b.t_start) & (t < b.t_end)
        return jnp.where(on, share[:, None] * params["force"][None, :], 0.0)

    return SimpleNamespace(params={"force": jnp.asarray(b.force, dtype)}, particle_force=particle_force)
