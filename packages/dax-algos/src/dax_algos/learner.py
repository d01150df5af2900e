"""Learning methods: the :class:`Learner` protocol each one fills in, and train-then-
evaluate (:func:`learner_episode`), the episode the runner calls for a learner.

* **Training.** ``make_train(env, config) -> train(key, params[, data]) -> (Policy,
  UpdateMetrics)`` is one pure function that jits whole and vmaps over seeds; ``metrics``
  holds one :class:`UpdateMetrics` entry per training update. ``data`` is what an
  imitation method learns from (its :attr:`Learner.demo_spec` says which file).
* **Rewards.** The RL methods train on ``r_gt + aux_weight * r_aux``
  (:func:`dax_algos.rl.training.training_params`); evaluation uses the params the caller
  passes (the task's default has ``aux_weight = 0``: r_gt only).
* **Evaluation** (:func:`make_evaluate`): ``n`` episodes of the deterministic policy from
  ``n`` fresh starts; the score is the mean final-step r_gt. The untrained policy (the
  same network at initialisation, :meth:`Learner.untrained`) is evaluated on the same
  starts beside it, the baseline a learner must beat.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp

import dax_tasks

from .actions import to_action
from .episode import EpisodeOutput, PlanStats
from .mlp_policy import ObsNorm, feature_dim, features, policy_env


class Policy(NamedTuple):
    """A trained policy: the network's parameters and its input normaliser (``None`` for
    a policy that normalises nothing, e.g. Transporter networks)."""

    params: object
    obs_norm: ObsNorm | None


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


def make_evaluate(env, act: Callable, n_rollouts: int,
                  inputs: Callable | None = None, per_rollout: bool = False) -> Callable:
    """``evaluate(policy, key, params) -> EpisodeOutput``: ``n_rollouts`` episodes of the
    deterministic policy ``act(policy, inputs(obs, t)) -> z`` from starts drawn from
    ``key``, rewards with ``params`` (r_gt only for the task's default params); ``inputs``
    defaults to :func:`dax_algos.mlp_policy.features`. The output's per-step fields are
    means over the rollouts (``finite``: all of them), ``actions`` are those of the first
    rollout (its start is ``split(key, n_rollouts)[0]``, its final-step r_gt
    ``actions_score``: what the runner records to replay and draw the episode) and
    ``score`` the mean final-step r_gt. With ``per_rollout`` nothing is averaged: every
    field has the rollouts as its first axis (``score``: each rollout's final-step r_gt),
    for a standard error over the evaluation starts. The rollouts are split over the
    devices (:func:`dax_tasks.shard_batch`)."""
    horizon = env.horizon
    world = isinstance(env, dax_tasks.ObjectFrame)  # record the actions the task stepped
    if inputs is None:
        def inputs(obs, t):
            return features(obs, t, horizon)

    def one(policy, key, params):
        obs, state = env.reset(key, params)

        def body(carry, _):
            obs, state = carry
            z = act(policy, inputs(obs, state.t))
            action = to_action(env, z)
            obs, state, reward, _, info = env.step(state, action, params)
            if world:
                action = info["world_action"]
            return (obs, state), (action, reward, info["r_gt"], info["distance"],
                                  info["finite"])

        _, out = jax.lax.scan(body, (obs, state), None, length=horizon)
        return out

    def evaluate(policy, key, params):
        keys = dax_tasks.shard_batch(jax.random.split(key, n_rollouts))
        actions, reward, r_gt, dist, finite = jax.vmap(one, in_axes=(None, 0, None))(
            policy, keys, params)
        if per_rollout:
            return EpisodeOutput(score=r_gt[:, -1], r_gt=r_gt, reward=reward, distance=dist,
                                 finite=finite, actions=actions, stats=None)
        return EpisodeOutput(
            score=jnp.mean(r_gt[:, -1]), r_gt=jnp.mean(r_gt, 0), reward=jnp.mean(reward, 0),
            distance=jnp.mean(dist, 0), finite=jnp.all(finite, 0), actions=actions[0],
            stats=None, actions_score=r_gt[0, -1])

    return evaluate


def evaluate_features(env, config, act: Callable, per_rollout: bool = False) -> Callable:
    """The default :attr:`Learner.make_evaluate`: :func:`make_evaluate` of ``act`` on
    :func:`dax_algos.mlp_policy.features`, ``config.n_eval`` rollouts, in the env the
    policy acts in (:func:`dax_algos.mlp_policy.policy_env`; the recorded actions are the
    task's, in table coordinates)."""
    return make_evaluate(policy_env(env, config), act, config.n_eval,
                         per_rollout=per_rollout)


def no_demonstrations(config) -> None:
    """The default :attr:`Learner.demo_spec`: the method learns from no file."""
    return None


@dataclasses.dataclass(frozen=True)
class Learner:
    """A learning method, as the functions its module fills in (the registry holds it in
    a :class:`dax_algos.method.LearnerMethod`; :func:`learner_episode` and the runner call
    only these).

    make_train(env, config) -> train(key, params[, data]) -> (Policy, UpdateMetrics):
    pure, jittable whole. make_act(env, config) -> act(policy, inputs) -> z: the
    deterministic normalised action. network(env, config) -> :class:`dax_algos.nets.
    Network` whose parameters are ``Policy.params`` (what a policy file stores).
    train_env_steps(env, config) -> int: the environment steps one ``train`` call
    simulates (0 for a method that learns from demonstrations only).
    make_evaluate(env, config, act, per_rollout=False) -> evaluate(policy, key, params) ->
    EpisodeOutput: the evaluation rollouts (default :func:`evaluate_features`).
    demo_spec(config) -> :class:`dax_algos.il.demos.DemoSpec` | None: the demonstrations
    ``train`` takes as ``data`` (default :func:`no_demonstrations`).
    normalises_inputs: the policy carries an :class:`dax_algos.mlp_policy.ObsNorm` (the
    MLP policies) or ``None`` (:meth:`untrained`).
    """

    make_train: Callable
    make_act: Callable
    network: Callable
    train_env_steps: Callable
    make_evaluate: Callable = evaluate_features
    demo_spec: Callable = no_demonstrations
    normalises_inputs: bool = True

    def untrained(self, env, config, key) -> Policy:
        """A policy before training: the network's parameters at initialisation from
        ``key`` and, for a policy that normalises its inputs, the normaliser's initial
        statistics (zero mean, unit variance)."""
        norm = ObsNorm.create(feature_dim(env)) if self.normalises_inputs else None
        return Policy(self.network(env, config).init(key), norm)


class LearnOutput(NamedTuple):
    """What a learner's episode returns: the evaluation (``episode``; its ``stats`` are
    per training update), the learning curve, the trained policy and the untrained
    policy's score on the same evaluation starts (``untrained_score``)."""

    episode: EpisodeOutput
    metrics: UpdateMetrics
    policy: object
    untrained_score: jnp.ndarray


def stats_from_metrics(m: UpdateMetrics) -> PlanStats:
    """Per-update :class:`dax_algos.episode.PlanStats` for the runner's gradient columns."""
    finite = jnp.isfinite(m.grad_norm)
    return PlanStats(
        objective=m.episode_return,
        grad_norm_max=jnp.where(finite, m.grad_norm, jnp.inf),
        grad_norm_sum=jnp.where(finite, m.grad_norm, 0.0) * m.grad_steps,
        grad_steps=m.grad_steps, nonfinite_grads=m.nonfinite)


def untrained_key(key) -> jax.Array:
    """The key the untrained policy of a seed is drawn from, given the seed's episode key
    (``PRNGKey(seed)``): ``fold_in(key, 2)``, apart from the training's (1) and the
    evaluation's (0). The runner's untrained column and the ablations' use it."""
    return jax.random.fold_in(key, 2)


def learner_episode(learner: Learner, env, config) -> Callable:
    """``episode(key, params, *data) -> LearnOutput``: train from ``fold_in(key, 1)`` (with
    ``data``, e.g. demonstrations, for a method whose ``train`` takes them), then evaluate
    from ``fold_in(key, 0)`` with ``params`` (the learner's ``make_evaluate``), and the
    untrained policy (:meth:`Learner.untrained` of :func:`untrained_key`) on the same
    starts. Pure; the runner jits it and calls it per seed."""
    train = learner.make_train(env, config)
    evaluate = learner.make_evaluate(env, config, learner.make_act(env, config))

    def episode(key, params, *data):
        policy, metrics = train(jax.random.fold_in(key, 1), params, *data)
        start = jax.random.fold_in(key, 0)
        untrained = learner.untrained(env, config, untrained_key(key))
        # both policies through one traced evaluation (a two-step lax.map, run one after
        # the other as before): the rollout is compiled once, not twice
        untrained = jax.tree.map(lambda u, t: u.astype(t.dtype), untrained, policy)
        both = jax.tree.map(lambda t, u: jnp.stack([t, u]), policy, untrained)
        outs = jax.lax.map(lambda p: evaluate(p, start, params), both)
        out = jax.tree.map(lambda x: x[0], outs)
        out = out._replace(stats=stats_from_metrics(metrics))
        return LearnOutput(out, metrics, policy, outs.score[1])

    return episode
