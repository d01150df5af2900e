"""ILD, imitation learning as state matching through differentiable physics (Chen et al.
2023, "Imitation Learning as State Matching via Differentiable Physics"), from one expert
demonstration.

The policy (an MLP on the task's ``state`` observation and ``t / horizon``, as the RL
methods', :mod:`dax_algos.mlp_policy`) is rolled through the differentiable step from ``num_envs``
starts and its parameters descend the distance between the states it visits and the
demonstration's states at the same steps, summed over the episode: the action of step
``t`` gets gradient from the state after it and from every later one (through the
simulator). A state is the object's points (particles, cloth vertices; they correspond by
index across starts) and the end effector, and the distance at step ``t`` is

* ``weighting="per_part"`` (default): ``object_weight * mean_i |x_i - x*_i|^2 +
  effector_weight * |e - e*|^2``: each part averaged over its own points, then weighted;
* ``weighting="flat"``: ``(sum_i |x_i - x*_i|^2 + |e - e*|^2) / (N + 1)``: the whole state
  as one vector, every point alike, as a plain L2 state distance does. With N object
  points the end effector's term carries ``1 / (N + 1)`` of the weight: on a pour task
  (476 particles) the gripper's signal is drowned, the open problem the ILD paper names.

Starts: ``starts="random"`` (default) draws each training episode's start from the task's
own distribution (so the policy learns to follow the demonstration from where an
evaluation episode starts); ``starts="demo"`` restarts every episode from the
demonstration's own start (``reset(PRNGKey(seed))``, the file's seed), the setting in which
reproducing the demonstration exactly is possible. Alignment: ``align="none"`` (default)
tracks the demonstration's absolute states; ``align="start"`` first moves the whole
demonstration (object points and end effector, every step) by the rigid motion in the table
plane (a rotation about the vertical and a shift) that best maps its start's object points
onto the episode's start's (least squares, :func:`planar_fit`), as the cloth tasks' distance
aligns the goal to the cloth: from a start elsewhere on the table, or turned, the target is
the demonstrated motion where the object is, not where the demonstration's object was.
``align="goal"`` moves it instead by the task's own goal alignment (its ``goal_pose``,
:func:`goal_motion`): the motion that takes the demonstration's start, in the frame in which
the goal lies on it, to the episode's start in that frame. On the cloth tasks that is a
rigid fit as ``start``'s; on Push-Rope, whose distance slides the goal along its line only,
it is a shift along the line, so the demonstration's pushes across the line stay where
the goal is.
``window`` truncates backpropagation as
in APG (``None``: the whole episode); each update is one episode per env, in
``ceil(H / window)`` gradient steps, the state carried between them ``stop_gradient``-ed.
Non-finite gradients are counted and their step skipped, as in the RL methods.
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

import dax_tasks

from .. import nets
from ..actions import to_action
from ..checks import check_choice, check_fields
from ..learner import Learner, Policy, UpdateMetrics
from ..mlp_policy import ObsNorm, batch_features, deterministic_act, feature_dim
from ..optim import guarded_update, make_optimiser
from . import demos

WEIGHTINGS = ("per_part", "flat")
ALIGNS = ("none", "start", "goal")


@dataclasses.dataclass(frozen=True)
class ILDConfig:
    """total_env_steps: training budget (``num_envs * horizon`` per update); window:
    backpropagation horizon in env steps (``None``: the episode); weighting,
    object_weight, effector_weight: the state distance (see the module docstring);
    starts: ``random`` or ``demo``; align: ``none``, ``start`` or ``goal`` (the module
    docstring)."""

    total_env_steps: int = 2_000
    num_envs: int = 4
    window: int | None = None
    learning_rate: float = 1e-3
    max_grad_norm: float | None = 0.3
    zero_nans: bool = False
    policy_hidden: tuple = (256, 256)
    activation: str = "swish"
    weighting: str = "per_part"
    object_weight: float = 1.0
    effector_weight: float = 1.0
    starts: str = "random"
    align: str = "none"
    normalize_obs: bool = True
    remat: bool = False
    n_eval: int = 20

    def __post_init__(self):
        check_fields(self, ints=("total_env_steps", "num_envs", "n_eval"),
                     positive=("learning_rate",),
                     non_negative=("object_weight", "effector_weight"),
                     optional_ints=("window",), optional_positive=("max_grad_norm",))
        check_choice("weighting", self.weighting, WEIGHTINGS)
        if self.starts not in ("random", "demo"):
            raise ValueError(f"starts must be 'random' or 'demo', got {self.starts!r}")
        check_choice("align", self.align, ALIGNS)

    def window_for(self, env) -> int:
        return env.horizon if self.window is None else min(self.window, env.horizon)

    def updates_for(self, env) -> int:
        return max(1, self.total_env_steps // (self.num_envs * env.horizon))


def train_env_steps(env, config: ILDConfig) -> int:
    """Environment steps simulated in training (the windows of the last one may run past
    the horizon; those steps count too)."""
    w = config.window_for(env)
    return config.num_envs * w * math.ceil(env.horizon / w) * config.updates_for(env)


class Demonstration(NamedTuple):
    """One demonstration's states: ``points`` (H + 1, N, 3) and ``effector`` (H + 1, 3)
    [m] at steps 0..H, and its start ``key`` (the reset key of its seed)."""

    points: jnp.ndarray
    effector: jnp.ndarray
    key: jnp.ndarray


def demonstration_from_episode(env, episode) -> Demonstration:
    """The :class:`Demonstration` of a dax-data episode recorded with point stride 1."""
    steps = np.asarray(episode.point_steps)
    if episode.length != env.horizon or not np.array_equal(steps, np.arange(env.horizon + 1)):
        raise ValueError(f"ILD needs a whole episode ({env.horizon} steps) with the object's "
                         f"points at every step (point stride 1); got {episode.length} steps "
                         f"with points at {steps.tolist()[:6]}...")
    return Demonstration(jnp.asarray(episode.points, jnp.float32),
                         jnp.asarray(episode.end_effector, jnp.float32),
                         jax.random.PRNGKey(int(episode.seed)))


def load_data(env, path) -> Demonstration:
    """The first episode of the demonstration file ``path``, checked against ``env``."""
    return demonstration_from_episode(env, demos.load_episodes(path, env, 1)[0])


def demo_spec(config: ILDConfig) -> demos.DemoSpec:
    """dax-data's standard ``ild`` set, read by :func:`load_data`."""
    return demos.DemoSpec("ild", load_data)


