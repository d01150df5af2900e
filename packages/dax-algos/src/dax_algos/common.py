"""Pieces the planners share: normalised actions, the planning objective, the receding-horizon
episode and the planner interface.

Actions are planned in *normalised* coordinates ``z`` in ``[-1, 1]^d`` (the task's action box
mapped affinely), so one step size or standard deviation fits every task; ``to_action`` maps
back. A plan is a ``(h, d)`` array of normalised actions for the next ``h`` environment steps.

A planner is a :class:`Planner`: ``init(key) -> pstate`` and ``plan(pstate, env_state, key,
params) -> (action, pstate, PlanStats)``, both pure and jittable; :func:`make_episode` runs
one episode with it as a single ``lax.scan`` (replanning from the current state at every
step). ``env`` is a pure :class:`dax_tasks.Env` and ``params`` its :class:`dax_tasks.EnvParams`
(data, so changing λ or a material number does not recompile an episode).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

OBJECTIVES = ("final", "sum")


class NotApplicable(ValueError):
    """A method does not apply to a task (the expert row on a task without a scripted
    expert, Transporter networks on a task without macro actions); the runner records
    ``status=skipped``, not a failure."""


def action_scale(env) -> tuple[jnp.ndarray, jnp.ndarray]:
    """``(mid, half)`` of the env's action box: ``action = mid + half * z``."""
    low = np.asarray(env.spec.action_low, np.float32)
    high = np.asarray(env.spec.action_high, np.float32)
    return jnp.asarray(0.5 * (low + high)), jnp.asarray(0.5 * (high - low))


def to_action(env, z):
    """The action of normalised coordinates ``z`` (clipped to [-1, 1]) [task units]."""
    mid, half = action_scale(env)
    return mid + half * jnp.clip(z, -1.0, 1.0)


def to_normalised(env, action):
    """Inverse of :func:`to_action` (0 where the box has zero width)."""
    mid, half = action_scale(env)
    return jnp.where(half > 0, (action - mid) / jnp.where(half > 0, half, 1.0), 0.0)


def plan_length(env, horizon: int) -> int:
    """The planning horizon actually used: ``horizon`` clipped to the episode length."""
    return max(1, min(int(horizon), int(env.horizon)))


def check_objective(objective: str) -> None:
    if objective not in OBJECTIVES:
        raise ValueError(f"unknown planning objective {objective!r}; "
                         f"valid: {', '.join(OBJECTIVES)}")


def make_objective(env, objective: str = "final") -> Callable:
    """``value(env_state, z_seq, params) -> scalar``: the return of the normalised action
    sequence ``z_seq`` (h, d) simulated from ``env_state`` with the env's pure step.

    ``"final"``: the task reward after the last planned step that is still inside the
    episode (the episode score is the final-step ``r_gt``); ``"sum"``: the sum of the rewards
    of the planned steps inside the episode. Steps past the episode's end are simulated (the
    shapes are static) but do not count. Differentiable in ``z_seq``, ``env_state`` and
    ``params``.
    """
    check_objective(objective)
    horizon = env.horizon

    def value(env_state, z_seq, params):
        def body(s, z):
            _, s2, reward, _, _ = env.step(s, to_action(env, z), params)
            return s2, (reward, s.t)

        _, (rewards, t0) = jax.lax.scan(body, env_state, z_seq)
        valid = t0 < horizon
        if objective == "sum":
            return jnp.sum(jnp.where(valid, rewards, 0.0))
        last = jnp.maximum(jnp.sum(valid.astype(jnp.int32)) - 1, 0)
        return rewards[last]

    return value


class PlanStats(NamedTuple):
    """Per-replanning statistics (scalars).

    objective: value of the chosen plan; grad_norm_max / grad_norm_sum: the largest (inf if
    any was non-finite) and the sum of the finite raw (unclipped) global gradient norms of
    the gradient steps; grad_steps: the
    number of gradient steps; nonfinite_grads: gradient steps whose gradient was NaN/inf.
    """

    objective: jnp.ndarray
    grad_norm_max: jnp.ndarray
    grad_norm_sum: jnp.ndarray
    grad_steps: jnp.ndarray
    nonfinite_grads: jnp.ndarray


