"""Pieces the reinforcement-learning methods (PPO, APG, SHAC) share.

* **Observations.** A policy sees the task's ``state`` observation flattened, plus the
  fraction of the episode elapsed, ``t / horizon``: every task has a fixed horizon and is
  scored on its *final* step, so the time left is part of the state (without it the value
  of a state is not defined). :class:`ObsNorm` keeps running mean and variance of these
  features (updated from each batch of collected observations, outside any gradient) and
  normalises them, clipped to ±10.
* **Actions.** Policies output normalised actions ``z = tanh(u)`` in ``(-1, 1)^d``; the
  task's action is ``common.to_action(env, z)`` (the box mapped affinely), so macro tasks
  get their pick-and-place / push coordinates and low-level tasks their velocities.
* **Rewards.** Training steps the env with ``params.replace(aux_weight=config.aux_weight)``
  (1.0 by default: ``r_gt + r_aux``, the literature's training reward); evaluation uses the
  params the caller passes (the task's default has ``aux_weight = 0``: r_gt only).
* **Evaluation** (:func:`make_evaluate`): ``n`` episodes with the deterministic policy
  (``z = tanh(mean)``) from ``n`` fresh starts; the score is the mean final-step r_gt.
* **Interface.** A method is ``make_train(env, config) -> train(key, params) ->
  (policy_state, metrics)``, pure and jittable whole; ``metrics`` holds one entry per
  training update (:class:`UpdateMetrics`). :func:`learner_runnable` turns it into the
  runner's ``episode(key, params)``: train, then evaluate.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import optax

from dax_tasks.core.sharding import shard_batch

from . import common

LOG_2PI = float(jnp.log(2.0 * jnp.pi))


# ----------------------------------------------------------------------------- observations

def features(obs, t, horizon: int):
    """The policy input of one env: the flattened observation and ``t / horizon``."""
    return jnp.concatenate([jnp.ravel(obs).astype(jnp.float32),
                            jnp.reshape(t / horizon, (1,)).astype(jnp.float32)])


def batch_features(obs, t, horizon: int):
    return jax.vmap(lambda o, tt: features(o, tt, horizon))(obs, t)


def feature_dim(env) -> int:
    return int(jnp.size(jnp.zeros(env.observation_space.shape))) + 1


class ObsNorm(NamedTuple):
    """Running mean / variance of the policy's input features (Chan et al.'s parallel
    update); ``count`` starts at a tiny value so the first batch sets the statistics."""

    mean: jnp.ndarray
    var: jnp.ndarray
    count: jnp.ndarray

    @staticmethod
    def create(dim: int) -> ObsNorm:
        return ObsNorm(jnp.zeros(dim, jnp.float32), jnp.ones(dim, jnp.float32),
                       jnp.asarray(1e-4, jnp.float32))

    def update(self, x) -> ObsNorm:
        x = jax.lax.stop_gradient(jnp.reshape(x, (-1, self.mean.shape[0])))
        n = jnp.asarray(x.shape[0], jnp.float32)
        b_mean, b_var = jnp.mean(x, 0), jnp.var(x, 0)
        total = self.count + n
        delta = b_mean - self.mean
        mean = self.mean + delta * n / total
        m2 = self.var * self.count + b_var * n + delta**2 * self.count * n / total
        return ObsNorm(mean, m2 / total, total)

    def __call__(self, x, enabled: bool = True):
        if not enabled:
            return x
        mean, var = jax.lax.stop_gradient(self.mean), jax.lax.stop_gradient(self.var)
        return jnp.clip((x - mean) / jnp.sqrt(var + 1e-8), -10.0, 10.0)


# ----------------------------------------------------------------------------- policies

def gaussian_log_prob(u, mean, log_std):
    return jnp.sum(-0.5 * ((u - mean) / jnp.exp(log_std)) ** 2 - log_std - 0.5 * LOG_2PI,
                   axis=-1)


def gaussian_entropy(log_std):
    return jnp.sum(log_std + 0.5 * (1.0 + LOG_2PI), axis=-1)


def training_params(params, aux_weight: float):
    """The env params used for training: the given ones with the auxiliary reward's weight
    set to ``aux_weight``."""
    return params.replace(aux_weight=jnp.asarray(aux_weight, jnp.float32))


def make_optimiser(learning_rate: float, max_grad_norm: float | None,
                   zero_nans: bool = False) -> optax.GradientTransformation:
    """``[zero_nans] -> [clip_by_global_norm] -> adam``."""
    parts = [optax.zero_nans()] if zero_nans else []
    if max_grad_norm is not None:
        parts.append(optax.clip_by_global_norm(max_grad_norm))
    parts.append(optax.adam(learning_rate))
    return optax.chain(*parts)


def guarded_update(opt, grads, opt_state, params, zero_nans: bool):
    """One optimiser step that never lets a non-finite gradient into the parameters.

    Returns ``(params, opt_state, raw_norm, nonfinite)``: the raw (unclipped) global norm
    and whether the gradient had a NaN/inf. With ``zero_nans`` the optimiser zeroes the
    non-finite entries and applies the rest (asked for explicitly); otherwise the whole
    update is skipped (parameters and optimiser state unchanged) and counted.
    """
    norm = optax.tree.norm(grads)
    nonfinite = ~jnp.isfinite(norm)
    updates, new_opt_state = opt.update(grads, opt_state, params)
    new_params = optax.apply_updates(params, updates)
    if zero_nans:
        return new_params, new_opt_state, norm, nonfinite
    keep = jnp.logical_not(nonfinite)
    pick = lambda new, old: jax.tree_util.tree_map(  # noqa: E731
        lambda a, b: jnp.where(keep, a, b), new, old)
    return pick(new_params, params), pick(new_opt_state, opt_state), norm, nonfinite


# ----------------------------------------------------------------------------- metrics

class UpdateMetrics(NamedTuple):
    """Per training update (each field has a leading update axis after the scan).

    env_steps: environment steps simulated by training so far (cumulative);
    score: mean final-step r_gt of the training episodes that ended in this update (NaN if
    none ended); episode_return: their mean return (training reward);
    grad_norm: raw global norm of the policy gradient (the last one of the update);
    nonfinite: policy-gradient steps of this update whose gradient was NaN/inf;
    grad_steps: policy-gradient steps in this update; loss: the method's main loss.
    """

    env_steps: jnp.ndarray
    score: jnp.ndarray
    episode_return: jnp.ndarray
    grad_norm: jnp.ndarray
    nonfinite: jnp.ndarray
    grad_steps: jnp.ndarray
    loss: jnp.ndarray


def finished_episodes(info, done):
    """``(score, return)`` means over the episodes that ended in a batch of steps (NaN
    when none ended); ``info`` from :class:`dax_tasks.core.wrappers.EpisodeStatistics`."""
    done = done.astype(jnp.float32)
    n = jnp.sum(done)
    score = jnp.sum(info["episode_final_r_gt"] * done) / jnp.maximum(n, 1.0)
    ret = jnp.sum(info["episode_return"] * done) / jnp.maximum(n, 1.0)
    return jnp.where(n > 0, score, jnp.nan), jnp.where(n > 0, ret, jnp.nan)


# ----------------------------------------------------------------------------- evaluation

class Policy(NamedTuple):
    """What evaluation needs of a trained policy: ``act(policy, inputs) -> z``; ``obs_norm``
    is ``None`` for a policy that normalises nothing (Transporter networks)."""

    params: object
    obs_norm: ObsNorm


def make_evaluate(env, act: Callable, n_rollouts: int,
                  inputs: Callable | None = None, per_rollout: bool = False) -> Callable:
    """``evaluate(policy, key, params) -> common.EpisodeOutput``: ``n_rollouts`` episodes of
    the deterministic policy ``act(policy, inputs(obs, t)) -> z`` from starts drawn from
    ``key``, rewards with ``params`` (r_gt only for the task's default params); ``inputs``
    defaults to :func:`features`. The output's per-step fields are means over the rollouts
    (``finite``: all of them), ``actions`` are those of the first rollout (its start is
    ``split(key, n_rollouts)[0]``, its final-step r_gt ``actions_score``: what the runner
    records to replay and draw the episode) and ``score`` the mean final-step r_gt. With
    ``per_rollout`` nothing is averaged: every field has the rollouts as its first axis
    (``score``: each rollout's final-step r_gt), for a standard error over the evaluation
    starts."""
    horizon = env.horizon
    if inputs is None:
        def inputs(obs, t):
            return features(obs, t, horizon)

    def one(policy, key, params):
        obs, state = env.reset(key, params)

        def body(carry, _):
            obs, state = carry
            z = act(policy, inputs(obs, state.t))
            action = common.to_action(env, z)
            obs, state, reward, _, info = env.step(state, action, params)
            return (obs, state), (action, reward, info["r_gt"], info["distance"],
                                  info["finite"])

        _, out = jax.lax.scan(body, (obs, state), None, length=horizon)
        return out

    def evaluate(policy, key, params):
        keys = shard_batch(jax.random.split(key, n_rollouts))  # over the devices
        actions, reward, r_gt, dist, finite = jax.vmap(one, in_axes=(None, 0, None))(
            policy, keys, params)
        if per_rollout:
            return common.EpisodeOutput(score=r_gt[:, -1], r_gt=r_gt, reward=reward,
                                        distance=dist, finite=finite, actions=actions,
                                        stats=None)
        return common.EpisodeOutput(
            score=jnp.mean(r_gt[:, -1]), r_gt=jnp.mean(r_gt, 0), reward=jnp.mean(reward, 0),
            distance=jnp.mean(dist, 0), finite=jnp.all(finite, 0), actions=actions[0],
            stats=None, actions_score=r_gt[0, -1])

    return evaluate


class LearnOutput(NamedTuple):
    """What a learning method's runnable returns: the evaluation (``episode``; its
    ``stats`` are per training update), the learning curve and the trained policy."""

    episode: common.EpisodeOutput
    metrics: UpdateMetrics
    policy: object


def stats_from_metrics(m: UpdateMetrics) -> common.PlanStats:
    """Per-update :class:`common.PlanStats` for the runner's gradient columns."""
    finite = jnp.isfinite(m.grad_norm)
    return common.PlanStats(
        objective=m.episode_return,
        grad_norm_max=jnp.where(finite, m.grad_norm, jnp.inf),
        grad_norm_sum=jnp.where(finite, m.grad_norm, 0.0) * m.grad_steps,
        grad_steps=m.grad_steps, nonfinite_grads=m.nonfinite)


def learner_episode(make_train_fn: Callable, act: Callable, env, config,
                    n_eval: int, evaluate: Callable | None = None) -> Callable:
    """``episode(key, params, *data) -> LearnOutput``: train from ``fold_in(key, 1)`` with
    the training reward (and ``data``, e.g. demonstrations, for methods whose ``train``
    takes them), then evaluate ``n_eval`` rollouts from ``fold_in(key, 0)`` with ``params``
    (``evaluate``, default :func:`make_evaluate` of ``act``). Pure; the runner jits (and
    vmaps over seeds) it."""
    train = make_train_fn(env, config)
    evaluate = make_evaluate(env, act, n_eval) if evaluate is None else evaluate

    def episode(key, params, *data):
        policy, metrics = train(jax.random.fold_in(key, 1), params, *data)
        out = evaluate(policy, jax.random.fold_in(key, 0), params)
        out = out._replace(stats=stats_from_metrics(metrics))
        return LearnOutput(out, metrics, policy)

    return episode


def check_fields(cfg, ints=(), positive=(), non_negative=(), fractions=()) -> None:
    """Validate a config's fields by name: positive ints, finite positive / non-negative
    numbers, and numbers in [0, 1]."""
    for name in ints:
        common.check_positive_int(name, getattr(cfg, name))
    for name in positive:
        common.check_positive(name, getattr(cfg, name))
    for name in non_negative:
        common.check_positive(name, getattr(cfg, name), allow_zero=True)
    for name in fractions:
        v = getattr(cfg, name)
        common.check_positive(name, v, allow_zero=True)
        if v > 1:
            raise ValueError(f"{name} must be in [0, 1], got {v!r}")
    hidden = [f.name for f in dataclasses.fields(cfg) if f.name.endswith("hidden")]
    for name in hidden:
        v = getattr(cfg, name)
        if not (isinstance(v, tuple) and v and all(isinstance(h, int) and h > 0 for h in v)):
            raise ValueError(f"{name} must be a non-empty tuple of positive ints, got {v!r}")


def td_lambda(rewards, values, done, last_value, discount: float, lam: float):
    """TD(λ) returns over a ``(T, B)`` batch of steps: ``G_t = r_t + γ (1 - d_t)
    [(1 - λ) V(s_{t+1}) + λ G_{t+1}]`` with ``G_T = V(s_T)`` (``last_value``). ``done``
    marks the last step of an episode (the tasks end at their horizon: no bootstrap past
    it). ``G - values`` is GAE(γ, λ)."""
    done = done.astype(jnp.float32)
    next_values = jnp.concatenate([values[1:], last_value[None]], axis=0)

    def body(g_next, x):
        r, v_next, d = x
        g = r + discount * (1.0 - d) * ((1.0 - lam) * v_next + lam * g_next)
        return g, g

    _, returns = jax.lax.scan(body, last_value, (rewards, next_values, done), reverse=True)
    return returns


def make_act(policy_net, normalize_obs: bool) -> Callable:
    """``act(policy, feats) -> z``: the deterministic action ``tanh(mean)``."""

    def act(policy: Policy, feats):
        mean, _ = policy_net.apply(policy.params, policy.obs_norm(feats, normalize_obs))
        return jnp.tanh(mean)

    return act
