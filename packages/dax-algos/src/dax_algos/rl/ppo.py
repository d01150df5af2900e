"""PPO (Schulman et al. 2017): the clipped surrogate objective with GAE, an entropy bonus
and observation normalisation, in the PureJaxRL pattern: ``make_train(env, config)``
returns ``train(key, params)``, one pure function (collection, advantages and every
minibatch step inside ``lax.scan``s) that jits whole and vmaps over seeds.

The simulator is a black box: collected transitions pass through ``lax.stop_gradient``
and the loss sees only the stored inputs, log-probabilities and returns. Per update,
``num_envs`` auto-resetting envs (:func:`dax_tasks.training_env`) run
``unroll_length`` steps of the stochastic policy (a diagonal Gaussian over pre-``tanh``
actions; the squash is part of the environment, so the ratio needs no correction); GAE
advantages (normalised per minibatch) and TD(λ) value targets are computed
(:func:`dax_algos.rl.losses.gae`), then ``epochs`` passes of ``minibatches`` Adam steps
on :func:`dax_algos.rl.losses.ppo_loss` (``clip surrogate + value_cost * value loss -
entropy_cost * entropy``), the gradient clipped to ``max_grad_norm``. Episodes end at
the task's horizon, which is terminal (no bootstrap past it). Defaults follow the earlier
JAX port for these tasks (learning rate 1e-3, 64 envs, unroll 3, discount 0.9, GAE λ 0.95,
clip 0.3, entropy cost 1e-4).
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp

import dax_tasks

from .. import nets
from ..actions import to_action
from ..checks import check_fields
from ..learner import Learner, Policy
from ..mlp_policy import (
    ObsNorm,
    batch_features,
    check_frame,
    deterministic_act,
    feature_dim,
    policy_env,
)
from ..optim import guarded_update, make_optimiser
from . import gaussian, losses
from .training import training_params, update_metrics


@dataclasses.dataclass(frozen=True)
class PPOConfig:
    """total_env_steps: training budget in environment steps (``num_envs *
    unroll_length`` per update); policy_hidden / value_hidden: MLP widths; activation:
    ``swish`` / ``tanh`` / ``relu`` / ``elu``; init_log_std: the Gaussian's initial log
    standard deviation (pre-``tanh``); max_grad_norm: global-norm clip (``None``: off);
    aux_weight: weight of r_aux in the training reward; n_eval: evaluation rollouts.
    frame: ``"table"`` (the task's observation and actions) or ``"object"`` (a macro
    task's in the object's own frame, :class:`dax_tasks.ObjectFrame`)."""

    total_env_steps: int = 100_000
    num_envs: int = 64
    unroll_length: int = 3
    epochs: int = 4
    minibatches: int = 4
    learning_rate: float = 1e-3
    discount: float = 0.9
    gae_lambda: float = 0.95
    clip: float = 0.3
    entropy_cost: float = 1e-4
    value_cost: float = 0.5
    max_grad_norm: float | None = 0.5
    policy_hidden: tuple = (64, 64)
    value_hidden: tuple = (128, 128)
    activation: str = "swish"
    init_log_std: float = -0.5
    normalize_obs: bool = True
    frame: str = "table"
    aux_weight: float = 1.0
    n_eval: int = 20

    def __post_init__(self):
        check_frame(self.frame)
        check_fields(self, ints=("total_env_steps", "num_envs", "unroll_length", "epochs",
                                 "minibatches", "n_eval"),
                     positive=("learning_rate", "clip"),
                     non_negative=("entropy_cost", "value_cost", "aux_weight"),
                     fractions=("discount", "gae_lambda"),
                     optional_positive=("max_grad_norm",))
        if (self.num_envs * self.unroll_length) % self.minibatches:
            raise ValueError(f"minibatches ({self.minibatches}) must divide num_envs * "
                             f"unroll_length ({self.num_envs * self.unroll_length})")

    @property
    def steps_per_update(self) -> int:
        return self.num_envs * self.unroll_length

    @property
    def updates(self) -> int:
        return max(1, self.total_env_steps // self.steps_per_update)


class Transition(NamedTuple):
    """One collected step of every env (a leading time axis after the unroll)."""

    feats: jnp.ndarray       # raw policy inputs (for the normaliser)
    inputs: jnp.ndarray      # normalised inputs the policy saw
    u: jnp.ndarray           # pre-tanh action sample
    log_prob: jnp.ndarray
    value: jnp.ndarray
    reward: jnp.ndarray
    done: jnp.ndarray


def policy_network(env, config: PPOConfig) -> nets.Network:
    """The Gaussian policy (what a policy file stores)."""
    return nets.policy_network(feature_dim(env), env.spec.action_dim, config.policy_hidden,
                               config.activation, config.init_log_std)


def value_network(env, config: PPOConfig) -> nets.Network:
    """The value function (an MLP on the same features)."""
    return nets.value_network(feature_dim(env), config.value_hidden, config.activation)


def make_act(env, config: PPOConfig):
    """``act(policy, feats) -> z``: the trained policy's deterministic action."""
    return deterministic_act(policy_network(env, config), config.normalize_obs)


def train_env_steps(env, config: PPOConfig) -> int:
    """``num_envs * unroll_length`` per update, :attr:`PPOConfig.updates` updates."""
    return config.steps_per_update * config.updates


