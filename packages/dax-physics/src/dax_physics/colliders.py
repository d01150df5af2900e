"""Kinematic signed-distance colliders (SI units, z up).

A collider is split like the rest of dax-physics:

* :class:`ColliderSpec` (static, hashable): the shape, its dimensions [m], the contact
  mode and the Coulomb friction coefficient;
* :class:`ColliderState` (pytree of arrays, one row per collider): position [m], orientation
  (unit quaternion ``(w, x, y, z)``), linear velocity [m/s] and angular velocity [rad/s],
  both in the world frame. Velocities are the *commands*: a task sets them and
  :func:`advance` integrates the pose over a time step, so a collider serves as a gripper,
  a pusher or a held bowl.

Points are (..., 3) [m] in the world frame unless said otherwise, signed distances [m]
(negative inside the solid), normals unit vectors pointing out of it. Everything is pure
and differentiable (the SDF's gradient is the normal); the MPM grid applies the contact
conditions on its nodes (:func:`apply_colliders_grid`), the cloth on its vertices
(:func:`apply_colliders`).

Shapes, in the collider's local frame (the solid is where the SDF is negative):

``plane``     half-space ``z_local <= 0`` (a table: pose it at the table height).
``box``       ``dims = (hx, hy, hz)`` half extents.
``sphere``    ``dims = (r,)``.
``capsule``   ``dims = (r, half_length)``, segment along local z.
``cylinder``  ``dims = (r, half_height)``, axis local z, centred at the origin.
``bowl``      ``dims = (r_outer, height, wall)``: an open cup, bottom at local z = 0, rim at
              z = height, wall and bottom thickness ``wall``. Make ``wall`` at least about
              two grid cells so MPM particles cannot tunnel through it. On the MPM grid,
              nodes more than dx/2 inside the wall move with the bowl whatever the mode:
              in a wall two cells thick the middle node's SDF gradient vanishes (both
              faces are equally near) and the next one's points out of the far face, so
              liquid resting on the bottom would otherwise sink into it.

Contact modes for grid velocities ``v`` relative to the collider ``v_rel = v - v_c``
(``n`` is the outward normal):

``sticky``    ``v = v_c`` (no slip, no separation).
``slip``      the normal component of ``v_rel`` is removed both ways; Coulomb friction
              on the tangential part.
``separate``  only the approaching normal component (``v_rel . n < 0``) is removed, so
              material can leave the surface; Coulomb friction
              ``|v_t| <- max(0, |v_t| - mu |v_n|)`` on the tangential part.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from ._fusion import materialise_cotangent
from ._pytree import pytree_dataclass
from .precision import HIGHEST
from .precision import mm as _mm

SHAPES = {"plane": 0, "box": 3, "sphere": 1, "capsule": 2, "cylinder": 2, "bowl": 3}
MODES = ("sticky", "slip", "separate")
_EPS = 1e-12


@dataclasses.dataclass(frozen=True)
class ColliderSpec:
    """Static description of one kinematic collider.

    shape: one of ``plane, box, sphere, capsule, cylinder, bowl``.
    dims: shape dimensions [m] (see module docstring).
    mode: ``sticky``, ``slip`` or ``separate``.
    friction: Coulomb friction coefficient mu [-] (``slip`` and ``separate``).
    margin: skin thickness [m]; grid nodes within ``margin`` of the surface feel it.
    project: MPM particles that end a substep inside the solid are put back on its surface
        (:func:`project_particles`), on top of the grid condition. The cloth ignores it
        (its vertices meet the colliders directly).
    """

    shape: str
    dims: tuple = ()
    mode: str = "separate"
    friction: float = 0.0
    margin: float = 0.0
    project: bool = False

    def __post_init__(self):
        if self.shape not in SHAPES:
            raise ValueError(
                f"unknown collider shape {self.shape!r}; valid shapes: {', '.join(SHAPES)}")
        object.__setattr__(self, "dims", tuple(float(d) for d in self.dims))
        if len(self.dims) != SHAPES[self.shape]:
            raise ValueError(f"collider shape {self.shape!r} takes {SHAPES[self.shape]} dims, "
                             f"got {len(self.dims)}: {self.dims}")
        if any(not d > 0 for d in self.dims):
            raise ValueError(f"collider dims must be > 0 m, got {self.dims}")
        if self.mode not in MODES:
            raise ValueError(f"unknown contact mode {self.mode!r}; valid modes: {', '.join(MODES)}")
        if self.friction < 0:
            raise ValueError(f"friction coefficient must be >= 0, got {self.friction}")
        if not isinstance(self.project, bool):
            raise TypeError(f"project must be a bool, got {self.project!r}")
        if self.shape == "bowl" and not self.dims[2] < self.dims[0]:
            raise ValueError(f"bowl wall {self.dims[2]} m must be thinner than its radius "
                             f"{self.dims[0]} m")


@pytree_dataclass
class ColliderState:
    """Poses and velocity commands of K colliders (world frame, SI)."""

    pos: jnp.ndarray      # (K, 3) [m]
    quat: jnp.ndarray     # (K, 4) unit quaternion (w, x, y, z)
    lin_vel: jnp.ndarray  # (K, 3) [m/s]
    ang_vel: jnp.ndarray  # (K, 3) [rad/s]

    @staticmethod
    def create(pos, quat=None, lin_vel=None, ang_vel=None, dtype=jnp.float32) -> ColliderState:
        pos = jnp.asarray(pos, dtype).reshape(-1, 3)
        k = pos.shape[0]
        if quat is None:
            quat = jnp.tile(jnp.asarray([1.0, 0.0, 0.0, 0.0], dtype), (k, 1))
        quat = jnp.asarray(quat, dtype).reshape(k, 4)
        lin_vel = jnp.zeros((k, 3), dtype) if lin_vel is None else jnp.asarray(lin_vel, dtype)
        ang_vel = jnp.zeros((k, 3), dtype) if ang_vel is None else jnp.asarray(ang_vel, dtype)
        return ColliderState(pos, quat, lin_vel.reshape(k, 3), ang_vel.reshape(k, 3))

    @staticmethod
    def empty(dtype=jnp.float32) -> ColliderState:
        return ColliderState.create(jnp.zeros((0, 3), dtype), dtype=dtype)

    def with_velocity(self, index: int, lin_vel=None, ang_vel=None) -> ColliderState:
        """Set collider ``index``'s velocity command (world frame)."""
        out = self
        if lin_vel is not None:
            out = out.replace(lin_vel=out.lin_vel.at[index].set(lin_vel))
        if ang_vel is not None:
            out = out.replace(ang_vel=out.ang_vel.at[index].set(ang_vel))
        return out


