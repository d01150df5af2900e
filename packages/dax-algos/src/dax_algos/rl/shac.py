"""SHAC, short-horizon actor-critic (Xu et al. 2022): the policy is rolled through the
differentiable step for a short window and the tail beyond it is bootstrapped with a
learned critic.

Per update, ``num_envs`` auto-resetting envs run ``window`` steps of the stochastic policy
(reparameterised: ``z = tanh(mean + std * eps)``, so the gradient reaches the mean and the
standard deviation through the simulator). The actor loss is the negative of

    sum over envs and episodes-in-window of  sum_t γ^t r_t  [+ γ^k V_target(s_window)]

divided by ``window * num_envs`` (:func:`dax_algos.rl.losses.shac_actor_objective`); the
bootstrap term is added only for an env whose episode has not ended at the window's last
step (the tasks end at their horizon, which is terminal). The gradient's raw norm is
recorded and clipped to ``max_grad_norm``; a non-finite one is counted and its update
skipped (``zero_nans=True``: zeroed entries). Then the critic regresses TD(λ) targets
(:func:`dax_algos.rl.losses.td_lambda`) computed with the *target* critic over the
window's stored inputs, ``critic_iterations`` passes of ``critic_minibatches`` Adam steps
(:func:`dax_algos.rl.losses.critic_loss`), and the target critic follows by a soft update
``target = α target + (1 - α) critic``.
The window is the episode when the episode is shorter (the macro tasks), which makes SHAC
an APG with a stochastic policy there. Defaults from the paper, scaled for CPU budgets:
actor (512, 256, 128, 64) / critic (256, 128, 64, 32) swish with LayerNorm in the critic,
γ 0.99, λ 0.95, 16 critic iterations, α 0.2, clip 1.0, window 32.
"""

from __future__ import annotations

import dataclasses

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
from . import losses
from .training import training_params, update_metrics


