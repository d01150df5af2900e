"""Gymnasium adapters: one environment (:class:`DaxEnv`) and a batched vector environment
(:class:`DaxVectorEnv`) over any dax-tasks task, registered on ``import dax_tasks`` as

    dax/PourWater-v0  dax/PourSoup-v0  dax/PushRope-v0  dax/WhipRope-v0  dax/FoldCloth1-v0
    dax/FoldCloth3-v0  dax/FoldTShirt-v0  dax/UnfoldCloth1-v0  dax/UnfoldCloth3-v0

``gymnasium.make("dax/FoldCloth1-v0", **kwargs)`` and ``gymnasium.make_vec(id, num_envs=B,
vectorization_mode="vector_entry_point", **kwargs)``: ``kwargs`` other than
``render_mode`` go to :func:`dax_tasks.make` (``seed``, ``goal_path``, spec overrides such as
``aux_reward=True``).

Semantics. Observations are float32 NumPy arrays (the task's flattened particle
observation); ``reward`` is the task's reward (``r_gt``, plus ``r_aux`` when the spec asks);
``info`` carries ``r_gt``, ``distance``, ``finite``, ``t`` and ``clipped``. Episodes end by
time only: ``truncated`` is true at the task's horizon and ``terminated`` is always false.
``reset(seed=s)`` is deterministic: the same seed gives the same start; a first ``reset()``
without a seed uses the ``seed`` given to ``gymnasium.make`` (default 0), so it is
deterministic too (later seedless resets continue the environment's random stream).

Actions. A wrong shape or a NaN/inf raises ``ValueError`` naming the problem. Actions
outside the bounds are *clipped* to them (``info["clipped"]`` says when), as the task itself
does; the gradient-based API (``dax_tasks.make``) has the same clipping.

Why not Gymnasium's ``FunctionalJaxEnv``/``FunctionalJaxVectorEnv``: they call the
transition and the reward as separate functions (which would run the physics twice or
recompute the reward), do not check actions, and their vector autoreset indexes the state
as one array (``state.at[...]``), which fails on a task state that is a pytree.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import jax
import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode

from .registry import TASKS, make

#: Gymnasium id of each task.
GYM_IDS = {
    "pour_water": "dax/PourWater-v0",
    "pour_soup": "dax/PourSoup-v0",
    "push_rope": "dax/PushRope-v0",
    "whip_rope": "dax/WhipRope-v0",
    "fold_cloth1": "dax/FoldCloth1-v0",
    "fold_cloth3": "dax/FoldCloth3-v0",
    "fold_tshirt": "dax/FoldTShirt-v0",
    "unfold_cloth1": "dax/UnfoldCloth1-v0",
    "unfold_cloth3": "dax/UnfoldCloth3-v0",
}
assert set(GYM_IDS) == set(TASKS)

RENDER_RES = 256


def _box(box) -> spaces.Box:
    return spaces.Box(np.asarray(box.low, np.float32), np.asarray(box.high, np.float32),
                      shape=tuple(box.shape), dtype=np.float32)


def _check_action(task_name: str, action, shape: tuple) -> np.ndarray:
    try:
        a = np.asarray(action, dtype=np.float32)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{task_name}: action is not an array of numbers ({err})") from None
    if a.shape != shape:
        raise ValueError(f"{task_name}: expected an action of shape {shape}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{task_name}: action contains NaN or inf: {a.tolist()}")
    return a


def _info(info: dict, clipped) -> dict:
    out = {k: np.asarray(v) for k, v in info.items()}
    out["clipped"] = np.asarray(clipped)
    return out


class DaxEnv(gym.Env):
    """One environment of task ``task`` (see the module docstring)."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 4}

    def __init__(self, task: str = "fold_cloth1", render_mode: str | None = None,
                 **make_kwargs: Any):
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.task = make(task, batch_size=None, **make_kwargs)
        self.render_mode = render_mode
        self.action_space = _box(self.task.action_space)
        self.observation_space = _box(self.task.observation_space)
        self._low = np.asarray(self.task.spec.action_low, np.float32)
        self._high = np.asarray(self.task.spec.action_high, np.float32)
        self._state = None

    @property
    def state(self):
        """The task state (a pytree of JAX arrays) of the current episode."""
        return self._state

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        if seed is None and self._np_random is None:
            seed = self.task.seed  # the first reset follows gymnasium.make(..., seed=s)
        super().reset(seed=seed)
        key = jax.random.PRNGKey(int(self.np_random.integers(0, 2**31 - 1)))
        obs, self._state = self.task.reset(key)
        return np.asarray(obs, np.float32), {}

    def step(self, action):
        if self._state is None:
            raise RuntimeError("call reset() before step()")
        a = _check_action(self.task.spec.name, action, self.action_space.shape)
        clipped = bool(np.any((a < self._low) | (a > self._high)))
        obs, self._state, reward, done, info = self.task.step(self._state, a)
        return (np.asarray(obs, np.float32), float(reward), False, bool(done),
                _info(info, clipped))

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        if self._state is None:
            raise RuntimeError("call reset() before render()")
        return self.task.render(self._state, res=RENDER_RES)