def planar_fit(source, target):
    """``(rot (2, 2), shift (2,))``: the rigid motion in the x-y plane, ``p -> rot @ p +
    shift``, that maps the points ``source`` (N, 3) onto ``target`` (N, 3) (corresponding
    by index) with the least squared error (the closed-form 2-D Kabsch fit); z is left
    as it is."""
    s, t = source[:, :2], target[:, :2]
    cs, ct = jnp.mean(s, 0), jnp.mean(t, 0)
    a, b = s - cs, t - ct
    angle = jnp.arctan2(jnp.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]),
                        jnp.sum(a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1]))
    c, n = jnp.cos(angle), jnp.sin(angle)
    rot = jnp.stack([jnp.stack([c, -n]), jnp.stack([n, c])])
    return rot, ct - rot @ cs


def move_demonstration(demo: Demonstration, rot, shift) -> Demonstration:
    """``demo`` with every step's object points and end effector moved by the planar
    rigid motion ``(rot, shift)`` (:func:`planar_fit`)."""
    def move(p):
        return jnp.concatenate([p[..., :2] @ rot.T + shift, p[..., 2:]], -1)

    return demo._replace(points=move(demo.points), effector=move(demo.effector))


def goal_motion(env, demo_start, start, goal):
    """``(rot (2, 2), shift (2,))``: the motion in the table plane ``p -> rot @ p + shift``
    that takes the object points ``demo_start`` (N, 3) to ``start`` (N, 3) as the task
    sees them: with the task's goal poses ``(R_d, s_d) = env.goal_pose(demo_start, goal)``
    and ``(R_e, s_e) = env.goal_pose(start, goal)`` (the motion that lays ``goal`` on each),
    ``rot = R_e R_d^T`` and ``shift = s_e - rot s_d``, so a point at a given place in the
    demonstration's goal frame lands at the same place in the episode's."""
    rot_d, shift_d = env.goal_pose(demo_start, goal)
    rot_e, shift_e = env.goal_pose(start, goal)
    rot = rot_e @ rot_d.T
    return rot, shift_e - rot @ shift_d


