"""Grasping: pick vertices with a gripper, move, release; the pick-and-place macro.

Points are (3,) [m] in the world frame; durations are in substeps of ``cfg.dt``. The
macros run :func:`~dax_physics.cloth.rollout` scans and, like it, leave the time step to
:func:`~dax_physics.cloth.check_params`. A non-finite point is refused eagerly when
concrete; inside ``jit`` it grasps nothing.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from .sim import Cloth, ClothConfig, ClothState, rollout


def _is_concrete(*trees) -> bool:
    """Whether no leaf of ``trees`` is a tracer (the arrays can be looked at)."""
    return not any(isinstance(leaf, jax.core.Tracer) for t in trees
                   for leaf in jax.tree_util.tree_leaves(t))


def _check_point(name, p):
    if _is_concrete(p):
        a = np.asarray(p, float)
        if a.shape != (3,):
            raise ValueError(f"{name} must be an (x, y, z) point in m, got shape {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{name} must be finite, got {a.tolist()}")


def nearest_vertex_point(state: ClothState, point):
    """Position [m] of the cloth vertex nearest to ``point`` (the contact adjustment)."""
    d2 = jnp.sum((jax.lax.stop_gradient(state.x) - point) ** 2, -1)
    return state.x[jnp.argmin(d2)]


def grasp(state: ClothState, gripper: int, point, radius: float, snap: bool = False
          ) -> ClothState:
    """Attach every free vertex within ``radius`` [m] of ``point`` [m] to gripper
    ``gripper`` and put the gripper there (its velocity command is zeroed).

    snap: contact adjustment - move ``point`` to the nearest cloth vertex first, so the
        grasp always holds at least one vertex.
    With ``snap=False`` a point with no vertex in reach is a documented no-op for the cloth
    (the gripper still moves to ``point`` and will carry nothing). A non-finite point raises
    ``ValueError`` when concrete; inside jit it grasps nothing and leaves the gripper where
    it was, so no NaN reaches the state.
    """
    _check_point("pick point", point)
    point = jnp.asarray(point, state.x.dtype)
    ok = jnp.all(jnp.isfinite(point))
    point = jnp.where(ok, point, state.gripper_pos[gripper])
    if snap:
        point = nearest_vertex_point(state, point)
    d2 = jnp.sum((jax.lax.stop_gradient(state.x) - jax.lax.stop_gradient(point)) ** 2, -1)
    free = jnp.sum(state.grip, 0) == 0
    take = (d2 <= radius * radius) & free & ok
    grip = state.grip.at[gripper].set(jnp.where(take, 1.0, state.grip[gripper]))
    return state.replace(grip=grip, gripper_pos=state.gripper_pos.at[gripper].set(point),
                         gripper_vel=state.gripper_vel.at[gripper].set(0.0))


def release(state: ClothState, gripper: int) -> ClothState:
    """Detach every vertex from ``gripper``; they keep their current velocity."""
    return state.replace(grip=state.grip.at[gripper].set(0.0))


def move_gripper(cfg: ClothConfig, cloth: Cloth, state: ClothState, gripper: int, target,
                 n_steps: int, segment: int | None = None) -> ClothState:
    """Move gripper ``gripper`` in a straight line to ``target`` [m] at constant speed over
    ``n_steps`` substeps while simulating the cloth (other grippers hold their velocity)."""
    target = jnp.asarray(target, state.x.dtype)
    vel = (target - state.gripper_pos[gripper]) / (n_steps * cfg.dt)
    gv = jnp.broadcast_to(state.gripper_vel.at[gripper].set(vel),
                          (n_steps,) + state.gripper_vel.shape)
    out = rollout(cfg, cloth, state, n_steps, segment=segment, gripper_vel=gv)
    return out.replace(gripper_vel=out.gripper_vel.at[gripper].set(0.0))


@dataclasses.dataclass(frozen=True)
class PickPlace:
    """Static schedule of the pick-and-place macro (durations in substeps).

    approach_steps: gripper descends from ``approach_height`` [m] above the pick point.
    lift_steps: lifts the grasp to ``lift_height`` [m] above the higher of pick and place.
    move_steps: moves horizontally to above the place point.
    lower_steps: lowers onto the place point.
    settle_steps: after release, the cloth settles.
    radius: grasp radius [m]. snap: contact adjustment (pick the nearest vertex).
    gripper: which gripper to use. segment: substeps per checkpointed segment
    (:func:`dax_physics.checkpointed_scan`).
    """

    approach_steps: int = 100
    lift_steps: int = 1000
    move_steps: int = 2000
    lower_steps: int = 1000
    settle_steps: int = 2000
    approach_height: float = 0.05
    lift_height: float = 0.1
    radius: float = 0.02
    snap: bool = True
    gripper: int = 0
    segment: int | None = None

    @property
    def n_steps(self) -> int:
        return (self.approach_steps + self.lift_steps + self.move_steps + self.lower_steps
                + self.settle_steps)


def pick_and_place(cfg: ClothConfig, cloth: Cloth, state: ClothState, pick, place,
                   schedule: PickPlace = PickPlace()) -> ClothState:
    """Pick at ``pick`` [m], carry to ``place`` [m], release and settle: approach, grasp,
    lift, move, lower, release, settle - all substeps inside ``lax.scan`` s.

    Differentiable with respect to ``place`` (and ``pick`` when ``snap=False``, through the
    gripper path) and to the cloth's material arrays. See :func:`grasp` for the behaviour
    with nothing in reach or a non-finite pick point.
    """
    _check_point("pick point", pick)
    _check_point("place point", place)
    sc = schedule
    g = sc.gripper
    dt = cfg.dt
    dtype = state.x.dtype
    pick = jnp.asarray(pick, dtype)
    place = jnp.asarray(place, dtype)
    ok = jnp.all(jnp.isfinite(pick)) & jnp.all(jnp.isfinite(place))
    pick = jnp.where(ok, pick, 0.0)
    place = jnp.where(ok, place, 0.0)
    if sc.snap:
        pick = nearest_vertex_point(state, pick)
    up = jnp.asarray([0.0, 0.0, 1.0], dtype)
    start = pick + sc.approach_height * up
    state = state.replace(gripper_pos=state.gripper_pos.at[g].set(start))
    if sc.approach_steps:
        state = move_gripper(cfg, cloth, state, g, pick, sc.approach_steps, sc.segment)
    # an invalid (non-finite) pick/place grasps nothing: a no-op for the cloth
    state = grasp(state, g, jnp.where(ok, pick, jnp.nan), sc.radius, snap=False)
    z_lift = jnp.maximum(pick[2], place[2]) + sc.lift_height
    p1 = pick.at[2].set(z_lift)
    p2 = place.at[2].set(z_lift)
    vels = []
    for a, b, n in ((pick, p1, sc.lift_steps), (p1, p2, sc.move_steps),
                    (p2, place, sc.lower_steps)):
        if n:
            vel = (b - a) / (n * dt)
            vels.append(jnp.broadcast_to(state.gripper_vel.at[g].set(vel),
                                         (n,) + state.gripper_vel.shape))
    if vels:
        gv = jnp.concatenate(vels)
        state = rollout(cfg, cloth, state, gv.shape[0], segment=sc.segment, gripper_vel=gv)
    state = release(state, g).replace(gripper_vel=state.gripper_vel.at[g].set(0.0))
    return rollout(cfg, cloth, state, sc.settle_steps, segment=sc.segment)
