"""Kinematic signed-distance colliders (SI units, z up).

A collider is split like the rest of dax-physics:

* :class:`ColliderSpec` (static, hashable): the shape, its dimensions [m], the contact
  mode and the Coulomb friction coefficient;
* :class:`ColliderState` (pytree of arrays, one row per collider): position [m], orientation
  (unit quaternion ``(w, x, y, z)``), linear velocity [m/s] and angular velocity [rad/s],
  both in the world frame. Velocities are the *commands*: a task sets them and
  :func:`advance` integrates the pose over a time step, so a collider serves as a gripper,
  a pusher or a held bowl.

Shapes, in the collider's local frame (the solid is where the SDF is negative):

``plane``     half-space ``z_local <= 0`` (a table: pose it at the table height).
``box``       ``dims = (hx, hy, hz)`` half extents.
``sphere``    ``dims = (r,)``.
``capsule``   ``dims = (r, half_length)``, segment along local z.
``cylinder``  ``dims = (r, half_height)``, axis local z, centred at the origin.
``bowl``      ``dims = (r_outer, height, wall)``: an open cup, bottom at local z = 0, rim at
              z = height, wall and bottom thickness ``wall``. Make ``wall`` at least about
              two grid cells so MPM particles cannot tunnel through it.

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

import jax
import jax.numpy as jnp

from ._pytree import pytree_dataclass

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
    """

    shape: str
    dims: tuple = ()
    mode: str = "separate"
    friction: float = 0.0
    margin: float = 0.0

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


def _box_sdf(p, h):
    q = jnp.abs(p) - h
    outside = _safe_norm(jnp.maximum(q, 0.0))
    outside = jnp.where(jnp.all(q <= 0.0, axis=-1), 0.0, outside)
    return outside + jnp.minimum(jnp.max(q, axis=-1), 0.0)


def _cyl_sdf(p, r, hh, zc=0.0):
    d = jnp.stack([_safe_norm(p[..., :2]) - r, jnp.abs(p[..., 2] - zc) - hh], -1)
    outside = _safe_norm(jnp.maximum(d, 0.0))
    outside = jnp.where(jnp.all(d <= 0.0, axis=-1), 0.0, outside)
    return outside + jnp.minimum(jnp.max(d, axis=-1), 0.0)


def local_sdf(spec: ColliderSpec, p):
    """Signed distance [m] of local-frame points ``p`` (..., 3) to the collider's surface."""
    d = spec.dims
    if spec.shape == "plane":
        return p[..., 2]
    if spec.shape == "box":
        return _box_sdf(p, jnp.asarray(d, p.dtype))
    if spec.shape == "sphere":
        return _safe_norm(p) - d[0]
    if spec.shape == "capsule":
        r, hl = d
        q = p.at[..., 2].set(p[..., 2] - jnp.clip(p[..., 2], -hl, hl))
        return _safe_norm(q) - r
    if spec.shape == "cylinder":
        return _cyl_sdf(p, d[0], d[1])
    # bowl: outer cylinder minus a cavity open at the top.
    r, h, t = d
    outer = _cyl_sdf(p, r, 0.5 * h, 0.5 * h)
    cavity_top = h + r  # the cavity pokes out above the rim, so the cup is open
    cavity = _cyl_sdf(p, r - t, 0.5 * (cavity_top - t), 0.5 * (cavity_top + t))
    return jnp.maximum(outer, -cavity)


def sdf(spec: ColliderSpec, pos, quat, x):
    """World-frame signed distance [m] and outward unit normal at points ``x`` (..., 3)."""
    R = quat_to_matrix(quat)
    p = (x - pos) @ R  # R^T (x - pos) for row vectors

    def one(pl):
        return local_sdf(spec, pl)

    flat = p.reshape(-1, 3)
    phi, grad = jax.vmap(jax.value_and_grad(one))(flat)
    n = grad @ R.T
    n = n / _safe_norm(n)[..., None]
    return phi.reshape(x.shape[:-1]), n.reshape(x.shape)


def velocity_at(state: ColliderState, index: int, x):
    """Rigid velocity [m/s] of collider ``index`` at world points ``x`` (..., 3)."""
    r = x - state.pos[index]
    return state.lin_vel[index] + jnp.cross(jnp.broadcast_to(state.ang_vel[index], r.shape), r)


def project_velocity(spec: ColliderSpec, v, v_c, n, inside):
    """Apply the contact condition of ``spec`` to velocities ``v`` at points flagged
    ``inside`` (collider velocity ``v_c``, outward normal ``n``)."""
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
    if spec.friction > 0.0:
        vt_norm = _safe_norm(v_t)[..., None]
        scale = jnp.maximum(vt_norm - spec.friction * normal_speed, 0.0) / vt_norm
        v_t = v_t * scale
    return jnp.where(apply, v_c + v_t, v)


def apply_colliders(specs, state: ColliderState, x, v):
    """Apply every collider's boundary condition to velocities ``v`` at grid points ``x``."""
    for k, spec in enumerate(specs):
        phi, n = sdf(spec, state.pos[k], state.quat[k], x)
        inside = phi < spec.margin
        v = project_velocity(spec, v, velocity_at(state, k, x), n, inside)
    return v


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