@dataclasses.dataclass(frozen=True)
class SHACConfig:
    """total_env_steps: training budget in environment steps (``num_envs * window`` per
    update); window: backpropagation horizon (clipped to the episode length).
    frame: ``"table"`` (the task's observation and actions) or ``"object"`` (a macro
    task's in the object's own frame, :class:`dax_tasks.ObjectFrame`)."""

    total_env_steps: int = 20_000
    num_envs: int = 8
    window: int = 32
    actor_learning_rate: float = 1e-3
    critic_learning_rate: float = 1e-3
    discount: float = 0.99
    td_lambda: float = 0.95
    critic_iterations: int = 16
    critic_minibatches: int = 4
    target_alpha: float = 0.2
    max_grad_norm: float | None = 1.0
    zero_nans: bool = False
    actor_hidden: tuple = (512, 256, 128, 64)
    critic_hidden: tuple = (256, 128, 64, 32)
    activation: str = "swish"
    init_log_std: float = -1.0
    normalize_obs: bool = True
    frame: str = "table"
    aux_weight: float = 1.0
    n_eval: int = 20

    def __post_init__(self):
        check_frame(self.frame)
        check_fields(self, ints=("total_env_steps", "num_envs", "window",
                                 "critic_iterations", "critic_minibatches", "n_eval"),
                     positive=("actor_learning_rate", "critic_learning_rate"),
                     non_negative=("aux_weight",),
                     fractions=("discount", "td_lambda", "target_alpha"),
                     optional_positive=("max_grad_norm",))

    def window_for(self, env) -> int:
        return min(self.window, env.horizon)

    def updates_for(self, env) -> int:
        return max(1, self.total_env_steps // (self.num_envs * self.window_for(env)))


def policy_network(env, config: SHACConfig) -> nets.Network:
    """The actor, a Gaussian policy (what a policy file stores)."""
    return nets.policy_network(feature_dim(env), env.spec.action_dim, config.actor_hidden,
                               config.activation, config.init_log_std)


def value_network(env, config: SHACConfig) -> nets.Network:
    """The critic (LayerNorm before each activation)."""
    return nets.value_network(feature_dim(env), config.critic_hidden, config.activation,
                              layer_norm=True)


def make_act(env, config: SHACConfig):
    """``act(policy, feats) -> z``: the trained actor's deterministic action."""
    return deterministic_act(policy_network(env, config), config.normalize_obs)


def train_env_steps(env, config: SHACConfig) -> int:
    """``num_envs * window`` per update, :meth:`SHACConfig.updates_for` updates."""
    return config.num_envs * config.window_for(env) * config.updates_for(env)


def make_train(env, config: SHACConfig):
    """``train(key, params=None) -> (Policy, UpdateMetrics)``."""
    env = policy_env(env, config)
    window = config.window_for(env)
    venv = dax_tasks.training_env(env, config.num_envs)
    pnet, vnet = policy_network(env, config), value_network(env, config)
    actor_opt = make_optimiser(config.actor_learning_rate, config.max_grad_norm,
                               config.zero_nans)
    critic_opt = make_optimiser(config.critic_learning_rate, None)
    n = window * config.num_envs
    fit_critic = make_fit_critic(vnet, critic_opt, config, n)
    actor_grad = jax.value_and_grad(make_actor_loss(env, venv, pnet, vnet, config, window),
                                    has_aux=True)

    def value(vparams, norm, feats):
        return vnet.apply(vparams, norm(feats, config.normalize_obs))[..., 0]

    def train(key, params=None):
        params = env.default_params if params is None else params
        tparams = training_params(params, config.aux_weight)
        k_pi, k_v, k_env, k_run = jax.random.split(key, 4)
        policy, critic = pnet.init(k_pi), vnet.init(k_v)
        target = critic
        a_state, c_state = actor_opt.init(policy), critic_opt.init(critic)
        obs, state = venv.reset(k_env, tparams)
        norm = ObsNorm.create(feature_dim(env))

        def update(carry, k):
            policy, critic, target, a_state, c_state, norm, obs, state, steps = carry
            k_roll, k_crit = jax.random.split(k)
            (loss, aux), grads = actor_grad(policy, target, norm, obs, state, k_roll,
                                            tparams)
            obs, state, feats, last_feats, reward, done, info = jax.lax.stop_gradient(aux)
            policy, a_state, gnorm, bad = guarded_update(actor_opt, grads, a_state, policy,
                                                         config.zero_nans)
            # critic: TD(λ) targets from the target critic over the window's inputs
            targets = losses.td_lambda(reward, value(target, norm, feats), done,
                                       value(target, norm, last_feats), config.discount,
                                       config.td_lambda)
            critic, c_state = fit_critic(critic, c_state, norm, feats, targets, k_crit)
            a = config.target_alpha
            target = jax.tree_util.tree_map(lambda t, c: a * t + (1 - a) * c, target, critic)
            norm = norm.update(feats) if config.normalize_obs else norm
            steps = steps + n
            metrics = update_metrics(steps, info, done, gnorm, bad, 1, loss)
            return (policy, critic, target, a_state, c_state, norm, obs, state, steps), metrics

        carry = (policy, critic, target, a_state, c_state, norm, obs, state,
                 jnp.zeros((), jnp.int32))
        (policy, _, _, _, _, norm, *_), metrics = jax.lax.scan(
            update, carry, jax.random.split(k_run, config.updates_for(env)))
        return Policy(policy, norm), metrics

    return train


def make_actor_loss(env, venv, pnet, vnet, config: SHACConfig, window: int):
    """``actor_loss(policy, target, norm, obs, state, key, params) -> (-objective, (obs,
    state, feats, last_feats, reward, done, info))``: ``window`` steps of the
    reparameterised stochastic policy through the batched env, and the negative of
    :func:`dax_algos.rl.losses.shac_actor_objective` with the target critic's value of
    the state after the window; differentiable in ``policy`` through the simulator."""
    horizon = env.horizon

    def actor_loss(policy, target, norm, obs, state, key, params):
        def step(carry, k):
            obs, state = carry
            feats = batch_features(obs, state.t, horizon)
            mean, log_std = pnet.apply(policy, norm(feats, config.normalize_obs))
            u = mean + jnp.exp(log_std) * jax.random.normal(k, mean.shape)
            obs, state, reward, done, info = venv.step(
                state, to_action(env, jnp.tanh(u)), params)
            return (obs, state), (feats, reward, done, info)

        (obs, state), (feats, reward, done, info) = jax.lax.scan(
            step, (obs, state), jax.random.split(key, window))
        last_feats = batch_features(obs, state.t, horizon)
        tail = vnet.apply(target, norm(last_feats, config.normalize_obs))[..., 0]
        objective = losses.shac_actor_objective(reward, done, tail, config.discount)
        return -objective, (obs, state, feats, last_feats, reward, done, info)

    return actor_loss


def make_fit_critic(vnet, critic_opt, config: SHACConfig, n: int):
    """``fit(critic, opt_state, norm, feats, targets, key) -> (critic, opt_state)``:
    ``critic_iterations`` passes over the window's ``n`` (feature, target) pairs, each a
    random permutation cut into ``critic_minibatches`` minibatches, one ``critic_opt``
    step on :func:`dax_algos.rl.losses.critic_loss` per minibatch."""
    if n % config.critic_minibatches:
        raise ValueError(f"critic_minibatches ({config.critic_minibatches}) must divide "
                         f"window * num_envs ({n})")
    mb = n // config.critic_minibatches

    def loss(vparams, norm, feats, target):
        values = vnet.apply(vparams, norm(feats, config.normalize_obs))[..., 0]
        return losses.critic_loss(values, target)

    def critic_step(carry, batch):
        vparams, opt_state, norm = carry
        feats, target = batch
        value, grads = jax.value_and_grad(loss)(vparams, norm, feats, target)
        updates, opt_state = critic_opt.update(grads, opt_state, vparams)
        return (jax.tree_util.tree_map(lambda p, u: p + u, vparams, updates), opt_state,
                norm), value

    def fit(critic, opt_state, norm, feats, targets, key):
        data = (feats.reshape(n, -1), targets.reshape(n))

        def iteration(c, ki):
            perm = jax.random.permutation(ki, n)
            batches = jax.tree_util.tree_map(
                lambda x: x[perm].reshape(config.critic_minibatches, mb, *x.shape[1:]), data)
            return jax.lax.scan(critic_step, c, batches)

        (critic, opt_state, _), _ = jax.lax.scan(
            iteration, (critic, opt_state, norm),
            jax.random.split(key, config.critic_iterations))
        return critic, opt_state

    return fit


LEARNER = Learner(make_train=make_train, make_act=make_act, network=policy_network,
                  train_env_steps=train_env_steps)
