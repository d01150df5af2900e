"""APG, the analytic policy gradient (as in Brax): the policy is rolled through the task's
differentiable step and its parameters ascend the sum of rewards by backpropagation.

Per update, ``num_envs`` auto-resetting envs run ``window`` steps of the deterministic
policy (``z = tanh(mean)``; ``action_noise`` adds Gaussian exploration noise to ``z``'s
pre-squash value); the loss is ``-mean_env(sum of training rewards over the window)``
(:func:`dax_algos.rl.losses.apg_return`) and its gradient flows through every simulator
step. ``window=None`` backpropagates through the
whole episode (each update is one episode per env); a shorter window truncates the
gradient: the state carried into the next window is ``stop_gradient``-ed (Brax's
truncation). The gradient's raw global norm is recorded, then clipped to
``max_grad_norm``; a non-finite gradient is counted and its update skipped (parameters and
optimiser state unchanged), or, with ``zero_nans=True``, its NaN/inf entries are zeroed and
the rest applied. ``remat=True`` recomputes each env step in the backward pass instead of
storing its intermediates (less memory, one more forward per step). Defaults from the
literature: MLP (512, 256) swish, Adam 1e-4, 4 envs, clip 0.3.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

import dax_tasks

from .. import nets
from ..actions import to_action
from ..checks import OMIT_DEFAULT, check_choice, check_fields
from ..learner import Learner, Policy
from ..mlp_policy import (
    ObsNorm,
    batch_features,
    check_frame,
    deterministic_act,
    feature_dim,
    policy_env,
)
from ..optim import check_lr_schedule, guarded_update, make_optimiser
from . import losses
from .training import training_params, update_metrics

OBJECTIVES = ("sum", "final")
#: What the backward pass does to the gradient reaching each env step's action from the
#: simulator (``APGConfig.action_grad``).
ACTION_GRADS = ("raw", "median_clip")


@jax.custom_vjp
def median_clipped(z):
    """Identity on the batch of actions ``z`` (num_envs, action_dim); in the backward
    pass, each env's row of the cotangent is scaled down to the median of the rows' norms
    where it is longer (shorter rows, zero rows included, pass unchanged).

    A heavy-tailed batch gradient (one env's step through contact many orders larger than
    the others') then moves the policy no more than a typical env's does, while keeping
    each row's direction; the median is of this step's batch, so no scale is chosen by
    hand."""
    return z


def _median_clipped_fwd(z):
    return z, None


def _median_clipped_bwd(_, g):
    norm = jnp.sqrt(jnp.sum(g * g, axis=-1, keepdims=True))
    cap = jnp.median(norm)
    return (g * jnp.minimum(1.0, cap / jnp.maximum(norm, 1e-30)),)


median_clipped.defvjp(_median_clipped_fwd, _median_clipped_bwd)


@dataclasses.dataclass(frozen=True)
class APGConfig:
    """total_env_steps: training budget in environment steps (``num_envs * window`` per
    update); window: backpropagation horizon in env steps (``None``: the episode);
    action_noise: std of exploration noise on the pre-squash action (0: none);
    objective: ``"sum"`` ascends the window's summed training rewards (r_gt + aux_weight
    r_aux per step), ``"final"`` the final-step r_gt of each episode that ends in the
    window (the score itself; a window in which no episode ends has no gradient).
    frame: ``"table"`` (the task's observation and actions) or ``"object"`` (a macro
    task's in the object's own frame, :class:`dax_tasks.ObjectFrame`); lr_schedule:
    ``"constant"`` or ``"linear"`` (to 0 over the run's updates, :data:`dax_algos.optim.
    LR_SCHEDULES`); action_grad: ``"raw"``, or ``"median_clip"`` to clip each env's
    action gradient at every step to the batch's median norm (:func:`median_clipped`)."""

    total_env_steps: int = 20_000
    num_envs: int = 4
    window: int | None = None
    learning_rate: float = 1e-4
    max_grad_norm: float | None = 0.3
    zero_nans: bool = False
    policy_hidden: tuple = (512, 256)
    activation: str = "swish"
    action_noise: float = 0.0
    normalize_obs: bool = True
    frame: str = "table"
    remat: bool = False
    aux_weight: float = 1.0
    objective: str = "sum"
    lr_schedule: str = "constant"
    action_grad: str = dataclasses.field(default="raw", metadata=OMIT_DEFAULT)
    n_eval: int = 20

    def __post_init__(self):
        check_frame(self.frame)
        check_lr_schedule(self.lr_schedule)
        check_fields(self, ints=("total_env_steps", "num_envs", "n_eval"),
                     positive=("learning_rate",), non_negative=("action_noise", "aux_weight"),
                     optional_ints=("window",), optional_positive=("max_grad_norm",))
        check_choice("action_grad", self.action_grad, ACTION_GRADS)
        check_choice("objective", self.objective, OBJECTIVES)

    def window_for(self, env) -> int:
        return env.horizon if self.window is None else self.window

    def updates_for(self, env) -> int:
        return max(1, self.total_env_steps // (self.num_envs * self.window_for(env)))


def network(env, config: APGConfig) -> nets.Network:
    """The deterministic policy's network (a Gaussian policy whose mean is used)."""
    return nets.policy_network(feature_dim(env), env.spec.action_dim,
                               config.policy_hidden, config.activation)


def make_act(env, config: APGConfig):
    """``act(policy, feats) -> z``: the trained policy's deterministic action."""
    return deterministic_act(network(env, config), config.normalize_obs)


def train_env_steps(env, config: APGConfig) -> int:
    """``num_envs * window`` per update, :meth:`APGConfig.updates_for` updates."""
    return config.num_envs * config.window_for(env) * config.updates_for(env)


def make_rollout(env, venv, pnet, config, window: int):
    """``rollout(policy_params, norm, obs, state, key, params) -> (objective, (obs,
    state, feats, reward, done, info))``: ``window`` steps of the batched env and
    :func:`dax_algos.rl.losses.apg_return` of their rewards (``config.objective="final"``:
    of each step's r_gt where an episode ends there, zero elsewhere), differentiable in
    ``policy_params`` through the simulator."""
    horizon = env.horizon

    def step(carry, k, policy_params, norm, params):
        obs, state = carry
        feats = batch_features(obs, state.t, horizon)
        mean, _ = pnet.apply(policy_params, norm(feats, config.normalize_obs))
        if config.action_noise > 0:
            mean = mean + config.action_noise * jax.random.normal(k, mean.shape)
        z = jnp.tanh(mean)
        if config.action_grad == "median_clip":
            z = median_clipped(z)
        obs, state, reward, done, info = venv.step(state, to_action(env, z), params)
        return (obs, state), (feats, reward, done, info)

    def rollout(policy_params, norm, obs, state, key, params):
        body = lambda c, k: step(c, k, policy_params, norm, params)  # noqa: E731
        if config.remat:
            body = jax.checkpoint(body)
        (obs, state), (feats, reward, done, info) = jax.lax.scan(
            body, (obs, state), jax.random.split(key, window))
        ascended = reward if config.objective == "sum" else jnp.where(done, info["r_gt"], 0.0)
        return losses.apg_return(ascended), (obs, state, feats, reward, done, info)

    return rollout


def make_train(env, config: APGConfig):
    """``train(key, params=None) -> (Policy, UpdateMetrics)``."""
    env = policy_env(env, config)
    window = config.window_for(env)
    venv = dax_tasks.training_env(env, config.num_envs)
    pnet = network(env, config)
    opt = make_optimiser(config.learning_rate, config.max_grad_norm, config.zero_nans,
                         lr_schedule=config.lr_schedule, steps=config.updates_for(env))
    rollout = make_rollout(env, venv, pnet, config, window)

    def loss(policy_params, *args):
        total, aux = rollout(policy_params, *args)
        return -total, aux

    grad_fn = jax.grad(loss, has_aux=True)

    def train(key, params=None):
        params = env.default_params if params is None else params
        tparams = training_params(params, config.aux_weight)
        k_pi, k_env, k_run = jax.random.split(key, 3)
        policy = pnet.init(k_pi)
        opt_state = opt.init(policy)
        obs, state = venv.reset(k_env, tparams)
        norm = ObsNorm.create(feature_dim(env))

        def update(carry, k):
            policy, opt_state, norm, obs, state, steps = carry
            obs, state = jax.lax.stop_gradient((obs, state))  # truncation between windows
            grads, (obs, state, feats, reward, done, info) = grad_fn(
                policy, norm, obs, state, k, tparams)
            policy, opt_state, gnorm, bad = guarded_update(opt, grads, opt_state, policy,
                                                           config.zero_nans)
            norm = norm.update(feats) if config.normalize_obs else norm
            steps = steps + window * config.num_envs
            metrics = update_metrics(steps, info, done, gnorm, bad, 1,
                                     -losses.apg_return(reward))
            return (policy, opt_state, norm, obs, state, steps), metrics

        carry = (policy, opt_state, norm, obs, state, jnp.zeros((), jnp.int32))
        (policy, _, norm, *_), metrics = jax.lax.scan(
            update, carry, jax.random.split(k_run, config.updates_for(env)))
        return Policy(policy, norm), metrics

    return train


LEARNER = Learner(make_train=make_train, make_act=make_act, network=network,
                  train_env_steps=train_env_steps)