def make_train(env, config: PPOConfig):
    """``train(key, params=None) -> (Policy, UpdateMetrics)`` (see the module docstring)."""
    env = policy_env(env, config)
    venv = dax_tasks.training_env(env, config.num_envs)
    pnet, vnet = policy_network(env, config), value_network(env, config)
    opt = make_optimiser(config.learning_rate, config.max_grad_norm)
    collect = make_collect(env, venv, pnet, vnet, config)
    learn = make_learn(pnet, vnet, opt, config)

    def train(key, params=None):
        params = env.default_params if params is None else params
        tparams = training_params(params, config.aux_weight)
        k_pi, k_v, k_env, k_run = jax.random.split(key, 4)
        net = {"policy": pnet.init(k_pi), "value": vnet.init(k_v)}
        opt_state = opt.init(net)
        obs, state = venv.reset(k_env, tparams)
        norm = ObsNorm.create(feature_dim(env))

        def update(carry, k):
            net, opt_state, norm, obs, state, steps = carry
            k_act, k_sgd = jax.random.split(k)
            (obs, state), (tr, info), data = collect(net, norm, obs, state, k_act, tparams)
            (net, opt_state), (loss, gnorm, bad) = learn(net, opt_state, data, k_sgd)
            norm = norm.update(tr.feats) if config.normalize_obs else norm
            steps = steps + config.steps_per_update
            metrics = update_metrics(steps, info, tr.done, jnp.max(gnorm),
                                     jnp.sum(bad.astype(jnp.int32)),
                                     config.epochs * config.minibatches, jnp.mean(loss))
            return (net, opt_state, norm, obs, state, steps), metrics

        carry = (net, opt_state, norm, obs, state, jnp.zeros((), jnp.int32))
        (net, _, norm, *_), metrics = jax.lax.scan(
            update, carry, jax.random.split(k_run, config.updates))
        return Policy(net["policy"], norm), metrics

    return train


def make_collect(env, venv, pnet, vnet, config: PPOConfig):
    """``collect(net, norm, obs, state, key, params) -> ((obs, state), (Transition, info),
    data)``: ``unroll_length`` steps of the stochastic policy in the batched env (the
    simulator a black box: the transitions are ``stop_gradient``-ed) and the training data
    ``(inputs, u, log_prob, advantages, returns)``, each flattened to ``(num_envs *
    unroll_length, ...)`` (:func:`dax_algos.rl.losses.gae`)."""
    horizon, batch = env.horizon, config.steps_per_update

    def collect(net, norm, obs, state, key, params):
        def env_step(carry, k):
            net, norm, obs, state = carry
            feats = batch_features(obs, state.t, horizon)
            inputs = norm(feats, config.normalize_obs)
            mean, log_std = pnet.apply(net["policy"], inputs)
            u = mean + jnp.exp(log_std) * jax.random.normal(k, mean.shape)
            value = vnet.apply(net["value"], inputs)[..., 0]
            action = to_action(env, jnp.tanh(u))
            obs, state, reward, done, info = venv.step(state, action, params)
            tr = Transition(feats, inputs, u, gaussian.log_prob(u, mean, log_std), value,
                            reward, done)
            return (net, norm, obs, state), (tr, info)

        (_, _, obs, state), (tr, info) = jax.lax.scan(
            env_step, (net, norm, obs, state), jax.random.split(key, config.unroll_length))
        tr, info = jax.lax.stop_gradient((tr, info))  # the simulator is a black box
        last_in = norm(batch_features(obs, state.t, horizon), config.normalize_obs)
        last_value = vnet.apply(net["value"], last_in)[..., 0]
        adv, returns = losses.gae(tr.reward, tr.value, tr.done, last_value,
                                  config.discount, config.gae_lambda)
        data = jax.tree_util.tree_map(lambda x: x.reshape(batch, *x.shape[2:]),
                                      (tr.inputs, tr.u, tr.log_prob, adv, returns))
        return (obs, state), (tr, info), data

    return collect


def make_learn(pnet, vnet, opt, config: PPOConfig):
    """``learn(net, opt_state, data, key) -> ((net, opt_state), (loss, grad_norm,
    nonfinite))``: ``epochs`` passes over ``data`` (:func:`make_collect`'s), each a random
    permutation cut into ``minibatches`` minibatches, one guarded Adam step on
    :func:`dax_algos.rl.losses.ppo_loss` per minibatch; the per-step values have the shape
    ``(epochs, minibatches)``."""
    batch = config.steps_per_update
    mb_size = batch // config.minibatches

    def loss_fn(net, mb):
        inputs, u, old_logp, adv, target = mb
        mean, log_std = pnet.apply(net["policy"], inputs)
        value = vnet.apply(net["value"], inputs)[..., 0]
        return losses.ppo_loss(gaussian.log_prob(u, mean, log_std), old_logp, adv, value,
                               target, gaussian.entropy(log_std), config.clip,
                               config.value_cost, config.entropy_cost)

    def sgd_step(carry, mb):
        net, opt_state = carry
        loss, grads = jax.value_and_grad(loss_fn)(net, mb)
        net, opt_state, norm, bad = guarded_update(opt, grads, opt_state, net, False)
        return (net, opt_state), (loss, norm, bad)

    def learn(net, opt_state, data, key):
        def epoch(c, ke):
            perm = jax.random.permutation(ke, batch)
            mbs = jax.tree_util.tree_map(
                lambda x: x[perm].reshape(config.minibatches, mb_size, *x.shape[1:]), data)
            return jax.lax.scan(sgd_step, c, mbs)

        return jax.lax.scan(epoch, (net, opt_state), jax.random.split(key, config.epochs))

    return learn


LEARNER = Learner(make_train=make_train, make_act=make_act, network=policy_network,
                  train_env_steps=train_env_steps)