def quat_to_matrix(q):
    """Rotation matrix (3, 3) of a unit quaternion (w, x, y, z)."""
    w, x, y, z = q[0], q[1], q[2], q[3]
    return jnp.stack([
        jnp.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)]),
        jnp.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)]),
        jnp.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]),
    ])


def quat_from_axis_angle(axis, angle):
    """Unit quaternion (w, x, y, z) for a rotation of ``angle`` [rad] about ``axis``."""
    axis = jnp.asarray(axis, jnp.float32)
    axis = axis / jnp.linalg.norm(axis)
    return jnp.concatenate([jnp.cos(angle / 2)[None], jnp.sin(angle / 2) * axis])


def _safe_norm(v, axis=-1):
    return jnp.sqrt(jnp.sum(v * v, axis=axis) + _EPS)


# The signed distances below take the three coordinates as separate arrays (structure of
# arrays): XLA:CPU vectorises elementwise math on (M,) rows, not on (M, 3) rows of three.

def _hypot(*c):
    return jnp.sqrt(sum(ci * ci for ci in c) + _EPS)


def _outside_inside(d):
    """Exact SDF from per-axis distances ``d`` (tuple of arrays) of a convex slab set.

    The outside distance is ``hypot(...) - sqrt(eps)``: the ``eps`` that keeps the
    gradient finite at the surface must not lift the distance there (a point on a face a
    rounding error outside would get sqrt(eps) = 1e-6 m, equal to :data:`SURFACE_TOL`, and
    miss the surface)."""
    outside = _hypot(*(jnp.maximum(di, 0.0) for di in d)) - math.sqrt(_EPS)
    inside_all = functools.reduce(jnp.logical_and, [di <= 0.0 for di in d])
    outside = jnp.where(inside_all, 0.0, outside)
    return outside + jnp.minimum(functools.reduce(jnp.maximum, d), 0.0)


def _box_sdf(px, py, pz, h):
    return _outside_inside((jnp.abs(px) - h[0], jnp.abs(py) - h[1], jnp.abs(pz) - h[2]))


def _cyl_sdf(px, py, pz, r, hh, zc=0.0):
    return _outside_inside((_hypot(px, py) - r, jnp.abs(pz - zc) - hh))


