"""The pure environment core: :class:`Env`, its :class:`EnvParams` and :class:`EnvState`.

In the style of gymnax and Brax, an environment is a pair of pure functions::

    obs, state = env.reset(key, params)
    obs, state, reward, done, info = env.step(state, action, params)

with ``params = env.default_params`` when omitted. Both work under ``jax.jit``,
``jax.vmap`` and ``jax.grad`` (with respect to actions, the float leaves of the state, and
the params). Nothing here jits, vmaps, reads files or inspects values on the host: batching,
auto-reset, episode statistics, observation modes and the Gymnasium adapter are wrappers
(:mod:`dax_tasks.core.wrappers`, :mod:`dax_tasks.gym`); goal files (:mod:`dax_tasks.core.goals`) and
the eager input checks (:mod:`dax_tasks.core.checks`) are host-side helpers at the boundary.

**Static and dynamic.** ``env.spec`` (a :class:`~dax_tasks.TaskSpec`) fixes shapes and the
program; changing it means a new env and a recompile. ``params`` (an :class:`EnvParams`
pytree) holds every number that may change without recompiling: the goal particle set,
λ, the weight of the auxiliary reward, and the task's physics numbers (friction
coefficients, material constants, cloth stiffnesses). Change them, batch them (domain
randomisation) or differentiate through them.

**A task** is a subclass that fills in the hooks (see :class:`Env`); the reward, the step
counter, ``done``, action clipping, the ``finite`` flag and the observation/action spaces
are here, once.
"""

from __future__ import annotations

import copy
import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from dax_physics import MPMConfig, check_params, pytree_dataclass

from . import rewards
from .spec import Box, TaskSpec


@pytree_dataclass
class EnvParams:
    """Every number of a task that may change without recompiling (a pytree).

    goal: the goal particle set (N, 3) [m].
    lam: λ [1/m] of ``r_gt = exp(-λ D)``.
    aux_weight: weight [-] of the auxiliary reward in ``reward = r_gt + aux_weight *
        r_aux``: 0 for evaluation (every task's default), 1 for the literature's training
        reward.
    physics: the task's physics numbers (for the MPM tasks a
        :class:`dax_physics.MaterialParams` with the colliders' friction; for the cloth
        tasks their ``ClothParams``).

    ``replace(**changes)`` casts the new values of ``goal``, ``lam`` and ``aux_weight`` to
    the old ones' dtype, so ``params.replace(lam=5.0)`` does not retrace a jitted step.
    """

    goal: jnp.ndarray
    lam: jnp.ndarray
    aux_weight: jnp.ndarray
    physics: Any

    def replace(self, **changes) -> EnvParams:
        return replace_cast(self, changes, keep=("physics",))


def replace_cast(params, changes: dict, keep=()):
    """``dataclasses.replace(params, **changes)`` with each new value (but those named in
    ``keep``) cast to the dtype of the value it replaces, so a Python float does not make a
    weakly typed leaf that retraces a jitted function."""
    for name, value in changes.items():
        old = getattr(params, name, None)
        if name not in keep and old is not None:
            changes[name] = jnp.asarray(value, jnp.result_type(old))
    return dataclasses.replace(params, **changes)


def _float_dtype(physics):
    """The float type of a physics state: that of its first floating-point leaf (float32
    if it has none)."""
    for leaf in jax.tree_util.tree_leaves(physics):
        if jnp.issubdtype(jnp.result_type(leaf), jnp.floating):
            return jnp.result_type(leaf)
    return jnp.float32


def _real_array(value, what: str):
    """``value`` as a JAX array of real numbers (float, int or uint); ``ValueError`` naming
    ``what`` for complex numbers (``0.1+5j`` would act as 0.1), text, bools or objects.
    The dtype is static, so this holds under ``jit`` too."""
    try:
        a = jnp.asarray(value)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{what} is not an array of numbers ({err})") from None
    if a.dtype.kind not in "fiu":
        raise ValueError(f"{what} is not an array of real numbers (dtype {a.dtype})")
    return a


