"""Gymnasium adapters: one environment (:class:`DaxEnv`) and a batched vector environment
(:class:`DaxVectorEnv`) over any dax-tasks task, registered as

    dax/PourWater-v0  dax/PourSoup-v0  dax/PushRope-v0  dax/WhipRope-v0  dax/FoldCloth1-v0
    dax/FoldCloth3-v0  dax/FoldTShirt-v0  dax/UnfoldCloth1-v0  dax/UnfoldCloth3-v0

This is the only module of dax-tasks that imports gymnasium (the ``gym`` extra), and
importing it registers the nine ids (``import dax_tasks`` alone does not import gymnasium
and registers nothing with it). Either import it first or let Gymnasium import it through
the id's module prefix, as Gymnasium documents for ``"module:id"``::

    env = gymnasium.make("dax_tasks.gym:dax/FoldCloth1-v0", seed=0)
    venv = gymnasium.make_vec("dax_tasks.gym:dax/FoldCloth1-v0", num_envs=8,
                              vectorization_mode="vector_entry_point")

The registered entry points are strings (``"dax_tasks.gym:DaxEnv"``), so an
:class:`gymnasium.envs.registration.EnvSpec` saved elsewhere (a Minari dataset's) makes its
environment in a fresh process without any import first.

``make``'s keyword arguments: ``seed`` (the first reset's seed when ``reset`` gets none),
``obs_mode`` and ``image_size`` (:class:`dax_tasks.core.wrappers.ObservationMode`:
``state``, ``particles``, ``height``, ``rgb``, ``rgbd``) and every other ``kwarg`` but
``render_mode`` go to :func:`dax_tasks.make` (``goal_path``, spec overrides, ``lam``,
``aux_weight``).

Semantics. Observations are NumPy arrays of the observation space's dtype (float32, or
uint8 for ``rgb``); ``reward`` is the task's reward (``r_gt``, plus ``aux_weight * r_aux``);
``info`` carries ``r_gt``, ``distance``, ``finite``, ``t`` and ``clipped``. Episodes end by
time only: ``truncated`` is true at the task's horizon and ``terminated`` is always false.
``reset(seed=s)`` is deterministic: the same seed gives the same start; a first ``reset()``
without a seed uses the ``seed`` given to ``gymnasium.make`` (default 0), so it is
deterministic too (later seedless resets continue the environment's random stream).

Actions. A wrong shape or a NaN/inf raises ``ValueError`` naming the problem
(:func:`dax_tasks.core.checks.check_action`). Actions outside the bounds are *clipped* to them
(``info["clipped"]`` says when), as the pure env does.

Why not Gymnasium's ``FunctionalJaxEnv``/``FunctionalJaxVectorEnv``: they call the
transition and the reward as separate functions (which would run the physics twice or
recompute the reward), do not check actions, and their vector autoreset indexes the state
as one array (``state.at[...]``), which fails on a task state that is a pytree.
"""

from __future__ import annotations

from typing import Any

import gymnasium
import jax
import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode

from . import viz as _viz
from .core.checks import check_action
from .core.registry import make
from .core.wrappers import VmapWrapper

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

RENDER_RES = 256


def _box(box, batch: tuple = ()) -> spaces.Box:
    shape = tuple(batch) + tuple(box.shape)
    low = np.broadcast_to(np.asarray(box.low), shape)
    high = np.broadcast_to(np.asarray(box.high), shape)
    return spaces.Box(low.astype(box.dtype), high.astype(box.dtype), shape=shape,
                      dtype=box.dtype)


def _clipped(action, low, high, axis=None):
    """Whether ``action`` (as given, before :func:`check_action` clipped it) lies outside
    the action space's float32 bounds (per environment with ``axis=-1``)."""
    a = np.asarray(action, np.float64)
    return np.any((a < low) | (a > high), axis=axis)


def _info(info: dict, clipped) -> dict:
    out = {k: np.asarray(v) for k, v in info.items()}
    out["clipped"] = np.asarray(clipped)
    return out


class _Adapter:
    """What the single and the vector adapter share: the env, its bounds and camera."""

    def _build(self, task: str, render_mode: str | None, seed: int, make_kwargs: dict):
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.env = make(task, **make_kwargs)
        self.render_mode = render_mode
        self.seed = int(seed)
        self._low = np.asarray(self.env.spec.action_low, np.float32)
        self._high = np.asarray(self.env.spec.action_high, np.float32)
        self._obs_dtype = self.env.observation_space.dtype
        self._camera = None
        self._state = None

    @property
    def task(self):
        """The pure env (:class:`dax_tasks.Env`, possibly in an observation wrapper)."""
        return self.env

    @property
    def state(self):
        """The env state (a pytree of JAX arrays) of the current episode."""
        return self._state

    def _frame(self):
        if self._camera is None:
            self._camera = _viz.Camera.for_env(self.env)
        return _viz.render(self.env, self._state, RENDER_RES, self._camera)

    def _key(self, seed):
        if seed is None and self._np_random is None:
            seed = self.seed  # the first reset follows gymnasium.make(..., seed=s)
        return seed