def check_align(env, config: ILDConfig) -> None:
    """Raise ``ValueError`` if ``config.align`` needs what ``env`` lacks (``goal``: a
    task whose distance aligns its goal to the object, ``goal_pose``)."""
    if config.align == "goal" and not callable(getattr(env, "goal_pose", None)):
        raise ValueError(f"ILD align='goal' needs a task whose distance aligns its goal to "
                         f"the object (goal_pose); {env.spec.name} has none (use 'none' or "
                         f"'start')")


def episode_targets(env, demo: Demonstration, physics, params,
                    config: ILDConfig) -> Demonstration:
    """The demonstration each of a batch of episodes tracks, ``points`` (B, H + 1, N, 3)
    and ``effector`` (B, H + 1, 3), from the episodes' start ``physics`` (batched):
    ``demo`` itself (``align="none"``), moved onto each start by a rigid fit
    (``align="start"``, :func:`planar_fit`) or by the task's goal alignment
    (``align="goal"``, :func:`goal_motion` with ``params.goal``)."""
    batch = jax.tree_util.tree_leaves(physics)[0].shape[0]
    if config.align == "none":
        return demo._replace(
            points=jnp.broadcast_to(demo.points, (batch, *demo.points.shape)),
            effector=jnp.broadcast_to(demo.effector, (batch, *demo.effector.shape)))
    starts = jax.lax.stop_gradient(jax.vmap(env.object_points)(physics))
    if config.align == "goal":
        check_align(env, config)
        goal = jnp.asarray(params.goal, demo.points.dtype)
        rot, shift = jax.vmap(lambda s: goal_motion(env, demo.points[0], s, goal))(starts)
    else:
        rot, shift = jax.vmap(planar_fit, in_axes=(None, 0))(demo.points[0], starts)
    moved = jax.vmap(move_demonstration, in_axes=(None, 0, 0))(demo, rot, shift)
    return moved._replace(key=demo.key)


def state_distance(points, effector, target_points, target_effector, config: ILDConfig):
    """The state distance of one step [m^2] (see the module docstring)."""
    d_obj = jnp.sum((points - target_points) ** 2, axis=-1)
    d_ee = jnp.sum((effector - target_effector) ** 2, axis=-1)
    if config.weighting == "flat":
        return (jnp.sum(d_obj, axis=-1) + d_ee) / (points.shape[-2] + 1)
    return config.object_weight * jnp.mean(d_obj, axis=-1) + config.effector_weight * d_ee


def network(env, config: ILDConfig) -> nets.Network:
    """The deterministic policy's network (a Gaussian policy whose mean is used)."""
    return nets.policy_network(feature_dim(env), env.spec.action_dim,
                               config.policy_hidden, config.activation)


def make_act(env, config: ILDConfig):
    """``act(policy, feats) -> z``: the trained policy's deterministic action."""
    return deterministic_act(network(env, config), config.normalize_obs)