def _eager() -> bool:
    """Whether this code runs outside ``jit`` / ``scan`` tracing (where an operation gives a
    concrete array, not a tracer; ``vmap`` and ``grad`` of concrete values included)."""
    return not isinstance(jnp.add(0, 0), jax.core.Tracer)


def float_dtype():
    """The float type tasks compute in: float32, or float64 when JAX's ``jax_enable_x64``
    is on (then :meth:`Env.reset` returns a float64 physics state)."""
    return jnp.dtype(jax.dtypes.canonicalize_dtype(jnp.float64))


def cast_floats(tree, dtype):
    """``tree`` with every floating-point leaf cast to ``dtype`` (other leaves as they
    are; a leaf already of ``dtype`` is returned unchanged)."""
    def cast(leaf):
        if jnp.issubdtype(jnp.result_type(leaf), jnp.floating) and \
                jnp.result_type(leaf) != dtype:
            return jnp.asarray(leaf).astype(dtype)
        return leaf

    return jax.tree_util.tree_map(cast, tree)


@pytree_dataclass
class EnvState:
    """Dynamic state of one episode (a pytree).

    physics: the simulator state (e.g. :class:`dax_physics.MPMState`).
    t: environment steps taken in this episode (int32).
    finite: every action, physics state and reward of the episode so far was finite.
    extras: data the wrappers keep (episode statistics, the auto-reset key, ...); the
        bare env leaves it empty.
    """

    physics: Any
    t: jnp.ndarray
    finite: jnp.ndarray
    extras: dict = dataclasses.field(default_factory=dict)


