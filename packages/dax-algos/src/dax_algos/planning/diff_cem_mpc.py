"""diff-CEM-MPC: CEM first, then gradient refinement of its best sequence.

At every environment step: :func:`dax_algos.planning.cem_mpc.cem_optimise` from the
warm-start mean, then :func:`dax_algos.planning.diff_mpc.gradient_refine` from CEM's best
sequence with CEM's best value as the incumbent, so the chosen plan is never worse (by the
planning objective) than CEM's. The first action is executed; the next search starts from
the refined plan shifted by one step.
"""

from __future__ import annotations

import dataclasses

from .cem_mpc import CEMConfig, cem_optimise
from .diff_mpc import DiffMPCConfig, gradient_refine
from .planner import Planner, plan_length, warm_started_planner


@dataclasses.dataclass(frozen=True)
class DiffCEMConfig:
    """cem: the CEM stage; diff: the gradient stage (its ``horizon`` and ``objective`` are
    taken from ``cem``)."""

    cem: CEMConfig = CEMConfig()
    diff: DiffMPCConfig = DiffMPCConfig(steps=10)

    def __post_init__(self):
        if not isinstance(self.cem, CEMConfig) or not isinstance(self.diff, DiffMPCConfig):
            raise ValueError("DiffCEMConfig needs a CEMConfig and a DiffMPCConfig")


def make_planner(env, config: DiffCEMConfig) -> Planner:
    """diff-CEM-MPC for ``env``: pstate is the warm-start mean (h, d)."""
    cem = config.cem
    diff = dataclasses.replace(config.diff, horizon=cem.horizon, objective=cem.objective)
    h = plan_length(env, cem.horizon)

    def search(value_fn, mean, key):
        cem_z, cem_v = cem_optimise(value_fn, mean, key, cem)
        best_z, _, stats = gradient_refine(value_fn, cem_z, diff, best_z=cem_z, best_v=cem_v)
        return best_z, stats

    return warm_started_planner(
        env, cem.horizon, cem.objective, search,
        sim_steps_per_plan=cem.iterations * cem.population * h + (diff.steps + 1) * h,
        backprop_steps_per_plan=diff.steps * h, nan_grads_zeroed=diff.zero_nans)
