"""SHAC, short-horizon actor-critic (Xu et al. 2022): the policy is rolled through the
differentiable step for a short window and the tail beyond it is bootstrapped with a
learned critic.

Per update, ``num_envs`` auto-resetting envs run ``window`` steps of the stochastic policy
(reparameterised: ``z = tanh(mean + std * eps)``, so the gradient reaches the mean and the
standard deviation through the simulator). The actor loss is the negative of

    sum over envs and episodes-in-window of  sum_t γ^t r_t  [+ γ^k V_target(s_window)]

divided by ``window * num_envs``; the bootstrap term is added only for an env whose
episode has not ended at the window's last step (the tasks end at their horizon, which is
terminal). The gradient's raw norm is recorded and clipped to ``max_grad_norm``; a
non-finite one is counted and its update skipped (``zero_nans=True``: zeroed entries).
Then the critic regresses TD(λ) targets computed with the *target* critic over the
window's stored inputs, ``critic_iterations`` passes of ``critic_minibatches`` Adam steps,
and the target critic follows by a soft update ``target = α target + (1 - α) critic``.
The window is the episode when the episode is shorter (the macro tasks), which makes SHAC
an APG with a stochastic policy there. Defaults from the paper, scaled for CPU budgets:
actor (512, 256, 128, 64) / critic (256, 128, 64, 32) swish with LayerNorm in the critic,
γ 0.99, λ 0.95, 16 critic iterations, α 0.2, clip 1.0, window 32.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from dax_tasks.core.wrappers import training_env

from .. import common, learner, nets


@dataclasses.dataclass(frozen=True)
class SHACConfig:
    """total_env_steps: training budget in environment steps (``num_envs * window`` per
    update); window: backpropagation horizon (clipped to the episode length)."""

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
    aux_weight: float = 1.0
    n_eval: int = 20

    def __post_init__(self):
        learner.check_fields(self, ints=("total_env_steps", "num_envs", "window",
                                    "critic_iterations", "critic_minibatches", "n_eval"),
                        positive=("actor_learning_rate", "critic_learning_rate"),
                        non_negative=("aux_weight",),
                        fractions=("discount", "td_lambda", "target_alpha"))
        if self.max_grad_norm is not None:
            common.check_positive("max_grad_norm", self.max_grad_norm)

    def window_for(self, env) -> int:
        return min(self.window, env.horizon)

    def updates_for(self, env) -> int:
        return max(1, self.total_env_steps // (self.num_envs * self.window_for(env)))


def networks(env, config: SHACConfig):
    fdim = learner.feature_dim(env)
    return (nets.policy_network(fdim, env.spec.action_dim, config.actor_hidden,
                                config.activation, config.init_log_std),
            nets.value_network(fdim, config.critic_hidden, config.activation, layer_norm=True))


def make_act(env, config: SHACConfig):
    return learner.make_act(networks(env, config)[0], config.normalize_obs)


def make_train(env, config: SHACConfig):
    """``train(key, params=None) -> (learner.Policy, learner.UpdateMetrics)``."""
    horizon = env.horizon
    window = config.window_for(env)
    venv = training_env(env, config.num_envs)
    pnet, vnet = networks(env, config)
    actor_opt = learner.make_optimiser(config.actor_learning_rate, config.max_grad_norm,
                                  config.zero_nans)
    critic_opt = learner.make_optimiser(config.critic_learning_rate, None)
    n = window * config.num_envs
    if n % config.critic_minibatches:
        raise ValueError(f"critic_minibatches ({config.critic_minibatches}) must divide "
                         f"window * num_envs ({n})")
    mb = n // config.critic_minibatches
    gamma = config.discount

    def value(vparams, norm, feats):
        return vnet.apply(vparams, norm(feats, config.normalize_obs))[..., 0]

    def actor_objective(policy, target, norm, obs, state, key, params):
        def step(carry, k):
            obs, state, acc, disc, total = carry
            feats = learner.batch_features(obs, state.t, horizon)
            mean, log_std = pnet.apply(policy, norm(feats, config.normalize_obs))
            u = mean + jnp.exp(log_std) * jax.random.normal(k, mean.shape)
            obs, state, reward, done, info = venv.step(
                state, common.to_action(env, jnp.tanh(u)), params)
            acc = acc + disc * reward
            total = total + jnp.where(done, acc, 0.0)
            acc = jnp.where(done, 0.0, acc)
            disc = jnp.where(done, 1.0, disc * gamma)
            return (obs, state, acc, disc, total), (feats, reward, done, info)

        zeros = jnp.zeros(config.num_envs, jnp.float32)
        (obs, state, acc, disc, total), (feats, reward, done, info) = jax.lax.scan(
            step, (obs, state, zeros, jnp.ones_like(zeros), zeros),
            jax.random.split(key, window))
        last_feats = learner.batch_features(obs, state.t, horizon)
        tail = disc * value(target, norm, last_feats)
        total = total + jnp.where(done[-1], 0.0, acc + tail)
        return jnp.sum(total) / n, (obs, state, feats, last_feats, reward, done, info)

    def actor_loss(*args):
        total, aux = actor_objective(*args)
        return -total, aux

    actor_value_grad = jax.value_and_grad(actor_loss, has_aux=True)

    def critic_loss(vparams, norm, feats, target):
        return jnp.mean((value(vparams, norm, feats) - target) ** 2)

    def critic_step(carry, batch):
        vparams, opt_state, norm = carry
        feats, target = batch
        loss, grads = jax.value_and_grad(critic_loss)(vparams, norm, feats, target)
        updates, opt_state = critic_opt.update(grads, opt_state, vparams)
        return (jax.tree_util.tree_map(lambda p, u: p + u, vparams, updates), opt_state,
                norm), loss

    def train(key, params=None):
        params = env.default_params if params is None else params
        tparams = learner.training_params(params, config.aux_weight)
        k_pi, k_v, k_env, k_run = jax.random.split(key, 4)
        policy, critic = pnet.init(k_pi), vnet.init(k_v)
        target = critic
        a_state, c_state = actor_opt.init(policy), critic_opt.init(critic)
        obs, state = venv.reset(k_env, tparams)
        norm = learner.ObsNorm.create(learner.feature_dim(env))

        def update(carry, k):
            policy, critic, target, a_state, c_state, norm, obs, state, steps = carry
            k_roll, k_crit = jax.random.split(k)
            (loss, aux), grads = actor_value_grad(policy, target, norm, obs, state, k_roll,
                                                  tparams)
            obs, state, feats, last_feats, reward, done, info = jax.lax.stop_gradient(aux)
            policy, a_state, gnorm, bad = learner.guarded_update(actor_opt, grads, a_state, policy,
                                                            config.zero_nans)
            # critic: TD(λ) targets from the target critic over the window's inputs
            values = value(target, norm, feats)
            targets = learner.td_lambda(reward, values, done, value(target, norm, last_feats),
                                   gamma, config.td_lambda)
            data = (feats.reshape(n, -1), targets.reshape(n))

            def iteration(c, ki):
                perm = jax.random.permutation(ki, n)
                batches = jax.tree_util.tree_map(
                    lambda x: x[perm].reshape(config.critic_minibatches, mb, *x.shape[1:]),
                    data)
                return jax.lax.scan(critic_step, c, batches)

            (critic, c_state, _), _ = jax.lax.scan(
                iteration, (critic, c_state, norm),
                jax.random.split(k_crit, config.critic_iterations))
            a = config.target_alpha
            target = jax.tree_util.tree_map(lambda t, c: a * t + (1 - a) * c, target, critic)
            norm = norm.update(feats) if config.normalize_obs else norm
            steps = steps + n
            score, ret = learner.finished_episodes(info, done)
            metrics = learner.UpdateMetrics(
                env_steps=steps, score=score, episode_return=ret, grad_norm=gnorm,
                nonfinite=bad.astype(jnp.int32), grad_steps=jnp.ones((), jnp.int32),
                loss=loss)
            return (policy, critic, target, a_state, c_state, norm, obs, state, steps), metrics

        carry = (policy, critic, target, a_state, c_state, norm, obs, state,
                 jnp.zeros((), jnp.int32))
        (policy, _, _, _, _, norm, *_), metrics = jax.lax.scan(
            update, carry, jax.random.split(k_run, config.updates_for(env)))
        return learner.Policy(policy, norm), metrics

    return train
