"""What the RL methods' training loops share beyond their losses: the training reward's
params and the statistics of the episodes that ended in an update."""

from __future__ import annotations

import jax.numpy as jnp

from ..learner import UpdateMetrics


def training_params(params, aux_weight: float):
    """The env params used for training: the given ones with the auxiliary reward's weight
    set to ``aux_weight`` (1.0: r_gt + r_aux, the literature's training reward)."""
    return params.replace(aux_weight=jnp.asarray(aux_weight, jnp.float32))


def finished_episodes(info, done):
    """``(score, return)`` means over the episodes that ended in a batch of steps (NaN
    when none ended); ``info`` from :class:`dax_tasks.core.wrappers.EpisodeStatistics`
    (through :func:`dax_tasks.training_env`)."""
    done = done.astype(jnp.float32)
    n = jnp.sum(done)
    score = jnp.sum(info["episode_final_r_gt"] * done) / jnp.maximum(n, 1.0)
    ret = jnp.sum(info["episode_return"] * done) / jnp.maximum(n, 1.0)
    return jnp.where(n > 0, score, jnp.nan), jnp.where(n > 0, ret, jnp.nan)


def update_metrics(env_steps, info, done, grad_norm, nonfinite, grad_steps,
                   loss) -> UpdateMetrics:
    """An update's :class:`dax_algos.learner.UpdateMetrics`: the finished episodes' score
    and return from ``info`` / ``done`` (:func:`finished_episodes`), ``nonfinite`` counted
    as int32 and ``grad_steps`` as an int32 scalar."""
    score, ret = finished_episodes(info, done)
    return UpdateMetrics(env_steps=env_steps, score=score, episode_return=ret,
                         grad_norm=grad_norm, nonfinite=jnp.asarray(nonfinite, jnp.int32),
                         grad_steps=jnp.asarray(grad_steps, jnp.int32), loss=loss)
