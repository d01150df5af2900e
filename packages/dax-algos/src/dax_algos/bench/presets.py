"""Named grids for ``dax-bench run --preset NAME``: the tasks, methods, seeds, budget and
output directory of a grid that has a name. Any of them given on the command line
replaces the preset's.

* ``demo``: the main job (``nox -s demo``): Fold-Cloth-1, the random and expert rows, a
  planner without gradients (CEM-MPC) and with them (diff-MPC), and a learner that learns
  within the demo's minutes: ILD (gradients through the simulator), each training episode
  restarted from its demonstration's start (``starts="demo"``, 2 envs, learning rate
  3e-4, 192 env steps: 32 updates), so its learning curve rises from its untrained
  policy's score; its evaluation starts at random like every other row's; two seeds.
* ``cloth``: three cloth tasks (Fold-Cloth-1, Fold-T-shirt, Unfold-Cloth-1), every
  method, two seeds, quick budgets.
* ``paper``: every task and every method at the full budgets, five seeds (the
  literature's protocol: five training seeds, each evaluated on 20 rollouts); meant to run
  in chunks (``--max-minutes``) and resumed, or on a Ray cluster (``--backend ray``).
"""

from __future__ import annotations

import dataclasses


@dataclasses.dataclass(frozen=True)
class Preset:
    """A named grid: ``tasks`` and ``methods`` as ``dax-bench run`` takes them
    (comma-separated names or ``all``), ``seeds`` (seeds ``0 .. seeds - 1``), ``quick``
    (the quick budgets, else the full ones), ``out`` (the output directory)."""

    tasks: str
    methods: str
    seeds: int
    quick: bool
    out: str
    what: str
    method_overrides: dict = dataclasses.field(default_factory=dict)


PRESETS = {
    "demo": Preset("fold_cloth1", "random,expert,cem_mpc,diff_mpc,ild", 2, True,
                   "bench_out", "the main job: one cloth task, the reference rows, a "
                   "planner with and without gradients and a learner (ILD, trained from "
                   "its demonstration's start)",
                   {"ild": dict(total_env_steps=192, num_envs=2, learning_rate=3e-4,
                                remat=True, starts="demo", n_eval=4)}),
    "cloth": Preset("fold_cloth1,fold_tshirt,unfold_cloth1", "all", 2, True,
                    "bench_out_cloth", "three cloth tasks, every method, quick budgets"),
    "paper": Preset("all", "all", 5, False, "results_paper",
                    "every task and method, full budgets, five seeds"),
}


def get(name: str) -> Preset:
    """The preset called ``name`` (``ValueError`` listing the valid ones)."""
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; valid: {', '.join(PRESETS)}")
    return PRESETS[name]