class DaxEnv(_Adapter, gymnasium.Env):
    """One environment of task ``task`` (see the module docstring)."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 4}

    def __init__(self, task: str = "fold_cloth1", render_mode: str | None = None,
                 seed: int = 0, **make_kwargs: Any):
        self._build(task, render_mode, seed, make_kwargs)
        self.action_space = _box(self.env.action_space)
        self.observation_space = _box(self.env.observation_space)
        self._reset = jax.jit(self.env.reset)
        self._step = jax.jit(self.env.step)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=self._key(seed))
        key = jax.random.PRNGKey(int(self.np_random.integers(0, 2**31 - 1)))
        obs, self._state = self._reset(key)
        return np.asarray(obs, self._obs_dtype), {}

    def step(self, action):
        if self._state is None:
            raise RuntimeError("call reset() before step()")
        a = check_action(self.env, action)  # clipped to the bounds
        clipped = _clipped(action, self._low, self._high)
        obs, self._state, reward, done, info = self._step(self._state, a)
        return (np.asarray(obs, self._obs_dtype), float(reward), False, bool(done),
                _info(info, clipped))

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        if self._state is None:
            raise RuntimeError("call reset() before render()")
        return self._frame()


class DaxVectorEnv(_Adapter, gymnasium.vector.VectorEnv):
    """``num_envs`` environments of one task stepped together (one ``vmap``-ed ``jit`` call
    per step, :class:`dax_tasks.core.wrappers.VmapWrapper`). All environments share the horizon,
    so they end together; the step after the end resets them all
    (``AutoresetMode.NEXT_STEP``: that step's actions are ignored and its rewards are 0)."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 4,
                "autoreset_mode": AutoresetMode.NEXT_STEP}

    def __init__(self, task: str = "fold_cloth1", num_envs: int = 2,
                 render_mode: str | None = None, seed: int = 0, **make_kwargs: Any):
        self._build(task, render_mode, seed, make_kwargs)
        self.num_envs = num_envs
        self.single_action_space = _box(self.env.action_space)
        self.single_observation_space = _box(self.env.observation_space)
        self.action_space = _box(self.env.action_space, (num_envs,))
        self.observation_space = _box(self.env.observation_space, (num_envs,))
        batch = VmapWrapper(self.env, batch_size=num_envs)
        self._reset = jax.jit(batch.reset)
        self._step = jax.jit(batch.step)
        self._needs_reset = False

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        seed = self._key(seed)
        if seed is not None:
            self._np_random, self._np_random_seed = gymnasium.utils.seeding.np_random(seed)
        key = jax.random.PRNGKey(int(self.np_random.integers(0, 2**31 - 1)))
        obs, self._state = self._reset(key)
        self._needs_reset = False
        return np.asarray(obs, self._obs_dtype), {}

    def step(self, actions):
        if self._state is None:
            raise RuntimeError("call reset() before step()")
        if self._needs_reset:
            obs, _ = self.reset()
            zeros = np.zeros(self.num_envs, np.float32)
            false = np.zeros(self.num_envs, bool)
            return obs, zeros, false, false, {}
        a = check_action(self.env, actions, (self.num_envs,))  # clipped to the bounds
        clipped = _clipped(actions, self._low, self._high, axis=-1)
        obs, self._state, reward, done, info = self._step(self._state, a)
        truncated = np.asarray(done, bool)
        self._needs_reset = bool(truncated.any())
        return (np.asarray(obs, self._obs_dtype), np.asarray(reward, np.float32),
                np.zeros(self.num_envs, bool), truncated, _info(info, clipped))

    def render(self):
        if self.render_mode != "rgb_array" or self._state is None:
            return None
        return tuple(self._frame())


def register_all() -> None:
    """Register the nine Gymnasium ids (idempotent; run when this module is imported)."""
    for name, env_id in GYM_IDS.items():
        if env_id in gymnasium.registry:
            continue
        gymnasium.register(id=env_id, entry_point="dax_tasks.gym:DaxEnv",
                           vector_entry_point="dax_tasks.gym:DaxVectorEnv",
                           kwargs={"task": name})


register_all()