def make_window_loss(env, venv, pnet, config: ILDConfig, window: int):
    """``window_loss(policy, norm, obs, state, params, demo) -> (loss, (obs, state, feats,
    final_r_gt_sum, episodes_ended))``: ``window`` steps of the deterministic policy
    through the batched env ``venv`` from ``(obs, state)``, ``demo`` the batch's targets
    (:func:`episode_targets`); the loss is the
    :func:`state_distance` to the demonstration's state after each step, summed over the
    steps inside the episode and divided by ``num_envs * horizon``; differentiable in
    ``policy`` through the simulator."""
    horizon = env.horizon
    points_of = jax.vmap(env.object_points)
    effector_of = jax.vmap(env.end_effector)

    def window_loss(policy, norm, obs, state, params, demo):
        def step(carry, _):
            obs, state = carry
            t = state.t
            feats = batch_features(obs, t, horizon)
            mean, _ = pnet.apply(policy, norm(feats, config.normalize_obs))
            obs, state, _, _, info = venv.step(state, to_action(env, jnp.tanh(mean)),
                                               params)
            nxt = jnp.minimum(t + 1, horizon)
            envs = jnp.arange(nxt.shape[0])
            d = state_distance(points_of(state.physics), effector_of(state.physics),
                               demo.points[envs, nxt], demo.effector[envs, nxt], config)
            live = (t < horizon).astype(jnp.float32)
            final_r = jnp.where(t == horizon - 1, info["r_gt"], 0.0)
            return (obs, state), (feats, d * live, final_r, (t == horizon - 1))

        if config.remat:
            step = jax.checkpoint(step)
        (obs, state), (feats, d, final_r, last) = jax.lax.scan(step, (obs, state), None,
                                                              length=window)
        loss = jnp.sum(d) / (config.num_envs * horizon)
        return loss, (obs, state, feats, jnp.sum(final_r), jnp.sum(last))

    return window_loss


def make_train(env, config: ILDConfig):
    """``train(key, params, demo) -> (Policy, UpdateMetrics)``; ``demo`` a
    :class:`Demonstration`."""
    check_align(env, config)
    window = config.window_for(env)
    n_windows = math.ceil(env.horizon / window)
    venv = dax_tasks.VmapWrapper(env, config.num_envs)
    pnet = network(env, config)
    opt = make_optimiser(config.learning_rate, config.max_grad_norm, config.zero_nans)
    grad_fn = jax.value_and_grad(make_window_loss(env, venv, pnet, config, window),
                                 has_aux=True)

    def train(key, params, demo: Demonstration):
        k_pi, k_run = jax.random.split(key)
        policy = pnet.init(k_pi)
        opt_state = opt.init(policy)
        norm = ObsNorm.create(feature_dim(env))

        def update(carry, k):
            policy, opt_state, norm, steps = carry
            keys = jax.random.split(k, config.num_envs)
            if config.starts == "demo":
                keys = jnp.broadcast_to(demo.key, keys.shape)
            obs, state = venv.reset(keys, params)
            targets = episode_targets(env, demo, state.physics, params, config)

            def one_window(c, _):
                policy, opt_state, norm, obs, state = c
                (loss, (obs, state, feats, r_sum, n_last)), grads = grad_fn(
                    policy, norm, obs, state, params, targets)
                policy, opt_state, gnorm, bad = guarded_update(
                    opt, grads, opt_state, policy, config.zero_nans)
                norm = norm.update(feats) if config.normalize_obs else norm
                obs, state = jax.lax.stop_gradient((obs, state))
                return (policy, opt_state, norm, obs, state), (gnorm, bad, r_sum, n_last,
                                                               loss)

            (policy, opt_state, norm, _, _), (gnorm, bad, r_sum, n_last, loss) = jax.lax.scan(
                one_window, (policy, opt_state, norm, obs, state), None, length=n_windows)
            steps = steps + config.num_envs * window * n_windows
            metrics = UpdateMetrics(
                env_steps=steps, score=jnp.sum(r_sum) / jnp.maximum(jnp.sum(n_last), 1),
                episode_return=jnp.asarray(jnp.nan, jnp.float32), grad_norm=gnorm[-1],
                nonfinite=jnp.sum(bad.astype(jnp.int32)),
                grad_steps=jnp.asarray(n_windows, jnp.int32), loss=jnp.sum(loss))
            return (policy, opt_state, norm, steps), metrics

        carry = (policy, opt_state, norm, jnp.zeros((), jnp.int32))
        (policy, _, norm, _), metrics = jax.lax.scan(
            update, carry, jax.random.split(k_run, config.updates_for(env)))
        return Policy(policy, norm), metrics

    return train


LEARNER = Learner(make_train=make_train, make_act=make_act, network=network,
                  train_env_steps=train_env_steps, demo_spec=demo_spec)
