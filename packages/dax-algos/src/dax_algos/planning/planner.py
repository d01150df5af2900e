"""The planner interface and what the planners share: the planning objective, the plan's
warm start and the receding-horizon episode.

A plan is a ``(h, d)`` array of normalised actions (:mod:`dax_algos.actions`) for the
next ``h`` environment steps. A planner is a :class:`Planner`: ``init(key) -> pstate`` and
``plan(pstate, env_state, key, params) -> (action, pstate, PlanStats)``, both pure and
jittable; :func:`make_episode` runs one episode with it as a single ``lax.scan``
(replanning from the current state at every step). ``env`` is a pure
:class:`dax_tasks.Env` and ``params`` its :class:`dax_tasks.EnvParams` (data, so changing λ
or a material number does not recompile an episode).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp

from ..actions import to_action
from ..checks import check_choice
from ..episode import EpisodeOutput

OBJECTIVES = ("final", "sum")


@dataclasses.dataclass(frozen=True)
class Planner:
    """A method that chooses one action per environment step.

    init(key) -> pstate; plan(pstate, env_state, key, params) -> (action, pstate,
    PlanStats): pure. sim_steps_per_plan: environment steps simulated per ``plan`` call
    (planning rollouts, forward passes); backprop_steps_per_plan: environment steps
    differentiated through per call (reverse passes); nan_grads_zeroed: non-finite
    gradients are zeroed by design (``zero_nans``), so the runner does not fail a run for
    them.
    """

    init: Callable[[Any], Any]
    plan: Callable[[Any, Any, Any, Any], tuple]
    sim_steps_per_plan: int = 0
    backprop_steps_per_plan: int = 0
    nan_grads_zeroed: bool = False


def plan_length(env, horizon: int) -> int:
    """The planning horizon actually used: ``horizon`` clipped to [1, episode length]."""
    return max(1, min(int(horizon), int(env.horizon)))


def check_objective(objective: str) -> None:
    """``objective`` is one of :data:`OBJECTIVES` (``ValueError`` listing them if not)."""
    check_choice("planning objective", objective, OBJECTIVES)


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


def shift(z_seq, fill):
    """The plan ``(h, d)`` moved one step on (the next step's warm start), ``fill`` (d,)
    appended."""
    return jnp.concatenate([z_seq[1:], fill[None]], axis=0)


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


def warm_started_planner(env, horizon: int, objective: str, search: Callable,
                         **counts) -> Planner:
    """A :class:`Planner` whose search starts from a warm-start plan: the first plan from
    zeros ``(h, d)`` (the middle of the box), every later one from the previous plan
    shifted by one step with a zero last action. ``search(value_fn, z0, key) -> (best_z,
    PlanStats)`` maximises ``value_fn(z_seq)`` (the objective from the current state) from
    ``z0``; the first action of ``best_z`` is executed. ``h`` is ``horizon`` clipped
    (:func:`plan_length`); ``counts``: the :class:`Planner`'s step counts and
    ``nan_grads_zeroed``."""
    h = plan_length(env, horizon)
    d = env.spec.action_dim
    value = make_objective(env, objective)

    def init(key):
        return jnp.zeros((h, d), jnp.float32)

    def plan(z0, env_state, key, params):
        best_z, stats = search(lambda z: value(env_state, z, params), z0, key)
        return to_action(env, best_z[0]), shift(best_z, jnp.zeros(d)), stats

    return Planner(init=init, plan=plan, **counts)
