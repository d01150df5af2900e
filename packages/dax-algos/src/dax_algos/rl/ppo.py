"""PPO (Schulman et al. 2017): the clipped surrogate objective with GAE, an entropy bonus
and observation normalisation, in the PureJaxRL pattern: ``make_train(env, config)``
returns ``train(key, params)``, one pure function (collection, advantages and every
minibatch step inside ``lax.scan``s) that jits whole and vmaps over seeds.

The simulator is a black box: collected transitions pass through ``lax.stop_gradient``
and the loss sees only the stored inputs, log-probabilities and returns. Per update,
``num_envs`` auto-resetting envs (:func:`dax_tasks.core.wrappers.training_env`) run
``unroll_length`` steps of the stochastic policy (a diagonal Gaussian over pre-``tanh``
actions; the squash is part of the environment, so the ratio needs no correction); GAE
advantages (normalised per minibatch) and TD(λ) value targets are computed, then
``epochs`` passes of ``minibatches`` Adam steps on ``clip surrogate + value_cost * value
loss - entropy_cost * entropy``, the gradient clipped to ``max_grad_norm``. Episodes end at
the task's horizon, which is terminal (no bootstrap past it). Defaults follow the earlier
JAX port for these tasks (learning rate 1e-3, 64 envs, unroll 3, discount 0.9, GAE λ 0.95,
clip 0.3, entropy cost 1e-4).
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp

from dax_tasks.core.wrappers import training_env

from .. import common, learner, nets


@dataclasses.dataclass(frozen=True)
class PPOConfig:
    """total_env_steps: training budget in environment steps (``num_envs *
    unroll_length`` per update); policy_hidden / value_hidden: MLP widths; activation:
    ``swish`` / ``tanh`` / ``relu`` / ``elu``; init_log_std: the Gaussian's initial log
    standard deviation (pre-``tanh``); max_grad_norm: global-norm clip (``None``: off);
    aux_weight: weight of r_aux in the training reward; n_eval: evaluation rollouts."""

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
    aux_weight: float = 1.0
    n_eval: int = 20

    def __post_init__(self):
        learner.check_fields(self, ints=("total_env_steps", "num_envs", "unroll_length", "epochs",
                                    "minibatches", "n_eval"),
                        positive=("learning_rate", "clip"),
                        non_negative=("entropy_cost", "value_cost", "aux_weight"),
                        fractions=("discount", "gae_lambda"))
        if self.max_grad_norm is not None:
            common.check_positive("max_grad_norm", self.max_grad_norm)
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
    feats: jnp.ndarray       # raw policy inputs (for the normaliser)
    inputs: jnp.ndarray      # normalised inputs the policy saw
    u: jnp.ndarray           # pre-tanh action sample
    log_prob: jnp.ndarray
    value: jnp.ndarray
    reward: jnp.ndarray
    done: jnp.ndarray


def networks(env, config: PPOConfig):
    fdim = learner.feature_dim(env)
    return (nets.policy_network(fdim, env.spec.action_dim, config.policy_hidden,
                                config.activation, config.init_log_std),
            nets.value_network(fdim, config.value_hidden, config.activation))


def make_act(env, config: PPOConfig):
    return learner.make_act(networks(env, config)[0], config.normalize_obs)


def make_train(env, config: PPOConfig):
    """``train(key, params=None) -> (learner.Policy, learner.UpdateMetrics)`` (see module doc)."""
    horizon = env.horizon
    venv = training_env(env, config.num_envs)
    pnet, vnet = networks(env, config)
    opt = learner.make_optimiser(config.learning_rate, config.max_grad_norm)
    batch = config.steps_per_update
    mb_size = batch // config.minibatches

    def loss_fn(net, mb):
        inputs, u, old_logp, adv, target = mb
        mean, log_std = pnet.apply(net["policy"], inputs)
        logp = learner.gaussian_log_prob(u, mean, log_std)
        ratio = jnp.exp(logp - old_logp)
        adv = (adv - jnp.mean(adv)) / (jnp.std(adv) + 1e-8)
        surrogate = jnp.minimum(ratio * adv,
                                jnp.clip(ratio, 1 - config.clip, 1 + config.clip) * adv)
        policy_loss = -jnp.mean(surrogate)
        value = vnet.apply(net["value"], inputs)[..., 0]
        value_loss = 0.5 * jnp.mean((value - target) ** 2)
        entropy = jnp.mean(learner.gaussian_entropy(log_std))
        return policy_loss + config.value_cost * value_loss - config.entropy_cost * entropy

    def sgd_step(carry, mb):
        net, opt_state = carry
        loss, grads = jax.value_and_grad(loss_fn)(net, mb)
        net, opt_state, norm, bad = learner.guarded_update(opt, grads, opt_state, net, False)
        return (net, opt_state), (loss, norm, bad)

    def train(key, params=None):
        params = env.default_params if params is None else params
        tparams = learner.training_params(params, config.aux_weight)
        k_pi, k_v, k_env, k_run = jax.random.split(key, 4)
        net = {"policy": pnet.init(k_pi), "value": vnet.init(k_v)}
        opt_state = opt.init(net)
        obs, state = venv.reset(k_env, tparams)
        norm = learner.ObsNorm.create(learner.feature_dim(env))

        def env_step(carry, k):
            net, norm, obs, state = carry
            feats = learner.batch_features(obs, state.t, horizon)
            inputs = norm(feats, config.normalize_obs)
            mean, log_std = pnet.apply(net["policy"], inputs)
            u = mean + jnp.exp(log_std) * jax.random.normal(k, mean.shape)
            value = vnet.apply(net["value"], inputs)[..., 0]
            action = common.to_action(env, jnp.tanh(u))
            obs, state, reward, done, info = venv.step(state, action, tparams)
            tr = Transition(feats, inputs, u, learner.gaussian_log_prob(u, mean, log_std), value,
                            reward, done)
            return (net, norm, obs, state), (tr, info)

        def update(carry, k):
            net, opt_state, norm, obs, state, steps = carry
            k_act, k_sgd = jax.random.split(k)
            (_, _, obs, state), (tr, info) = jax.lax.scan(
                env_step, (net, norm, obs, state), jax.random.split(k_act, config.unroll_length))
            tr, info = jax.lax.stop_gradient((tr, info))  # the simulator is a black box
            last_in = norm(learner.batch_features(obs, state.t, horizon), config.normalize_obs)
            last_value = vnet.apply(net["value"], last_in)[..., 0]
            returns = learner.td_lambda(tr.reward, tr.value, tr.done, last_value,
                                   config.discount, config.gae_lambda)
            data = jax.tree_util.tree_map(
                lambda x: x.reshape(batch, *x.shape[2:]),
                (tr.inputs, tr.u, tr.log_prob, returns - tr.value, returns))

            def epoch(c, ke):
                perm = jax.random.permutation(ke, batch)
                mbs = jax.tree_util.tree_map(
                    lambda x: x[perm].reshape(config.minibatches, mb_size, *x.shape[1:]), data)
                return jax.lax.scan(sgd_step, c, mbs)

            (net, opt_state), (loss, gnorm, bad) = jax.lax.scan(
                epoch, (net, opt_state), jax.random.split(k_sgd, config.epochs))
            norm = norm.update(tr.feats) if config.normalize_obs else norm
            steps = steps + batch
            score, ret = learner.finished_episodes(info, tr.done)
            metrics = learner.UpdateMetrics(
                env_steps=steps, score=score, episode_return=ret, grad_norm=jnp.max(gnorm),
                nonfinite=jnp.sum(bad.astype(jnp.int32)),
                grad_steps=jnp.asarray(config.epochs * config.minibatches, jnp.int32),
                loss=jnp.mean(loss))
            return (net, opt_state, norm, obs, state, steps), metrics

        carry = (net, opt_state, norm, obs, state, jnp.zeros((), jnp.int32))
        (net, _, norm, *_), metrics = jax.lax.scan(
            update, carry, jax.random.split(k_run, config.updates))
        return learner.Policy(net["policy"], norm), metrics

    return train
