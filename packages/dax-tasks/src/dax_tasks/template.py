"""The task template: a declarative :class:`TaskSpec`, a few pure functions
(:class:`TaskDef`) and one generic :class:`Task` that turns them into
``reset(key) -> (obs, state)`` and ``step(state, action) -> (obs, state, reward, done, info)``.

A task file provides

* ``init(key, spec) -> physics`` — a randomised initial physics state (jittable: it runs
  under ``jit`` and ``vmap``, so it cannot use NumPy on traced values);
* ``apply_action(spec, physics, action) -> physics`` — one environment step: the physics
  substeps as a ``lax.scan`` (e.g. :func:`dax_physics.rollout`);
* ``goal(spec) -> (N, 3)`` — the goal particle set [m];
* ``object_points(spec, physics) -> (N, 3)`` — the particles the distance compares;
* ``end_effector(spec, physics) -> (3,)`` — the gripper / pusher position [m];
* optionally ``observe(spec, physics) -> obs``; the default is the object points
  (every ``spec.obs_stride``-th) flattened, followed by the end-effector position;
* optionally ``distance(spec, physics, goal) -> D`` [m] — replaces ``spec.distance`` for a
  task whose distance is not a point-set distance (e.g. the liquid left outside a target
  bowl); it must be differentiable and >= 0;
* optionally ``expert(spec, state: TaskState) -> action`` — a scripted expert with
  privileged state (it may read ``state.physics``, ``state.goal`` and the step counter
  ``state.t``); pure and jittable. dax-data records demonstrations with it.

Everything else (rewards, step counter, ``done``, bounds, batching, input checks) is here,
once, for every task.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from dax_physics import pytree_dataclass

from . import goals, rewards

ACTION_KINDS = ("push", "pick_place", "velocity")


@dataclasses.dataclass(frozen=True)
class TaskSpec:
    """Static, hashable description of a task (changing it recompiles).

    name: task name.
    horizon: episode length in environment steps; ``done`` once the counter reaches it.
    action_kind: ``push`` / ``pick_place`` (macro actions (x, y, z, x', y', z') [m]) or
        ``velocity`` (low-level velocity commands).
    action_low, action_high: per-dimension bounds (tuples of floats). Actions are clipped to
        them inside ``step`` (the gradient is zero across a clipped dimension).
    substeps: physics substeps per environment step.
    distance: ``"l2"`` (index correspondence) or ``"chamfer"``; see :mod:`dax_tasks.rewards`.
    lam: λ [1/m] of ``r_gt = exp(-λ D)``.
    aux_reward: add ``r_aux = exp(-||end-effector - nearest object particle||)`` to the
        reward (training); evaluation uses ``r_gt`` only (always in ``info['r_gt']``).
    contact_adjustment: for macro actions, snap the push/pick start to the object.
    obs_stride: the observation holds every ``obs_stride``-th object particle.
    scene: task-specific static data (a frozen dataclass: materials, resolution, ...).
    """

    name: str
    horizon: int
    action_kind: str
    action_low: tuple
    action_high: tuple
    substeps: int
    distance: str = "l2"
    lam: float = 1.0
    aux_reward: bool = False
    contact_adjustment: bool = True
    obs_stride: int = 1
    scene: Any = None

    def __post_init__(self):
        low = tuple(float(v) for v in self.action_low)
        high = tuple(float(v) for v in self.action_high)
        object.__setattr__(self, "action_low", low)
        object.__setattr__(self, "action_high", high)
        if not low or len(low) != len(high):
            raise ValueError(f"action bounds must be non-empty and of equal length, got "
                             f"{len(low)} low and {len(high)} high values")
        if not all(math.isfinite(a) and math.isfinite(b) and a <= b
                   for a, b in zip(low, high, strict=True)):
            raise ValueError(f"action bounds must be finite with low <= high, got {low}, {high}")
        if self.action_kind not in ACTION_KINDS:
            raise ValueError(f"unknown action kind {self.action_kind!r}; "
                             f"valid: {', '.join(ACTION_KINDS)}")
        if self.distance not in rewards.DISTANCES:
            raise ValueError(f"unknown distance {self.distance!r}; "
                             f"valid: {', '.join(rewards.DISTANCES)}")
        for field in ("horizon", "substeps", "obs_stride"):
            value = getattr(self, field)
            if not (isinstance(value, int) and value > 0):
                raise ValueError(f"{field} must be a positive int, got {value!r}")
        if not (math.isfinite(self.lam) and self.lam > 0):
            raise ValueError(f"lam must be a positive number in 1/m, got {self.lam}")
        hash(self.scene)  # a scene that is not hashable cannot be a static argument

    @property
    def action_dim(self) -> int:
        return len(self.action_low)


@dataclasses.dataclass(frozen=True)
class Box:
    """Bounds of an action or observation array (a minimal stand-in for Gymnasium's Box)."""

    low: np.ndarray
    high: np.ndarray
    shape: tuple
    dtype: Any = np.float32

    def sample(self, key):
        """A uniform sample (jax array); infinite bounds are replaced by [-1, 1]."""
        low = np.where(np.isfinite(self.low), self.low, -1.0)
        high = np.where(np.isfinite(self.high), self.high, 1.0)
        return jax.random.uniform(key, self.shape, self.dtype, low, high)

    def contains(self, x) -> bool:
        x = np.asarray(x)
        return (x.shape == self.shape and bool(np.all(np.isfinite(x)))
                and bool(np.all((x >= self.low) & (x <= self.high))))


def largest_divisor(n: int, at_most: int) -> int:
    """The largest divisor of ``n`` that is at most ``at_most`` (a segment length)."""
    return max(d for d in range(1, min(n, at_most) + 1) if n % d == 0)


def checkpointed_substeps(body, state, n: int, segment: int):
    """``state`` after ``body(state, i)`` for substeps ``i = 0 .. n - 1`` (int32): one
    ``lax.scan`` over segments of ``largest_divisor(n, segment)`` substeps, each wrapped in
    ``jax.checkpoint``, so reverse-mode memory grows with the number of segments rather
    than substeps (for an ``apply_action`` that acts on every substep)."""
    length = largest_divisor(n, segment)
    idx = jnp.arange(n, dtype=jnp.int32).reshape(n // length, length)

    @jax.checkpoint
    def seg(s, ii):
        return jax.lax.scan(lambda c, i: (body(c, i), None), s, ii)[0]

    return jax.lax.scan(lambda s, ii: (seg(s, ii), None), state, idx)[0]


def default_observe(defn: TaskDef, spec: TaskSpec, physics):
    pts = defn.object_points(spec, physics)[:: spec.obs_stride]
    return jnp.concatenate([pts.reshape(-1), defn.end_effector(spec, physics)])


@dataclasses.dataclass(frozen=True)
class TaskDef:
    """A task: its default spec and its pure functions (see the module docstring)."""

    spec: TaskSpec
    init: Callable
    apply_action: Callable
    goal: Callable
    object_points: Callable
    end_effector: Callable
    observe: Callable | None = None
    expert: Callable | None = None
    distance: Callable | None = None


@pytree_dataclass
class TaskState:
    """Dynamic state of one episode.

    physics: the simulator state (e.g. :class:`dax_physics.MPMState`).
    goal: goal particle set [m] (N, 3); part of the state so goals can be swapped or
        batched without recompiling.
    t: environment steps taken (int32).
    finite: every action and physics state so far was finite (bool).
    """

    physics: Any
    goal: jnp.ndarray
    t: jnp.ndarray
    finite: jnp.ndarray


def _is_traced(x) -> bool:
    return any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves(x))


class Task:
    """A task built from a :class:`TaskDef` (and optionally a replacement spec).

    ``reset`` and ``step`` are pure functions of their arguments: jit them, vmap them,
    differentiate ``step`` with respect to the action or the state (``step_diff`` is the
    same function, under the name the literature uses). Called eagerly they check their
    input and run a jitted implementation.

    batch_size: ``None`` for one environment; ``B`` gives states and actions a leading
        batch axis of size ``B`` (``vmap`` inside).
    seed: the key ``reset()`` uses when called without one.
    goal_path: a goal file (:mod:`dax_tasks.goals`) to use instead of the task's own goal;
        by default the goal comes from the cache directory, or is computed by the task's
        ``goal(spec)`` and cached there (``cache_goal=False`` computes it every time).

    **Bad input.** Eagerly (concrete arrays) a wrong action shape, a NaN/inf action or a
    wrong key shape raise ``ValueError``. Under ``jit``/``grad`` the values are not
    inspected (that would need a host sync): a wrong shape still fails at trace time, but a
    NaN action propagates into the physics and turns ``info['finite']`` (and the state's
    ``finite`` flag) false; it is never silently replaced.
    """

    def __init__(self, defn: TaskDef, spec: TaskSpec | None = None,
                 batch_size: int | None = None, seed: int = 0, goal_path=None,
                 cache_goal: bool = True):
        if batch_size is not None and not (isinstance(batch_size, int) and batch_size > 0):
            raise ValueError(f"batch_size must be None or a positive int, got {batch_size!r}")
        self.defn = defn
        self.spec = defn.spec if spec is None else spec
        self.batch_size = batch_size
        self.seed = int(seed)
        n_points = None
        if defn.distance is None and self.spec.distance == "l2":
            def points(key):
                return defn.object_points(self.spec, defn.init(key, self.spec))
            n_points = jax.eval_shape(points, jax.random.PRNGKey(0)).shape[0]
        #: The goal particle set [m] (NumPy) and where it came from (see dax_tasks.goals).
        self.goal, self.goal_provenance = goals.resolve_goal(
            defn, self.spec, goal_path, use_cache=cache_goal, n_points=n_points)
        low = np.asarray(self.spec.action_low, np.float32)
        high = np.asarray(self.spec.action_high, np.float32)
        self.single_action_space = Box(low, high, low.shape)
        self.action_shape = low.shape if batch_size is None else (batch_size, *low.shape)
        self.action_space = Box(np.broadcast_to(low, self.action_shape),
                                np.broadcast_to(high, self.action_shape), self.action_shape)
        obs = jax.eval_shape(self._reset_one, jax.random.PRNGKey(0))[0]
        self.single_observation_space = Box(np.full(obs.shape, -np.inf, np.float32),
                                            np.full(obs.shape, np.inf, np.float32), obs.shape)
        oshape = obs.shape if batch_size is None else (batch_size, *obs.shape)
        self.observation_space = Box(np.full(oshape, -np.inf, np.float32),
                                     np.full(oshape, np.inf, np.float32), oshape)
        reset, step = self._reset_one, self._step_one
        if batch_size is not None:
            reset, step = jax.vmap(reset), jax.vmap(step)
        self._reset = jax.jit(reset)
        self._step = jax.jit(step)
        self._expert = None
        if defn.expert is not None:
            expert = self._expert_one if batch_size is None else jax.vmap(self._expert_one)
            self._expert = jax.jit(expert)

    @property
    def horizon(self) -> int:
        return self.spec.horizon

    def __repr__(self):
        return f"Task({self.spec.name!r}, batch_size={self.batch_size})"

    # ------------------------------------------------------------------ pure single-env core
    def _observe(self, physics):
        if self.defn.observe is not None:
            return self.defn.observe(self.spec, physics)
        return default_observe(self.defn, self.spec, physics)

    def _reset_one(self, key):
        physics = self.defn.init(key, self.spec)
        goal = jnp.asarray(self.goal, jnp.float32)
        state = TaskState(physics=physics, goal=goal, t=jnp.zeros((), jnp.int32),
                          finite=jnp.asarray(True))
        return self._observe(physics), state

    def _step_one(self, state: TaskState, action):
        spec = self.spec
        action = jnp.asarray(action, jnp.float32)
        finite_action = jnp.all(jnp.isfinite(action))
        action = jnp.clip(action, jnp.asarray(spec.action_low, jnp.float32),
                          jnp.asarray(spec.action_high, jnp.float32))
        physics = self.defn.apply_action(spec, state.physics, action)
        pts = self.defn.object_points(spec, physics)
        if self.defn.distance is not None:
            dist = self.defn.distance(spec, physics, state.goal)
        else:
            dist = rewards.DISTANCES[spec.distance](pts, state.goal)
        r_gt = rewards.ground_truth_reward(dist, spec.lam)
        r_aux = rewards.auxiliary_reward(self.defn.end_effector(spec, physics), pts)
        reward = r_gt + r_aux if spec.aux_reward else r_gt
        physics_finite = getattr(physics, "finite", jnp.all(jnp.isfinite(pts)))
        finite = state.finite & finite_action & physics_finite & jnp.isfinite(reward)
        t = state.t + 1
        done = t >= spec.horizon
        escaped = getattr(physics, "escaped", jnp.asarray(False))
        info = {"r_gt": r_gt, "r_aux": r_aux, "distance": dist, "finite": finite,
                "escaped": escaped, "t": t}
        new_state = TaskState(physics=physics, goal=state.goal, t=t, finite=finite)
        return self._observe(physics), new_state, reward, done, info

    def _expert_one(self, state: TaskState):
        action = jnp.asarray(self.defn.expert(self.spec, state), jnp.float32)
        return jnp.clip(action, jnp.asarray(self.spec.action_low, jnp.float32),
                        jnp.asarray(self.spec.action_high, jnp.float32))

    # ------------------------------------------------------------------ public API
    @property
    def has_expert(self) -> bool:
        return self.defn.expert is not None

    def expert_action(self, state: TaskState):
        """The scripted expert's action for ``state`` (batched when the task is), inside
        the action bounds. Raises ``NotImplementedError`` if the task has no expert."""
        if self._expert is None:
            raise NotImplementedError(f"task {self.spec.name!r} has no scripted expert")
        return self._expert(state)

    def reset(self, key=None):
        """``(obs, state)`` of a new episode; ``key`` defaults to ``PRNGKey(seed)``. With a
        batch, one key is split into ``batch_size`` keys (or pass ``(B, 2)`` keys)."""
        if key is None:
            key = jax.random.PRNGKey(self.seed)
        if self.batch_size is not None:
            key = jnp.asarray(key) if not _is_traced(key) else key
            if key.shape == (2,):
                key = jax.random.split(key, self.batch_size)
            elif key.shape != (self.batch_size, 2):
                raise ValueError(f"expected a PRNGKey of shape (2,) or ({self.batch_size}, 2), "
                                 f"got {key.shape}")
        elif not _is_traced(key) and jnp.shape(key) != (2,):
            raise ValueError(f"expected a PRNGKey of shape (2,), got {jnp.shape(key)}")
        return self._reset(key)

    def step(self, state: TaskState, action):
        """``(obs, state, reward, done, info)`` after one environment step."""
        self.check_action(action)
        return self._step(state, action)

    #: The differentiable step: the same pure function (the literature's name for it).
    step_diff = step

    def check_action(self, action) -> None:
        """Raise ``ValueError`` for a wrong shape, or (for concrete arrays) NaN/inf."""
        shape = tuple(jnp.shape(action))
        if shape != self.action_shape:
            kind = self.spec.action_kind
            raise ValueError(f"{self.spec.name}: expected a {kind} action of shape "
                             f"{self.action_shape}, got {shape}")
        if not _is_traced(action):
            a = np.asarray(action)
            if not np.all(np.isfinite(a)):
                raise ValueError(f"{self.spec.name}: action contains NaN or inf: {a.tolist()}")

    # ------------------------------------------------------------------ images
    @property
    def view(self) -> tuple:
        """``(x0, x1, y0, y1, z0)`` [m]: the table window images show (see
        :mod:`dax_tasks.render`), around the goal and the start of episode ``seed``. Each
        object point covers a disc of 0.75 x the points' median spacing."""
        if getattr(self, "_view", None) is None:
            from . import render

            with jax.ensure_compile_time_eval():
                _, state = jax.jit(self._reset_one)(jax.random.PRNGKey(self.seed))
                pts = np.asarray(self.defn.object_points(self.spec, state.physics))
                ee = np.asarray(self.defn.end_effector(self.spec, state.physics))
            self._view = render.view_window(pts, extra=(self.goal, ee))
            self._splat = 0.75 * render.point_spacing(pts)
        return self._view

    def _images_one(self, state: TaskState, res: int):
        from . import render

        pts = self.defn.object_points(self.spec, state.physics)
        ee = self.defn.end_effector(self.spec, state.physics)
        view = self.view
        return {"height": render.height_map(pts, view, res, self._splat),
                "rgb": render.rgb_image(pts, ee, view, res, self._splat)}

    def image_obs(self, state: TaskState, res: int = 64):
        """Image observations of ``state``: ``{"height": (res, res) float32 [m], "rgb":
        (res, res, 3) uint8}`` (a leading batch axis when the task is batched). Pure JAX: it
        can be called inside ``jit``; eagerly it runs a jitted, cached implementation."""
        key = ("images", res)
        cache = self.__dict__.setdefault("_image_fns", {})
        if key not in cache:
            _ = self.view  # computed once, outside any trace
            fn = lambda s: self._images_one(s, res)  # noqa: E731
            cache[key] = jax.jit(fn if self.batch_size is None else jax.vmap(fn))
        return cache[key](state)

    def render(self, state: TaskState, res: int = 256) -> np.ndarray:
        """An RGB frame (res, res, 3) uint8 of ``state`` seen from above (NumPy); for a
        batched task, one frame per environment (B, res, res, 3)."""
        return np.asarray(self.image_obs(state, res)["rgb"])
