"""A smooth analytic toy task for checking learners: a point reaching a goal.

``PointReach`` is a :class:`dax_tasks.Env` like the nine tasks (same reset/step, params,
wrappers, rewards), but its physics is one line: the point ``x`` (3,) [m] moves by
``speed * action * dt`` per step, actions are velocities in [-1, 1]^3 [m/s] (scaled by
``params.physics``, the speed gain), and ``r_gt = exp(-λ |x - g|)`` with the goal ``g``
at the origin. Starts lie at a random direction and a distance drawn from
``[start_min, start_max]``. The return-maximising policy is known in closed form: the
reward decreases with the distance, and the action box is separable, so moving every
coordinate toward the goal by as much as the box allows is optimal at every step at once
(:func:`optimal_return`).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from dax_tasks import Env, TaskSpec


@dataclasses.dataclass(frozen=True)
class PointScene:
    """dt: seconds per step; start_min / start_max: start distance range [m]."""

    dt: float = 0.05
    start_min: float = 0.3
    start_max: float = 0.6


class PointReach(Env):
    """See the module docstring."""

    LAM = 5.0

    @property
    def substep_dt(self) -> float:
        return self.spec.scene.dt

    def default_physics_params(self):
        return jnp.asarray(1.0, jnp.float32)  # speed gain [-]

    def init(self, key, params):
        k_dir, k_r = jax.random.split(key)
        d = jax.random.normal(k_dir, (3,))
        d = d / jnp.linalg.norm(d)
        scene = self.spec.scene
        r = jax.random.uniform(k_r, (), minval=scene.start_min, maxval=scene.start_max)
        return (d * r).astype(jnp.float32)

    def apply_action(self, physics, action, params):
        return physics + params.physics * action * self.spec.scene.dt

    def object_points(self, physics):
        return physics[None]

    def end_effector(self, physics):
        return physics

    def canonical_goal(self) -> np.ndarray:
        return np.zeros((1, 3), np.float32)

    def expert(self, state, params):
        return jnp.clip(-state.physics / (params.physics * self.spec.scene.dt), -1.0, 1.0)


def point_reach(horizon: int = 10, **scene) -> PointReach:
    """The toy env with its goal (no file is read or written)."""
    spec = TaskSpec(name="point_reach", horizon=horizon, action_kind="velocity",
                    action_low=(-1.0,) * 3, action_high=(1.0,) * 3, substeps=1,
                    contact_adjustment=False, scene=PointScene(**scene))
    env = PointReach(spec)
    return env.with_goal(env.canonical_goal())


def optimal_return(env: PointReach, keys) -> np.ndarray:
    """The optimal return (sum of r_gt) of the episodes started from each of ``keys``:
    the expert's (each coordinate moved toward the goal as far as the box allows)."""

    def episode(key):
        _, state = env.reset(key)

        def body(state, _):
            _, state, _, _, info = env.step(state, env.expert_action(state))
            return state, info["r_gt"]

        return jnp.sum(jax.lax.scan(body, state, None, length=env.horizon)[1])

    return np.asarray(jax.jit(jax.vmap(episode))(keys))