def _local_sdf(spec: ColliderSpec, px, py, pz):
    d = spec.dims
    if spec.shape == "plane":
        return pz
    if spec.shape == "box":
        return _box_sdf(px, py, pz, d)
    if spec.shape == "sphere":
        return _hypot(px, py, pz) - d[0]
    if spec.shape == "capsule":
        r, hl = d
        return _hypot(px, py, pz - jnp.clip(pz, -hl, hl)) - r
    if spec.shape == "cylinder":
        return _cyl_sdf(px, py, pz, d[0], d[1])
    # bowl: outer cylinder minus a cavity open at the top.
    r, h, t = d
    outer = _cyl_sdf(px, py, pz, r, 0.5 * h, 0.5 * h)
    cavity_top = h + r  # the cavity pokes out above the rim, so the cup is open
    cavity = _cyl_sdf(px, py, pz, r - t, 0.5 * (cavity_top - t), 0.5 * (cavity_top + t))
    return jnp.maximum(outer, -cavity)


def sdf(spec: ColliderSpec, pos, quat, x):
    """World-frame signed distance [m] and outward unit normal at points ``x`` (..., 3).
    The normal is the SDF's gradient (reverse mode over all points at once: each point's
    distance depends on that point only)."""
    R = quat_to_matrix(quat)
    pt = _mm(R.T, (x.reshape(-1, 3) - pos).T)  # (3, M) local coordinates, one row per axis
    if spec.shape == "plane":
        phi, grad = pt[2], jnp.zeros_like(pt).at[2].set(1.0)
    else:
        phi, back = jax.vjp(lambda q: _local_sdf(spec, q[0], q[1], q[2]), pt)
        (grad,) = back(jnp.ones_like(phi))
    n = _mm(R, grad)
    n = (n / jnp.sqrt(jnp.sum(n * n, axis=0) + _EPS)).T
    return phi.reshape(x.shape[:-1]), n.reshape(x.shape)


def velocity_at(state: ColliderState, index: int, x):
    """Rigid velocity [m/s] of collider ``index`` at world points ``x`` (..., 3)."""
    r = x - state.pos[index]
    return state.lin_vel[index] + jnp.cross(jnp.broadcast_to(state.ang_vel[index], r.shape), r)


def project_velocity(spec: ColliderSpec, v, v_c, n, inside, friction=None):
    """Apply the contact condition of ``spec`` to velocities ``v`` at points flagged
    ``inside`` (collider velocity ``v_c``, outward normal ``n``). ``friction``: the
    Coulomb coefficient as data (a scalar array, differentiable); ``None`` uses
    ``spec.friction``."""
    if spec.mode == "sticky":
        return jnp.where(inside[..., None], v_c, v)
    v_rel = v - v_c
    vn = jnp.sum(v_rel * n, axis=-1, keepdims=True)
    v_t = v_rel - vn * n
    if spec.mode == "slip":
        apply = inside[..., None]
        normal_speed = jnp.abs(vn)
    else:  # separate
        apply = inside[..., None] & (vn < 0.0)
        normal_speed = -vn
    if friction is not None or spec.friction > 0.0:
        mu = spec.friction if friction is None else friction
        vt_norm = _safe_norm(v_t)[..., None]
        scale = jnp.maximum(vt_norm - mu * normal_speed, 0.0) / vt_norm
        v_t = v_t * scale
    return jnp.where(apply, v_c + v_t, v)


#: Grid nodes within this distance [m] outside a collider's surface count as touching it.
#: MPM nodes lie on a lattice, and scenes put surfaces on lattice planes (a bowl's rim at a
#: whole number of cells): such a node's SDF is zero up to float32 rounding (+-4e-9 m at
#: 0.1 m), so without a tolerance whether it touches would depend on how XLA fused the
#: arithmetic, and two compilations of one scene could differ.
SURFACE_TOL = 1e-6


def apply_colliders(specs, state: ColliderState, x, v, tol: float = 0.0, depth=None,
                    friction=None):
    """Apply every collider's boundary condition to velocities ``v`` at points ``x``; a
    point touches a collider where its SDF is below ``margin + tol``. With ``depth`` [m],
    points more than ``depth`` inside a bowl's wall move with the bowl (see the module
    docstring). ``friction``: (K,) Coulomb coefficients as data, one per collider
    (``None``: each spec's ``friction``)."""
    for k, spec in enumerate(specs):
        v = _apply_one(spec, state, k, x, v, tol, depth, _coefficient(friction, k))
    return v


def _coefficient(friction, k: int):
    return None if friction is None else friction[k]