class Env:
    """A task as a pure environment. Subclasses implement the hooks:

    * ``substep_dt`` (property): the physics substep [s];
    * ``default_physics_params()``: the default ``params.physics`` pytree;
    * ``init(key, params) -> physics``: a randomised initial physics state (jittable);
    * ``apply_action(physics, action, params) -> physics``: one environment step, the
      ``spec.substeps`` substeps as one scan;
    * ``object_points(physics) -> (N, 3)``, ``end_effector(physics) -> (3,)`` [m];
    * ``canonical_goal() -> (N, 3)`` [m] (NumPy): the goal computed from scratch (a
      scripted motion or a direct definition); :func:`dax_tasks.make` caches it on disk;

    and optionally override ``observe(physics)`` (default: every ``spec.obs_stride``-th
    object point, flattened, then the end effector), ``distance(physics, goal) -> D`` [m]
    (default: ``spec.distance`` between the object points and the goal),
    ``expert(state, params) -> action`` (a scripted expert with privileged state),
    ``check_physics_params(physics)`` (eager validation), ``object_faces`` (a mesh's
    triangles) and ``object_colors`` (a colour per point for RGB pictures). ``LAM`` is the
    default λ [1/m].

    An env needs its goal before ``default_params`` exists: :func:`dax_tasks.make` resolves
    it (file, cache, or ``canonical_goal``) and returns ``env.with_goal(points)``.
    """

    #: Default λ [1/m] of the task.
    LAM: float = 1.0

    def __init__(self, spec: TaskSpec):
        self.spec = spec
        self._goal: np.ndarray | None = None
        #: Where the goal came from (see :mod:`dax_tasks.core.goals`); set by ``with_goal``.
        self.goal_provenance: dict | None = None
        self._cache: dict = {}

    def __repr__(self):
        return f"{type(self).__name__}({self.spec.name!r})"

    # ------------------------------------------------------------------ hooks
    @property
    def substep_dt(self) -> float:
        raise NotImplementedError

    def default_physics_params(self):
        raise NotImplementedError

    def init(self, key, params: EnvParams):
        raise NotImplementedError

    def apply_action(self, physics, action, params: EnvParams):
        raise NotImplementedError

    def object_points(self, physics):
        raise NotImplementedError

    def end_effector(self, physics):
        raise NotImplementedError

    def canonical_goal(self) -> np.ndarray:
        raise NotImplementedError

    @property
    def object_faces(self):
        """Triangle faces (F, 3) of the object's surface for rendering and export (a
        cloth's mesh), or ``None`` when the object is particles."""
        return None

    @property
    def object_colors(self):
        """A colour per object point (N, 3) in [0, 1] (NumPy), the object's texture in RGB
        pictures (:func:`dax_tasks.viz.rgb_image`), or ``None``: shaded by height."""
        return None

    def observe(self, physics):
        pts = self.object_points(physics)[:: self.spec.obs_stride]
        return jnp.concatenate([pts.reshape(-1), self.end_effector(physics)])

    def distance(self, physics, goal):
        return rewards.DISTANCES[self.spec.distance](self.object_points(physics), goal)

    def expert(self, state: EnvState, params: EnvParams):
        raise NotImplementedError(f"task {self.spec.name!r} has no scripted expert")

    def check_physics_params(self, physics) -> None:
        """Raise ``ValueError`` if ``params.physics`` cannot run (eager; the default only
        checks that every leaf is finite)."""
        for path, leaf in jax.tree_util.tree_flatten_with_path(physics)[0]:
            if not np.all(np.isfinite(np.asarray(leaf))):
                raise ValueError(f"params.physics{jax.tree_util.keystr(path)} contains NaN "
                                 f"or inf")

    # ------------------------------------------------------------------ derived, static
    @property
    def name(self) -> str:
        return self.spec.name

    @property
    def horizon(self) -> int:
        return self.spec.horizon

    @property
    def dt(self) -> float:
        """Simulated seconds per environment step: ``spec.substeps * substep_dt``."""
        return self.spec.substeps * self.substep_dt

    @property
    def has_expert(self) -> bool:
        return type(self).expert is not Env.expert

    @property
    def action_space(self) -> Box:
        low = np.asarray(self.spec.action_low, np.float32)
        high = np.asarray(self.spec.action_high, np.float32)
        return Box(low, high, low.shape)

    @property
    def observation_space(self) -> Box:
        if "obs" not in self._cache:
            obs = jax.eval_shape(self.reset, jax.random.PRNGKey(0), self._shape_params())[0]
            self._cache["obs"] = Box.unbounded(obs.shape, np.dtype(obs.dtype))
        return self._cache["obs"]

    @property
    def n_object_points(self) -> int:
        """Number of object points (particles, cloth vertices) of the task."""
        if "n_points" not in self._cache:
            def points(key):
                return self.object_points(self.init(key, self._shape_params()))

            self._cache["n_points"] = jax.eval_shape(points, jax.random.PRNGKey(0)).shape[0]
        return self._cache["n_points"]

    @property
    def goal_correspondence(self) -> bool:
        """Whether the goal's points correspond to the object's by index (then the goal
        must have ``n_object_points`` rows)."""
        return self.spec.distance == "l2" and type(self).distance is Env.distance

    @property
    def n_goal_points(self) -> int | None:
        """The number of points a goal of this task must have, or ``None`` when any
        number works: ``n_object_points`` for an index-correspondence goal (a task whose
        goal is its object's particle set in some other sense overrides this)."""
        return self.n_object_points if self.goal_correspondence else None

    # ------------------------------------------------------------------ params
    def with_goal(self, points, provenance: dict | None = None) -> Env:
        """A copy of this env whose default goal is ``points`` (N, 3) [m]."""
        pts = np.asarray(points, np.float32)
        if pts.ndim != 2 or pts.shape[1] != 3 or not np.all(np.isfinite(pts)):
            raise ValueError(f"{self.name}: a goal must be a finite (N, 3) array of points "
                             f"in m, got shape {pts.shape}")
        if self.n_goal_points is not None and pts.shape[0] != self.n_goal_points:
            raise ValueError(f"{self.name}: the goal has {pts.shape[0]} points but the "
                             f"task's goal has {self.n_goal_points} (made for another scene "
                             f"resolution?)")
        new = copy.copy(self)
        new._goal, new.goal_provenance = pts, provenance
        new._cache = {k: v for k, v in self._cache.items() if k != "params"}
        return new

    def with_default_params(self, params: EnvParams) -> Env:
        """A copy of this env whose ``default_params`` are ``params`` (its goal too)."""
        new = self.with_goal(np.asarray(params.goal), self.goal_provenance)
        new._cache["params"] = params
        return new

    @property
    def goal(self) -> np.ndarray:
        """The default goal (N, 3) [m] (NumPy)."""
        if self._goal is None:
            raise ValueError(f"{self.name}: this env has no goal yet; build it with "
                             f"dax_tasks.make, or call env.with_goal(points)")
        return self._goal

    def _params(self, goal) -> EnvParams:
        # concrete arrays even when first asked for inside a trace (they are cached)
        with jax.ensure_compile_time_eval():
            return EnvParams(goal=jnp.asarray(goal, jnp.float32),
                             lam=jnp.asarray(self.LAM, jnp.float32),
                             aux_weight=jnp.zeros((), jnp.float32),
                             physics=self.default_physics_params())

    def _shape_params(self) -> EnvParams:
        """Params for shape evaluation before the goal is known (the goal is not read)."""
        return self._params(self._goal if self._goal is not None else np.zeros((1, 3)))

    @property
    def default_params(self) -> EnvParams:
        """The task's default :class:`EnvParams` (its goal, λ, no auxiliary reward and the
        default physics numbers); built once."""
        if "params" not in self._cache:
            self._cache["params"] = self._params(self.goal)
        return self._cache["params"]

    # ------------------------------------------------------------------ the pure API
    def reset(self, key, params: EnvParams | None = None):
        """``(obs, state)`` of a new episode drawn from ``key`` (a ``PRNGKey``).

        The physics state is float32, or float64 when ``jax_enable_x64`` is on
        (:func:`float_dtype`); the tasks draw their random numbers in float32 either way,
        so a seed gives the same initial state in both precisions, up to float32 rounding.
        """
        params = self._checked_shapes(params)
        physics = cast_floats(self.init(key, params), float_dtype())
        state = EnvState(physics=physics, t=jnp.zeros((), jnp.int32),
                         finite=jnp.asarray(True))
        return self.observe(physics), state

    def step(self, state: EnvState, action, params: EnvParams | None = None):
        """``(obs, state, reward, done, info)`` after one environment step.

        The action is clipped to the spec's bounds (zero gradient across a clipped
        dimension) in its own precision, then cast to the physics state's float type, so a
        finite float64 action beyond float32's range is clipped, not turned into inf. A
        wrong action shape, an action that is not real numbers (complex, text, bool) and
        params whose goal or ``lam`` has the wrong shape raise ``ValueError`` (at trace
        time, so under ``jit`` too). Values are not inspected here: a NaN/inf action or
        parameter turns ``info["finite"]`` and ``state.finite`` false, and a finite
        out-of-range parameter (a negative friction) runs as given under ``jit``; an
        eager call (concrete params other than :attr:`default_params`) refuses params
        :func:`dax_tasks.core.checks.check_params` refuses, in ``reset`` too. Use
        :func:`dax_tasks.core.checks.check_action` at the boundary to refuse a NaN/inf
        action.
        ``info``: ``r_gt``, ``r_aux``, ``distance`` [m], ``finite``, ``escaped`` (MPM
        particles left the grid), ``t``.
        """
        params = self._checked_shapes(params)
        spec = self.spec
        # the physics' float type (float32; float64 for a state cast to it, so a float64
        # gradient check sees the action it asks for, not its float32 rounding)
        dtype = _float_dtype(state.physics)
        action = _real_array(action, f"{spec.name}: action")
        if action.shape != (spec.action_dim,):
            raise ValueError(f"{spec.name}: expected a {spec.action_kind} action of shape "
                             f"({spec.action_dim},), got {action.shape}")
        # clip before any narrowing cast (a finite 1e39 in float64 is inf in float32)
        wide = jnp.promote_types(action.dtype, dtype) if jnp.issubdtype(
            action.dtype, jnp.floating) else dtype
        action = action.astype(wide)
        finite_action = jnp.all(jnp.isfinite(action))
        action = jnp.clip(action, jnp.asarray(spec.action_low, wide),
                          jnp.asarray(spec.action_high, wide)).astype(dtype)
        physics = self.apply_action(state.physics, action, params)
        pts = self.object_points(physics)
        dist = self.distance(physics, params.goal)
        r_gt = rewards.ground_truth_reward(dist, params.lam)
        r_aux = rewards.auxiliary_reward(self.end_effector(physics), pts)
        reward = r_gt + params.aux_weight * r_aux
        physics_finite = getattr(physics, "finite", jnp.all(jnp.isfinite(pts)))
        finite = state.finite & finite_action & physics_finite & jnp.isfinite(reward)
        t = state.t + 1
        done = t >= spec.horizon
        escaped = getattr(physics, "escaped", jnp.asarray(False))
        info = {"r_gt": r_gt, "r_aux": r_aux, "distance": dist, "finite": finite,
                "escaped": escaped, "t": t}
        new_state = state.replace(physics=physics, t=t, finite=finite)
        return self.observe(physics), new_state, reward, done, info

    def _checked_shapes(self, params: EnvParams | None) -> EnvParams:
        """``params`` (default: :attr:`default_params`), its static shapes checked: the
        goal's against the default goal's, ``lam`` and ``aux_weight`` scalars
        (``ValueError`` at trace time). Params other than :attr:`default_params` given
        as concrete values outside ``jit`` / ``scan`` (no leaf is a JAX tracer and
        nothing is being traced) also get the boundary's value checks,
        :func:`dax_tasks.core.checks.check_params` (a negative friction is refused);
        traced params (under ``jit``, or batched by ``vmap``) are not inspected."""
        if params is None or params is self._cache.get("params"):
            return self.default_params
        if self._goal is not None and jnp.shape(params.goal) != self._goal.shape:
            raise ValueError(f"{self.name}: params.goal must have shape {self._goal.shape}, "
                             f"got {jnp.shape(params.goal)}")
        for name in ("lam", "aux_weight"):
            if jnp.shape(getattr(params, name)) != ():
                raise ValueError(f"{self.name}: params.{name} must be a scalar, got shape "
                                 f"{jnp.shape(getattr(params, name))}")
        if _eager() and not any(isinstance(leaf, jax.core.Tracer)
                                for leaf in jax.tree_util.tree_leaves(params)):
            from .checks import check_params as check_values

            check_values(self, params)
        return params

    def expert_action(self, state: EnvState, params: EnvParams | None = None):
        """The scripted expert's action for ``state``, inside the action bounds (pure;
        ``NotImplementedError`` if the task has none)."""
        params = self.default_params if params is None else params
        action = self.expert(state, params)  # NotImplementedError first, for any state
        dtype = _float_dtype(state.physics)  # float64 for a float64 state
        action = jnp.asarray(action, dtype)
        return jnp.clip(action, jnp.asarray(self.spec.action_low, dtype),
                        jnp.asarray(self.spec.action_high, dtype))

    @property
    def unwrapped(self) -> Env:
        return self


class MPMEnv(Env):
    """An env whose physics is one MLS-MPM scene (:mod:`dax_physics.mpm`): ``self.cfg``
    is built once from the scene by the subclass's ``mpm_config(scene)``, and
    ``params.physics`` is its :class:`dax_physics.MaterialParams` (the material table and
    the colliders' friction), checked eagerly by :func:`dax_physics.check_params`. The
    object points are the particles."""

    def __init__(self, spec: TaskSpec):
        super().__init__(spec)
        self.cfg = self.mpm_config(spec.scene)  # raises if dt is unstable for the defaults
        with jax.ensure_compile_time_eval():
            self._physics_params = self.cfg.params

    @staticmethod
    def mpm_config(scene) -> MPMConfig:
        """The scene's :class:`dax_physics.MPMConfig` (a task sets ``mpm_config =
        staticmethod(its_function)``)."""
        raise NotImplementedError

    @property
    def substep_dt(self) -> float:
        return self.cfg.dt

    def default_physics_params(self):
        return self._physics_params

    def check_physics_params(self, physics) -> None:
        check_params(self.cfg, physics)

    def object_points(self, physics):
        return physics.x
