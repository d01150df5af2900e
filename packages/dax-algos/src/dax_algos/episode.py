"""What one evaluated episode is, for every method: :class:`EpisodeOutput` (scores, the
per-step rewards and distances, the executed actions) with its gradient statistics
:class:`PlanStats` (per replanning for a planner, per training update for a learner). The
runner turns it into a results row and records its actions."""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp


class PlanStats(NamedTuple):
    """Gradient statistics, scalars per replanning (a planner) or per training update (a
    learner, :func:`dax_algos.learner.stats_from_metrics`).

    objective: value of the chosen plan (a learner: the update's mean training return);
    grad_norm_max: the largest raw (unclipped) global gradient norm of the gradient steps
    (inf if any was non-finite); grad_norm_sum: the sum of the finite ones; grad_steps:
    the number of gradient steps; nonfinite_grads: gradient steps whose gradient had a
    NaN/inf.
    """

    objective: jnp.ndarray
    grad_norm_max: jnp.ndarray
    grad_norm_sum: jnp.ndarray
    grad_steps: jnp.ndarray
    nonfinite_grads: jnp.ndarray


def no_grad_stats(objective) -> PlanStats:
    """The :class:`PlanStats` of a step that took no gradient: ``objective`` and zeros."""
    z = jnp.zeros((), jnp.float32)
    return PlanStats(jnp.asarray(objective, jnp.float32), z, z, jnp.zeros((), jnp.int32),
                     jnp.zeros((), jnp.int32))


class EpisodeOutput(NamedTuple):
    """Result of one episode (arrays; leading axis = environment step where it has one).

    score: final-step ``r_gt`` (the evaluation score); r_gt, reward, distance, finite: per
    step; actions: the executed actions ``(T, d)`` [task units]; stats: :class:`PlanStats`
    per step (planners) or per update (learners); actions_score: the final-step ``r_gt``
    of the one episode ``actions`` come from where ``score`` is a mean over several (a
    learner's evaluation rollouts), ``None`` where it is ``score``.
    """

    score: jnp.ndarray
    r_gt: jnp.ndarray
    reward: jnp.ndarray
    distance: jnp.ndarray
    finite: jnp.ndarray
    actions: jnp.ndarray
    stats: PlanStats
    actions_score: jnp.ndarray | None = None