def _apply_one(spec: ColliderSpec, state: ColliderState, k: int, x, v, tol, depth,
               friction=None):
    phi, n = sdf(spec, state.pos[k], state.quat[k], x)
    inside = phi < spec.margin + tol
    v_c = velocity_at(state, k, x)
    v = project_velocity(spec, v, v_c, n, inside, friction)
    if depth is not None and spec.shape == "bowl":
        v = jnp.where((phi < -depth)[..., None], v_c, v)
    return v


def bounding_sphere(spec: ColliderSpec):
    """``(centre, radius)`` of a sphere in the collider's local frame [m] that holds every
    point where the SDF is below ``margin`` (the solid grown by its skin), or None for the
    unbounded plane."""
    d = spec.dims
    if spec.shape == "plane":
        return None
    centre = (0.0, 0.0, 0.0)
    if spec.shape == "bowl":  # the solid lies inside its outer cylinder, z in [0, height]
        centre, radius = (0.0, 0.0, 0.5 * d[1]), math.hypot(d[0], 0.5 * d[1])
    elif spec.shape == "box":
        radius = math.sqrt(sum(h * h for h in d))
    elif spec.shape == "sphere":
        radius = d[0]
    elif spec.shape == "capsule":
        radius = d[0] + d[1]
    else:  # cylinder
        radius = math.hypot(d[0], d[1])
    return centre, radius + max(spec.margin, 0.0)


def apply_colliders_grid(specs, state: ColliderState, v, dx: float, window, origin,
                         friction=None):
    """:func:`apply_colliders` on the nodes of a grid window: ``v`` (prod(window), 3) are the
    velocities of nodes ``origin + (i, j, k)`` [cells], row-major over ``window``.

    A bounded collider is evaluated only on the cube of nodes around its bounding sphere
    (a static size, placed where the collider is), not on the whole window: nodes outside
    it cannot be inside the collider, so the result is the same. Nodes within
    :data:`SURFACE_TOL` outside a surface count as touching it; nodes more than dx/2 inside
    a bowl's wall move with it. ``friction``: as for :func:`apply_colliders`.

    A collider evaluated on the whole window (a plane) is computed on one (window,) array
    per velocity component, the components written out (:func:`sdf_rows`): on XLA:CPU a
    sum over the 3-axis of (M, 3) arrays, a cross product or a 3 x 3 matrix product is a
    loop or a library call of its own over all M nodes, while rows fuse into one loop."""
    window = tuple(int(w) for w in window)
    v4 = v.reshape(*window, 3)
    zero = jnp.zeros((), jnp.int32)
    for k, spec in enumerate(specs):
        side, start = window, jnp.zeros((3,), jnp.int32)  # the whole window (a plane)
        bound = bounding_sphere(spec)
        if bound is not None:
            half = math.ceil(bound[1] / dx) + 1
            cube = tuple(min(2 * half + 1, w) for w in window)
            if 2 * math.prod(cube) <= math.prod(window):  # else not worth the slicing
                R = quat_to_matrix(state.quat[k])
                centre = state.pos[k] + _mm(R, jnp.asarray(bound[0], v.dtype))
                cell = jnp.floor(jax.lax.stop_gradient(centre) / dx).astype(jnp.int32)
                side = cube
                start = jnp.clip(cell - half - origin, 0,
                                 jnp.asarray(window) - jnp.asarray(side)).astype(jnp.int32)
        if side == window:  # the whole window: one row per component
            pts = [(jax.lax.broadcasted_iota(jnp.int32, side, a) + origin[a]
                    ).astype(v.dtype) * dx for a in range(3)]
            rows = _apply_one_rows(spec, state, k, pts, [v4[..., a] for a in range(3)],
                                   SURFACE_TOL, 0.5 * dx, _coefficient(friction, k))
            v4 = jnp.stack(rows, axis=-1)
            continue
        corner = (start[0], start[1], start[2], zero)
        sub = jax.lax.dynamic_slice(v4, corner, (*side, 3)).reshape(-1, 3)
        idx = jnp.asarray(np.indices(side).reshape(3, -1).T, jnp.int32)
        x = (idx + start + origin).astype(v.dtype) * dx
        sub = _apply_one(spec, state, k, x, sub, SURFACE_TOL, 0.5 * dx,
                         _coefficient(friction, k))
        v4 = jax.lax.dynamic_update_slice(v4, sub.reshape(*side, 3), corner)
    return v4.reshape(-1, 3)