class DaxVectorEnv(gym.vector.VectorEnv):
    """``num_envs`` environments of one task stepped together by the batched task (one
    ``vmap``-ed ``jit`` call per step). All environments share the horizon, so they end
    together; the step after the end resets them all (``AutoresetMode.NEXT_STEP``: that
    step's actions are ignored and its rewards are 0)."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 4,
                "autoreset_mode": AutoresetMode.NEXT_STEP}

    def __init__(self, task: str = "fold_cloth1", num_envs: int = 2,
                 render_mode: str | None = None, **make_kwargs: Any):
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.task = make(task, batch_size=num_envs, **make_kwargs)
        self.num_envs = num_envs
        self.render_mode = render_mode
        self.single_action_space = _box(self.task.single_action_space)
        self.single_observation_space = _box(self.task.single_observation_space)
        self.action_space = _box(self.task.action_space)
        self.observation_space = _box(self.task.observation_space)
        self._low = np.asarray(self.task.spec.action_low, np.float32)
        self._high = np.asarray(self.task.spec.action_high, np.float32)
        self._state = None
        self._needs_reset = False

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        if seed is None and self._np_random is None:
            seed = self.task.seed  # the first reset follows gymnasium.make_vec(..., seed=s)
        if seed is not None:
            self._np_random, self._np_random_seed = gym.utils.seeding.np_random(seed)
        key = jax.random.PRNGKey(int(self.np_random.integers(0, 2**31 - 1)))
        obs, self._state = self.task.reset(key)
        self._needs_reset = False
        return np.asarray(obs, np.float32), {}

    def step(self, actions):
        if self._state is None:
            raise RuntimeError("call reset() before step()")
        if self._needs_reset:
            obs, _ = self.reset()
            zeros = np.zeros(self.num_envs, np.float32)
            false = np.zeros(self.num_envs, bool)
            return obs, zeros, false, false, {}
        a = _check_action(self.task.spec.name, actions, self.action_space.shape)
        clipped = np.any((a < self._low) | (a > self._high), axis=-1)
        obs, self._state, reward, done, info = self.task.step(self._state, a)
        truncated = np.asarray(done, bool)
        self._needs_reset = bool(truncated.any())
        return (np.asarray(obs, np.float32), np.asarray(reward, np.float32),
                np.zeros(self.num_envs, bool), truncated, _info(info, clipped))

    def render(self):
        if self.render_mode != "rgb_array" or self._state is None:
            return None
        return tuple(self.task.render(self._state, res=RENDER_RES))


def register_all() -> None:
    """Register the nine Gymnasium ids (idempotent)."""
    for name, env_id in GYM_IDS.items():
        if env_id in gym.registry:
            continue
        gym.register(id=env_id, entry_point="dax_tasks.gym_envs:DaxEnv",
                     vector_entry_point="dax_tasks.gym_envs:DaxVectorEnv",
                     kwargs={"task": name})
