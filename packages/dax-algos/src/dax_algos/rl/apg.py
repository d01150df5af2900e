"""APG, the analytic policy gradient (as in Brax): the policy is rolled through the task's
differentiable step and its parameters ascend the sum of rewards by backpropagation.

Per update, ``num_envs`` auto-resetting envs run ``window`` steps of the deterministic
policy (``z = tanh(mean)``; ``action_noise`` adds Gaussian exploration noise to ``z``'s
pre-squash value); the loss is ``-mean_env(sum of training rewards over the window)`` and
its gradient flows through every simulator step. ``window=None`` backpropagates through the
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

from dax_tasks.core.wrappers import training_env

from .. import common, learner, nets


@dataclasses.dataclass(frozen=True)
class APGConfig:
    """total_env_steps: training budget in environment steps (``num_envs * window`` per
    update); window: backpropagation horizon in env steps (``None``: the episode);
    action_noise: std of exploration noise on the pre-squash action (0: none)."""

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
    remat: bool = False
    aux_weight: float = 1.0
    n_eval: int = 20

    def __post_init__(self):
        learner.check_fields(self, ints=("total_env_steps", "num_envs", "n_eval"),
                        positive=("learning_rate",),
                        non_negative=("action_noise", "aux_weight"))
        if self.window is not None:
            common.check_positive_int("window", self.window)
        if self.max_grad_norm is not None:
            common.check_positive("max_grad_norm", self.max_grad_norm)

    def window_for(self, env) -> int:
        return env.horizon if self.window is None else self.window

    def updates_for(self, env) -> int:
        return max(1, self.total_env_steps // (self.num_envs * self.window_for(env)))


def network(env, config):
    return nets.policy_network(learner.feature_dim(env), env.spec.action_dim,
                               config.policy_hidden, config.activation)


def make_act(env, config: APGConfig):
    return learner.make_act(network(env, config), config.normalize_obs)


def make_rollout(env, venv, pnet, config, window: int):
    """``rollout(policy_params, norm, obs, state, key, params) -> (total_reward, (obs,
    state, feats, reward, done, info))``: ``window`` steps of the batched env; the
    total is differentiable in ``policy_params`` through the simulator."""
    horizon = env.horizon

    def step(carry, k, policy_params, norm, params):
        obs, state = carry
        feats = learner.batch_features(obs, state.t, horizon)
        mean, _ = pnet.apply(policy_params, norm(feats, config.normalize_obs))
        if config.action_noise > 0:
            mean = mean + config.action_noise * jax.random.normal(k, mean.shape)
        obs, state, reward, done, info = venv.step(state, common.to_action(env, jnp.tanh(mean)),
                                                   params)
        return (obs, state), (feats, reward, done, info)

    def rollout(policy_params, norm, obs, state, key, params):
        body = lambda c, k: step(c, k, policy_params, norm, params)  # noqa: E731
        if config.remat:
            body = jax.checkpoint(body)
        (obs, state), (feats, reward, done, info) = jax.lax.scan(
            body, (obs, state), jax.random.split(key, window))
        return jnp.mean(jnp.sum(reward, 0)), (obs, state, feats, reward, done, info)

    return rollout


def make_train(env, config: APGConfig):
    """``train(key, params=None) -> (learner.Policy, learner.UpdateMetrics)``."""
    window = config.window_for(env)
    venv = training_env(env, config.num_envs)
    pnet = network(env, config)
    opt = learner.make_optimiser(config.learning_rate, config.max_grad_norm, config.zero_nans)
    rollout = make_rollout(env, venv, pnet, config, window)

    def loss(policy_params, *args):
        total, aux = rollout(policy_params, *args)
        return -total, aux

    grad_fn = jax.grad(loss, has_aux=True)

    def train(key, params=None):
        params = env.default_params if params is None else params
        tparams = learner.training_params(params, config.aux_weight)
        k_pi, k_env, k_run = jax.random.split(key, 3)
        policy = pnet.init(k_pi)
        opt_state = opt.init(policy)
        obs, state = venv.reset(k_env, tparams)
        norm = learner.ObsNorm.create(learner.feature_dim(env))

        def update(carry, k):
            policy, opt_state, norm, obs, state, steps = carry
            obs, state = jax.lax.stop_gradient((obs, state))  # truncation between windows
            grads, (obs, state, feats, reward, done, info) = grad_fn(
                policy, norm, obs, state, k, tparams)
            policy, opt_state, gnorm, bad = learner.guarded_update(opt, grads, opt_state, policy,
                                                              config.zero_nans)
            norm = norm.update(feats) if config.normalize_obs else norm
            steps = steps + window * config.num_envs
            score, ret = learner.finished_episodes(info, done)
            metrics = learner.UpdateMetrics(
                env_steps=steps, score=score, episode_return=ret, grad_norm=gnorm,
                nonfinite=bad.astype(jnp.int32), grad_steps=jnp.ones((), jnp.int32),
                loss=-jnp.mean(jnp.sum(reward, 0)))
            return (policy, opt_state, norm, obs, state, steps), metrics

        carry = (policy, opt_state, norm, obs, state, jnp.zeros((), jnp.int32))
        (policy, _, norm, *_), metrics = jax.lax.scan(
            update, carry, jax.random.split(k_run, config.updates_for(env)))
        return learner.Policy(policy, norm), metrics

    return train