def sdf_rows(spec: ColliderSpec, pos, quat, pts):
    """:func:`sdf` on points given as coordinate rows ``pts`` (3 arrays of one shape,
    world frame [m]): ``(phi, n)``, the signed distance [m] and the outward unit normal as
    3 rows, components written out (see :func:`apply_colliders_grid`)."""
    R = quat_to_matrix(quat)
    d = _per_point([pts[a] - pos[a] for a in range(3)])
    local = _per_point([R[0, a] * d[0] + R[1, a] * d[1] + R[2, a] * d[2]
                        for a in range(3)])  # R^T d
    if spec.shape == "plane":
        phi = local[2]
        return phi, [jnp.broadcast_to(R[i, 2], phi.shape) for i in range(3)]
    phi, back = jax.vjp(lambda a, b, c: _local_sdf(spec, a, b, c), *local)
    g = back(jnp.ones_like(phi))
    n = _per_point([R[i, 0] * g[0] + R[i, 1] * g[1] + R[i, 2] * g[2] for i in range(3)])
    inv = 1.0 / jnp.sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2] + _EPS)
    return phi, [ni * inv for ni in n]


def _per_point(rows):
    """``rows`` (3 arrays of one shape) themselves; in reverse mode their cotangents are
    materialised (:func:`dax_physics._fusion.materialise_cotangent`). Rows that combine
    the points with a collider's pose or velocity (scalars) pass here: each scalar's
    cotangent is a sum over every point, and XLA fuses such sums with the whole adjoint
    chain of the rows and redoes it in each of them."""
    return list(materialise_cotangent(jnp.stack(rows)))


def _velocity_rows(state: ColliderState, k: int, pts):
    """Rigid velocity [m/s] of collider ``k`` at the points ``pts`` (3 rows)."""
    w, c, lin = state.ang_vel[k], state.pos[k], state.lin_vel[k]
    r = _per_point([pts[a] - c[a] for a in range(3)])
    return _per_point([lin[0] + (w[1] * r[2] - w[2] * r[1]),
                       lin[1] + (w[2] * r[0] - w[0] * r[2]),
                       lin[2] + (w[0] * r[1] - w[1] * r[0])])


def _apply_one_rows(spec: ColliderSpec, state: ColliderState, k: int, pts, v, tol, depth,
                    friction=None):
    """:func:`_apply_one` on rows: points ``pts`` and velocities ``v`` (3 rows each)."""
    phi, n = sdf_rows(spec, state.pos[k], state.quat[k], pts)
    inside = phi < spec.margin + tol
    v_c = _velocity_rows(state, k, pts)
    if spec.mode == "sticky":
        v = [jnp.where(inside, v_c[i], v[i]) for i in range(3)]
    else:
        rel = [v[i] - v_c[i] for i in range(3)]
        vn = rel[0] * n[0] + rel[1] * n[1] + rel[2] * n[2]
        v_t = [rel[i] - vn * n[i] for i in range(3)]
        if spec.mode == "slip":
            apply, normal_speed = inside, jnp.abs(vn)
        else:  # separate
            apply, normal_speed = inside & (vn < 0.0), -vn
        if friction is not None or spec.friction > 0.0:
            mu = spec.friction if friction is None else friction
            vt_norm = jnp.sqrt(v_t[0] * v_t[0] + v_t[1] * v_t[1] + v_t[2] * v_t[2] + _EPS)
            slowed = materialise_cotangent(vt_norm - mu * normal_speed)
            scale = jnp.maximum(slowed, 0.0) / vt_norm
            v_t = [t * scale for t in v_t]
        v = [jnp.where(apply, v_c[i] + v_t[i], v[i]) for i in range(3)]
    if depth is not None and spec.shape == "bowl":
        deep = phi < -depth
        v = [jnp.where(deep, v_c[i], v[i]) for i in range(3)]
    return v