def no_grad_stats(objective) -> PlanStats:
    z = jnp.zeros((), jnp.float32)
    return PlanStats(jnp.asarray(objective, jnp.float32), z, z, jnp.zeros((), jnp.int32),
                     jnp.zeros((), jnp.int32))


@dataclasses.dataclass(frozen=True)
class Planner:
    """A method that chooses one action per environment step.

    init(key) -> pstate; plan(pstate, env_state, key, params) -> (action, pstate,
    PlanStats): pure.
    sim_steps_per_plan: environment steps simulated per ``plan`` call (planning rollouts,
    forward passes); backprop_steps_per_plan: environment steps differentiated through per
    call (reverse passes); nan_grads_zeroed: non-finite gradients are zeroed by design
    (``zero_nans``), so the runner does not fail a run for them.
    """

    init: Callable[[Any], Any]
    plan: Callable[[Any, Any, Any], tuple]
    sim_steps_per_plan: int = 0
    backprop_steps_per_plan: int = 0
    nan_grads_zeroed: bool = False


class EpisodeOutput(NamedTuple):
    """Result of one episode (arrays; leading axis = environment step where it has one).

    score: final-step ``r_gt`` (the evaluation score); r_gt, reward, distance, finite: per step;
    actions: the executed actions; stats: :class:`PlanStats` per step; actions_score: the
    final-step ``r_gt`` of the one episode ``actions`` come from where ``score`` is a mean
    over several (a learner's evaluation rollouts), ``None`` where it is ``score``.
    """

    score: jnp.ndarray
    r_gt: jnp.ndarray
    reward: jnp.ndarray
    distance: jnp.ndarray
    finite: jnp.ndarray
    actions: jnp.ndarray
    stats: PlanStats
    actions_score: jnp.ndarray | None = None


def make_episode(env, planner: Planner) -> Callable:
    """``episode(key, params) -> EpisodeOutput``: reset the env with ``fold_in(key, 0)`` (so
    every method sees the same initial state for a seed) and run ``env.horizon`` steps, the
    planner choosing each action from the current state with keys from ``fold_in(key, 1)``.
    Pure; jit it."""
    horizon = env.horizon

    def episode(key, params):
        _, state = env.reset(jax.random.fold_in(key, 0), params)
        k_init, k_run = jax.random.split(jax.random.fold_in(key, 1))
        pstate = planner.init(k_init)

        def body(carry, k):
            state, pstate = carry
            action, pstate, stats = planner.plan(pstate, state, k, params)
            _, state, reward, _, info = env.step(state, action, params)
            out = (action, reward, info["r_gt"], info["distance"], info["finite"], stats)
            return (state, pstate), out

        _, (actions, reward, r_gt, dist, finite, stats) = jax.lax.scan(
            body, (state, pstate), jax.random.split(k_run, horizon))
        return EpisodeOutput(score=r_gt[-1], r_gt=r_gt, reward=reward, distance=dist,
                             finite=finite, actions=actions, stats=stats)

    return episode


def episode_env_steps(env, planner: Planner) -> tuple[int, int]:
    """``(simulated, differentiated)`` environment steps of one episode: the planning
    rollouts (forward) plus the executed steps, and the steps of the reverse passes."""
    h = env.horizon
    return h * (planner.sim_steps_per_plan + 1), h * planner.backprop_steps_per_plan


def shift(z_seq, fill):
    """The plan moved one step on (warm start), ``fill`` (d,) appended."""
    return jnp.concatenate([z_seq[1:], fill[None]], axis=0)


def check_positive_int(name: str, value) -> None:
    if not (isinstance(value, int) and not isinstance(value, bool) and value > 0):
        raise ValueError(f"{name} must be a positive int, got {value!r}")


def check_positive(name: str, value, allow_zero: bool = False) -> None:
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and np.isfinite(value)
    if not ok or value < 0 or (value == 0 and not allow_zero):
        bound = ">= 0" if allow_zero else "> 0"
        raise ValueError(f"{name} must be a finite number {bound}, got {value!r}")
