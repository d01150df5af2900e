"""Wrappers around the pure env (:class:`dax_tasks.Env`), each small and each a pure
``reset(key, params)`` / ``step(state, action, params)`` pair again, so they compose:

* :class:`VmapWrapper`: a batch of envs whose size the caller chooses (``vmap`` over
  keys, and optionally over params: domain randomisation);
* :class:`AutoReset`: an env whose episode ended restarts inside the same step (a fresh
  start drawn from a key kept in the state), so a ``lax.scan`` can run many episodes;
* :class:`EpisodeStatistics`: the return, length and final ``r_gt`` of the last finished
  episode, in ``info``;
* :class:`ObservationMode`: the observation as ``state`` (the task's own), ``particles``,
  ``height``, ``rgb`` or ``rgbd`` (images from the pure-JAX renderer);
* :class:`ObjectFrame`: a macro task's observation and actions in the object's own frame
  (a start's place and heading on the table factored out).

The usual training stack is :func:`training_env`: ``VmapWrapper(EpisodeStatistics(
AutoReset(env)))``. Order matters where it says so: :class:`EpisodeStatistics` must sit
outside :class:`AutoReset` (it has to see the end of an episode before the reset), and
:class:`VmapWrapper` outermost. Wrappers keep their data in ``state.extras``, so
``state.physics`` is the simulator state at every level; anything a wrapper does not
define (``spec``, ``dt``, ``default_params``, ``object_points``, ``expert_action``, ...) is
the wrapped env's.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ..viz import images
from .sharding import shard_batch
from .spec import Box

#: Observation modes of :class:`ObservationMode`.
OBS_MODES = ("state", "particles", "height", "rgb", "rgbd")
#: The modes that are images (rendered by a :class:`dax_tasks.viz.Camera`).
IMAGE_MODES = ("height", "rgb", "rgbd")


class Wrapper:
    """Base class: forwards ``reset``, ``step`` and every other attribute to ``env``."""

    def __init__(self, env):
        self.env = env

    def __getattr__(self, name):
        if name == "env" or name.startswith("__"):
            raise AttributeError(name)
        return getattr(self.env, name)

    def __repr__(self):
        return f"{type(self).__name__}({self.env!r})"

    @property
    def unwrapped(self):
        return self.env.unwrapped

    def reset(self, key, params=None):
        return self.env.reset(key, params)

    def step(self, state, action, params=None):
        return self.env.step(state, action, params)


def _where(cond, a, b):
    """Leafwise ``where(cond, a, b)`` over two pytrees of the same structure."""
    return jax.tree_util.tree_map(
        lambda x, y: jnp.where(jnp.reshape(cond, cond.shape + (1,) * (x.ndim - cond.ndim)),
                               x, y), a, b)


def _is_single_key(key) -> bool:
    if jnp.issubdtype(key.dtype, jax.dtypes.prng_key):
        return key.ndim == 0
    return key.ndim == 1


class VmapWrapper(Wrapper):
    """``batch_size`` envs stepped together (``jax.vmap``).

    ``reset(key, params)`` takes one key (split into ``batch_size`` keys) or a batch of
    keys (``(B, 2)``); ``step(states, actions, params)`` takes batched states and actions
    (``(B, action_dim)``). With ``batch_params=True`` the params are batched too (a leading
    axis on every leaf; domain randomisation), and ``default_params`` is the default
    broadcast to ``batch_size``; otherwise one params is shared by the batch.
    ``expert_action(states, params)`` is batched the same way.

    With more than one device the batch is split over them (:mod:`dax_tasks.core.sharding`:
    keys, states, actions and every output along the batch axis, when the batch size is a
    multiple of the device count); nothing changes for the caller.
    """

    def __init__(self, env, batch_size: int | None = None, batch_params: bool = False):
        super().__init__(env)
        if batch_size is not None and not (isinstance(batch_size, int) and batch_size > 0):
            raise ValueError(f"batch_size must be None or a positive int, got {batch_size!r}")
        if batch_params and batch_size is None:
            raise ValueError("batch_params=True needs a batch_size")
        self.batch_size = batch_size
        self.batch_params = batch_params
        self._p_axis = 0 if batch_params else None

    @property
    def default_params(self):
        params = self.env.default_params
        if not self.batch_params:
            return params
        return jax.tree_util.tree_map(
            lambda a: jnp.broadcast_to(a, (self.batch_size, *jnp.shape(a))), params)

    def _params(self, params):
        return self.default_params if params is None else params

    def reset(self, key, params=None):
        key = jnp.asarray(key) if not isinstance(key, jax.Array) else key
        if _is_single_key(key):
            if self.batch_size is None:
                raise ValueError("VmapWrapper.reset got one key but no batch_size; pass a "
                                 "batch of keys or set batch_size")
            key = jax.random.split(key, self.batch_size)
        key = shard_batch(key)
        return shard_batch(jax.vmap(self.env.reset, in_axes=(0, self._p_axis))(
            key, self._params(params)))

    def step(self, state, action, params=None):
        want = (jnp.shape(state.t)[0], self.spec.action_dim)
        if jnp.shape(action) != want:
            raise ValueError(f"{self.spec.name}: expected a batch of {self.spec.action_kind} "
                             f"actions of shape {want}, got {jnp.shape(action)}")
        state, action = shard_batch((state, action))
        return shard_batch(jax.vmap(self.env.step, in_axes=(0, 0, self._p_axis))(
            state, action, self._params(params)))

    def expert_action(self, state, params=None):
        return shard_batch(jax.vmap(self.env.expert_action, in_axes=(0, self._p_axis))(
            shard_batch(state), self._params(params)))


class AutoReset(Wrapper):
    """An env that restarts when its episode ends, inside the same (jittable) step.

    ``reset(key)`` is the wrapped env's reset, and keeps a key in ``state.extras`` from
    which every later start is drawn. ``step`` returns, for a step that ends an episode,
    ``done = True``, that step's reward and ``info``, and the observation and state of a
    new episode. Data that wrappers *inside* this one keep in ``extras`` restarts with the
    episode; that of wrappers outside is kept.
    """

    KEY = "autoreset_key"

    def reset(self, key, params=None):
        obs, state = self.env.reset(key, params)
        extras = {**state.extras, self.KEY: jax.random.fold_in(key, 1)}
        return obs, state.replace(extras=extras)

    def step(self, state, action, params=None):
        obs, st, reward, done, info = self.env.step(state, action, params)
        key, k_reset = jax.random.split(state.extras[self.KEY])
        obs0, st0 = self.env.reset(k_reset, params)
        extras = dict(st.extras)
        for name, value in st0.extras.items():
            extras[name] = _where(done, value, st.extras[name])
        extras[self.KEY] = key
        new = st.replace(physics=_where(done, st0.physics, st.physics),
                         t=jnp.where(done, st0.t, st.t),
                         finite=jnp.where(done, st0.finite, st.finite), extras=extras)
        return jnp.where(done, obs0, obs), new, reward, done, info


class EpisodeStatistics(Wrapper):
    """Episode return, length and final ``r_gt``. ``info`` gains ``episode_return``,
    ``episode_length`` and ``episode_final_r_gt`` (of the most recently finished episode;
    0 before the first ends) and ``episode_done`` (this step ended one). Wrap it around
    :class:`AutoReset`, not inside it."""

    KEY = "episode"

    def reset(self, key, params=None):
        obs, state = self.env.reset(key, params)
        zero = jnp.zeros((), jnp.float32)
        none = jnp.zeros((), jnp.int32)
        stats = {"return": zero, "length": none, "last_return": zero, "last_length": none,
                 "last_r_gt": zero}
        return obs, state.replace(extras={**state.extras, self.KEY: stats})

    def step(self, state, action, params=None):
        obs, st, reward, done, info = self.env.step(state, action, params)
        e = state.extras[self.KEY]
        ret = e["return"] + reward
        length = e["length"] + 1
        stats = {"return": jnp.where(done, 0.0, ret), "length": jnp.where(done, 0, length),
                 "last_return": jnp.where(done, ret, e["last_return"]),
                 "last_length": jnp.where(done, length, e["last_length"]),
                 "last_r_gt": jnp.where(done, info["r_gt"], e["last_r_gt"])}
        info = {**info, "episode_return": stats["last_return"],
                "episode_length": stats["last_length"],
                "episode_final_r_gt": stats["last_r_gt"], "episode_done": done}
        return obs, st.replace(extras={**st.extras, self.KEY: stats}), reward, done, info


class ObservationMode(Wrapper):
    """The observation in one of :data:`OBS_MODES`:

    * ``state``: the task's own observation (``env.observe``);
    * ``particles``: every object point and then the end effector, ``(N + 1, 3)`` [m];
    * ``height``: a top-down height map ``(S, S, 1)`` float32 [m] above the view's base;
    * ``rgb``: a top-down picture ``(S, S, 3)`` uint8 (the object in its texture,
      ``env.object_colors``, brightened with height, or shaded by height if it has none;
      end effector in red);
    * ``rgbd``: both, ``(S, S, 4)`` float32: RGB in [0, 1], then the height map [m].

    ``S = image_size``. Images are pure JAX (:mod:`dax_tasks.viz`), so they render
    inside ``jit``/``vmap``; their view window is fixed when the wrapper is built (around
    the goal and the start of episode ``PRNGKey(0)``). With ``goal_image=True`` an image
    mode also shows the goal: the picture of ``params.goal`` in the same mode (no end
    effector) is appended along the channels, ``(S, S, 2 C)`` (a goal-conditioned
    observation, as goal-conditioned Transporter networks take it; ``rgb`` then stays
    uint8). With ``align_goal=True`` as well, the goal is pictured where the task's
    distance compares it: moved onto the object's current pose by the task's
    ``aligned_goal(points, goal)`` (the cloth tasks and Push-Rope, whose goals are shapes,
    not places); only for a task that has it.
    """

    def __init__(self, env, mode: str = "state", image_size: int = 64,
                 goal_image: bool = False, align_goal: bool = False):
        super().__init__(env)
        if mode not in OBS_MODES:
            raise ValueError(f"unknown observation mode {mode!r}; valid: "
                             f"{', '.join(OBS_MODES)}")
        if not (isinstance(image_size, int) and image_size >= 8):
            raise ValueError(f"image_size must be an int >= 8, got {image_size!r}")
        if goal_image and mode not in IMAGE_MODES:
            raise ValueError(f"goal_image needs an image mode ({', '.join(IMAGE_MODES)}), "
                             f"got {mode!r}")
        if align_goal and not goal_image:
            raise ValueError("align_goal pictures the goal: it needs goal_image=True")
        if align_goal and not callable(getattr(env, "aligned_goal", None)):
            raise ValueError(f"align_goal needs a task whose distance aligns its goal to "
                             f"the object (aligned_goal); {env.spec.name} has none")
        self.mode, self.image_size, self.goal_image = mode, image_size, goal_image
        self.align_goal = align_goal
        self.camera = images.Camera.for_env(env) if mode in IMAGE_MODES else None

    def image(self, points, end_effector=None):
        """The picture of ``points`` (N, 3) [m] in this image mode (no end effector marker
        if ``end_effector`` is ``None``)."""
        size, colors = self.image_size, self.env.object_colors
        if colors is not None and len(colors) != points.shape[0]:
            colors = None  # e.g. a goal set of another size than the object (Chamfer)
        if self.mode == "rgb":
            return self.camera.rgb(points, end_effector, size, colors)
        height = self.camera.height(points, size)[..., None]
        if self.mode == "height":
            return height
        rgb = rgb_as_float(self.camera.rgb(points, end_effector, size, colors))
        return jnp.concatenate([rgb, height], axis=-1)

    def goal_observation(self, params=None, points=None):
        """The goal's picture ``(S, S, C)``: :meth:`image` of ``params.goal``, or, with
        ``align_goal``, of the goal aligned to the object points ``points`` (N, 3) [m]
        (``ValueError`` if they are not given)."""
        params = self.env.default_params if params is None else params
        if not self.align_goal:
            return self.image(params.goal)
        if points is None:
            raise ValueError("align_goal: the goal's picture needs the object's points")
        goal = jnp.asarray(params.goal, jnp.asarray(points).dtype)
        return self.image(self.env.aligned_goal(points, goal))

    def observation(self, physics, params=None):
        if self.mode == "state":
            return self.env.observe(physics)
        pts, ee = self.env.object_points(physics), self.env.end_effector(physics)
        if self.mode == "particles":
            return jnp.concatenate([pts, ee[None]], axis=0)
        img = self.image(pts, ee)
        if self.goal_image:
            img = jnp.concatenate([img, self.goal_observation(params, pts)], axis=-1)
        return img

    def reset(self, key, params=None):
        _, state = self.env.reset(key, params)
        return self.observation(state.physics, params), state

    def step(self, state, action, params=None):
        _, st, reward, done, info = self.env.step(state, action, params)
        return self.observation(st.physics, params), st, reward, done, info

    @property
    def observation_space(self) -> Box:
        if self.mode == "state":
            return self.env.observation_space
        obs = jax.eval_shape(self.reset, jax.random.PRNGKey(0))[0]
        if self.mode == "rgb":
            return Box(np.zeros(obs.shape, np.uint8), np.full(obs.shape, 255, np.uint8),
                       obs.shape, np.uint8)
        if self.mode == "particles":
            return Box.unbounded(obs.shape)
        high = np.full(obs.shape, np.inf, np.float32)
        if self.mode == "rgbd":
            high[..., 0:3] = 1.0
            if self.goal_image:
                high[..., 4:7] = 1.0
        return Box(np.zeros(obs.shape, np.float32), high, obs.shape)


class ObjectFrame(Wrapper):
    """The env seen from the object's own frame: for a macro-action task whose distance
    aligns its goal to the object (``goal_pose(points, goal) -> (rot, shift)``: the cloth
    tasks, Push-Rope), the observation's points and end effector are expressed in the
    frame in which the goal would lie on the object (table-plane coordinates ``rot^T (p -
    shift)``, heights unchanged), and an action's pick and place (or push start and end)
    are given in that frame and moved back onto the table (``rot p + shift``) before the
    task steps. The frame is the pose of the object at the step (the observation's: the
    state the action is applied to), so a start at any place and heading that differs
    only by a rigid motion in the table plane looks the same and is acted on the same.

    Same observation shape as the task's (its ``observe``: the object points at
    ``obs_stride`` and the end effector, flattened); ``info["world_action"]`` is the
    action the task stepped, in table coordinates [m]. Rewards, ``r_gt`` and the physics
    are the task's, unchanged.
    """

    def __init__(self, env):
        super().__init__(env)
        if env.spec.action_kind not in ("push", "pick_place"):
            raise ValueError(f"ObjectFrame needs a macro-action task (push, pick_place); "
                             f"{env.spec.name} has {env.spec.action_kind} actions")
        if not callable(getattr(env, "goal_pose", None)):
            raise ValueError(f"ObjectFrame needs a task whose distance aligns its goal to "
                             f"the object (goal_pose); {env.spec.name} has none")
        want = jax.eval_shape(lambda k: env.reset(k)[0], jax.random.PRNGKey(0)).shape
        got = jax.eval_shape(lambda k: self._frame_obs(env.reset(k)[1].physics, None),
                             jax.random.PRNGKey(0)).shape
        if want != got:
            raise ValueError(f"ObjectFrame: {env.spec.name}'s observation {want} is not its "
                             f"object points and end effector {got}")

    def _pose(self, physics, params):
        params = self.env.default_params if params is None else params
        x = self.env.object_points(physics)
        return self.env.goal_pose(x, jnp.asarray(params.goal, x.dtype))

    def _frame_obs(self, physics, params):
        rot, shift = self._pose(physics, params)
        pts = self.env.object_points(physics)[:: self.env.spec.obs_stride]
        p = jnp.concatenate([pts, self.env.end_effector(physics)[None]], 0)
        xy = (p[:, :2] - shift) @ rot  # rot^T (p - shift), row by row
        return jnp.concatenate([xy, p[:, 2:]], 1).reshape(-1)

    def to_world(self, physics, action, params=None):
        """``action`` (6,) given in the object frame of ``physics``, in table coordinates."""
        rot, shift = self._pose(physics, params)
        a = jnp.reshape(action, (2, 3))
        xy = a[:, :2] @ rot.T + shift
        return jnp.concatenate([xy, a[:, 2:]], 1).reshape(action.shape)

    def reset(self, key, params=None):
        _, state = self.env.reset(key, params)
        return self._frame_obs(state.physics, params), state

    def step(self, state, action, params=None):
        world = self.to_world(state.physics, action, params)
        _, st, reward, done, info = self.env.step(state, world, params)
        info = {**info, "world_action": world}
        return self._frame_obs(st.physics, params), st, reward, done, info

    @property
    def observation_space(self) -> Box:
        return Box.unbounded(self.env.observation_space.shape)


def rgb_as_float(rgb):
    """A uint8 picture as the ``rgbd`` mode shows it: float32 in [0, 1] (JAX, so recorded
    pictures convert to the same bits as the observation: NumPy's float32 division rounds
    some values differently)."""
    return jnp.asarray(rgb).astype(jnp.float32) / 255.0


def training_env(env, batch_size: int, auto_reset: bool = True, episode_stats: bool = True,
                 batch_params: bool = False):
    """The stack an RL method steps: ``VmapWrapper(EpisodeStatistics(AutoReset(env)))``
    (each layer optional but the batch)."""
    if auto_reset:
        env = AutoReset(env)
    if episode_stats:
        env = EpisodeStatistics(env)
    return VmapWrapper(env, batch_size=batch_size, batch_params=batch_params)