def project_particles(specs, state: ColliderState, x, v, free):
    """Particles put back outside the colliders whose spec sets ``project``: ``(x, v)``.

    A grid condition acts on nodes, and a particle's velocity interpolates nodes on both
    sides of a surface, so particles can end a substep inside a thin solid (a bowl's wall
    two cells thick), and a moving collider sweeps over particles. Each particle ``free``
    (N,) bool that is inside such a collider (signed distance ``phi < 0`` at the pose
    ``state``, taken after the substep; inside several: the one it is deepest in) moves
    along the outward normal onto the surface (``x - phi n``), and its velocity relative
    to the collider loses the component into it (``v_rel . n < 0`` removed; the
    tangential part is left to the grid's friction). Particles outside, and held ones
    (``free`` false), are unchanged. ``x``, ``v``: (N, 3) [m], [m/s]. Pure and
    differentiable through the signed distance; the normal is held constant in reverse
    mode (its derivative, the surface's curvature, would cost a second derivative of the
    signed distance in every substep of a gradient). The colliders of one shape are
    evaluated together, as one (K, N) array (fewer, larger loops)."""
    ks = [k for k, spec in enumerate(specs) if spec.project]
    if not ks:
        return x, v
    order, phi, n = [], [], []
    for shape in dict.fromkeys(specs[k].shape for k in ks):
        group = [k for k in ks if specs[k].shape == shape]
        p, nn = _sdf_group([specs[k] for k in group], state.pos[jnp.asarray(group)],
                           state.quat[jnp.asarray(group)], x)
        order += group
        phi.append(p)
        n.append(nn)
    phi, n = jnp.concatenate(phi), jnp.concatenate(n)  # (K, N), (K, N, 3)
    if len(order) == 1:
        j, phi_j, n_j = order[0], phi[0], n[0]
        w, c, lin = state.ang_vel[j], state.pos[j], state.lin_vel[j]
    else:
        best = jnp.argmin(phi, axis=0)  # (N,) the collider each particle is deepest in
        phi_j = jnp.min(phi, axis=0)
        n_j = jnp.take_along_axis(n, best[None, :, None], axis=0)[0]
        sel = jnp.asarray(order)[best]
        w, c, lin = state.ang_vel[sel], state.pos[sel], state.lin_vel[sel]
    n_j = jax.lax.stop_gradient(n_j)
    inside = ((phi_j < 0.0) & free)[:, None]
    x = jnp.where(inside, x - phi_j[:, None] * n_j, x)
    rel = v - (lin + jnp.cross(jnp.broadcast_to(w, x.shape), x - c))
    vn = jnp.sum(rel * n_j, axis=-1, keepdims=True)
    v = jnp.where(inside & (vn < 0.0), v - vn * n_j, v)
    return x, v


def _sdf_group(specs, pos, quat, x):
    """:func:`sdf` of K colliders of one shape (``pos`` (K, 3), ``quat`` (K, 4)) at the
    same points ``x`` (N, 3): ``(phi, n)``, (K, N) and (K, N, 3). Their dimensions enter
    as (K, 1) columns."""
    R = jax.vmap(quat_to_matrix)(quat)  # (K, 3, 3)
    d = x.T[None] - pos[:, :, None]  # (K, 3, N)
    pt = jnp.einsum("kji,kjn->kin", R, d, precision=HIGHEST)  # R^T d, local coordinates
    shape = specs[0].shape
    if shape == "plane":
        phi, grad = pt[:, 2], jnp.zeros_like(pt).at[:, 2].set(1.0)
    else:
        dims = tuple(jnp.asarray([[s.dims[i]] for s in specs], x.dtype)
                     for i in range(len(specs[0].dims)))
        view = _ShapeView(shape, dims)
        phi, back = jax.vjp(lambda q: _local_sdf(view, q[:, 0], q[:, 1], q[:, 2]), pt)
        (grad,) = back(jnp.ones_like(phi))
    n = jnp.einsum("kij,kjn->kni", R, grad, precision=HIGHEST)  # (K, N, 3)
    n = n / jnp.sqrt(jnp.sum(n * n, axis=-1, keepdims=True) + _EPS)
    return phi, n


@dataclasses.dataclass(frozen=True)
class _ShapeView:
    """What :func:`_local_sdf` reads of a spec, with dimensions that may be arrays."""

    shape: str
    dims: tuple


def advance(state: ColliderState, dt) -> ColliderState:
    """Integrate poses over ``dt`` [s] with the current velocity commands."""
    if state.pos.shape[0] == 0:
        return state
    w = state.ang_vel
    q = state.quat
    # dq/dt = 1/2 (0, w) * q  (world-frame angular velocity)
    qw, qv = q[:, :1], q[:, 1:]
    dq_w = -jnp.sum(w * qv, axis=-1, keepdims=True)
    dq_v = w * qw + jnp.cross(w, qv)
    q = q + 0.5 * dt * jnp.concatenate([dq_w, dq_v], axis=-1)
    q = q / jnp.linalg.norm(q, axis=-1, keepdims=True)
    return state.replace(pos=state.pos + dt * state.lin_vel, quat=q)
