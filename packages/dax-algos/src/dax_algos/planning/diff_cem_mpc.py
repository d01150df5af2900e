"""diff-CEM-MPC: CEM first, then gradient refinement of its best sequence.

At every environment step: :func:`dax_algos.planning.cem_mpc.cem_optimise` from the warm-start
mean, then :func:`dax_algos.planning.diff_mpc.gradient_refine` from CEM's best sequence with CEM's
best value as the incumbent, so the chosen plan is never worse (by the planning objective)
than CEM's. The first action is executed; the next search starts from the refined plan
shifted by one step.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp

from .. import common
from .cem_mpc import CEMConfig, cem_optimise
from .diff_mpc import DiffMPCConfig, gradient_refine


@dataclasses.dataclass(frozen=True)
class DiffCEMConfig:
    """cem: the CEM stage; diff: the gradient stage (its ``horizon`` and ``objective`` are
    taken from ``cem``)."""

    cem: CEMConfig = CEMConfig()
    diff: DiffMPCConfig = DiffMPCConfig(steps=10)

    def __post_init__(self):
        if not isinstance(self.cem, CEMConfig) or not isinstance(self.diff, DiffMPCConfig):
            raise ValueError("DiffCEMConfig needs a CEMConfig and a DiffMPCConfig")


def make_planner(env, config: DiffCEMConfig) -> common.Planner:
    cem = config.cem
    diff = dataclasses.replace(config.diff, horizon=cem.horizon, objective=cem.objective)
    h = common.plan_length(env, cem.horizon)
    d = env.spec.action_dim
    value = common.make_objective(env, cem.objective)

    def init(key):
        return jnp.zeros((h, d), jnp.float32)

    def plan(mean, env_state, key, params):
        def f(z):
            return value(env_state, z, params)

        cem_z, cem_v = cem_optimise(f, mean, key, cem)
        best_z, _, stats = gradient_refine(f, cem_z, diff, best_z=cem_z, best_v=cem_v)
        action = common.to_action(env, best_z[0])
        return action, common.shift(best_z, jnp.zeros(d)), stats

    sims = cem.iterations * cem.population * h + (diff.steps + 1) * h
    return common.Planner(init=init, plan=plan, sim_steps_per_plan=sims,
                          backprop_steps_per_plan=diff.steps * h,
                          nan_grads_zeroed=diff.zero_nans)

