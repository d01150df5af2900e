"""Reference rows: ``random`` (uniform actions in the box) and ``expert`` (the task's scripted
expert with privileged state, :meth:`dax_tasks.Env.expert_action`). Both are planners
with no planning rollouts, so they share the episode driver of the planning methods."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from ..actions import to_action
from ..episode import no_grad_stats
from ..method import NotApplicable
from .planner import Planner


@dataclasses.dataclass(frozen=True)
class RandomConfig:
    """No options: one uniform action per step."""


@dataclasses.dataclass(frozen=True)
class ExpertConfig:
    """No options: the task's scripted expert."""


def make_random(env, config: RandomConfig) -> Planner:
    """A uniform normalised action in [-1, 1]^d every step (stats: no gradient, NaN
    objective)."""
    d = env.spec.action_dim

    def init(key):
        return jnp.zeros((), jnp.float32)

    def plan(pstate, env_state, key, params):
        z = jax.random.uniform(key, (d,), jnp.float32, -1.0, 1.0)
        return to_action(env, z), pstate, no_grad_stats(jnp.nan)

    return Planner(init=init, plan=plan)


def make_expert(env, config: ExpertConfig) -> Planner:
    """The task's scripted expert's action every step; :class:`dax_algos.method.
    NotApplicable` for a task without one."""
    if not env.has_expert:
        raise NotApplicable(f"task {env.spec.name!r} has no scripted expert")

    def init(key):
        return jnp.zeros((), jnp.float32)

    def plan(pstate, env_state, key, params):
        return env.expert_action(env_state, params), pstate, no_grad_stats(jnp.nan)

    return Planner(init=init, plan=plan)
