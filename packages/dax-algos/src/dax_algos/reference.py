"""Reference rows: ``random`` (uniform actions in the box) and ``expert`` (the task's scripted
expert with privileged state, :meth:`dax_tasks.Task.expert_action`). Both are planners
with no planning rollouts, so they share the episode driver of the planning methods."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from . import common


@dataclasses.dataclass(frozen=True)
class RandomConfig:
    """No options: one uniform action per step."""


@dataclasses.dataclass(frozen=True)
class ExpertConfig:
    """No options: the task's scripted expert."""


def make_random(task, config: RandomConfig) -> common.Planner:
    d = task.spec.action_dim

    def init(key):
        return jnp.zeros((), jnp.float32)

    def plan(pstate, env_state, key):
        z = jax.random.uniform(key, (d,), jnp.float32, -1.0, 1.0)
        return common.to_action(task, z), pstate, common.no_grad_stats(jnp.nan)

    return common.Planner(init=init, plan=plan)


def make_expert(task, config: ExpertConfig) -> common.Planner:
    if not task.has_expert:
        raise ValueError(f"task {task.spec.name!r} has no scripted expert")

    def init(key):
        return jnp.zeros((), jnp.float32)

    def plan(pstate, env_state, key):
        return task.expert_action(env_state), pstate, common.no_grad_stats(jnp.nan)

    return common.Planner(init=init, plan=plan)
