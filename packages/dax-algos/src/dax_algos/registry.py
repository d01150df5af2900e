"""The method registry: name -> :class:`dax_algos.method.PlannerMethod` or
:class:`dax_algos.method.LearnerMethod` (the method protocol, :mod:`dax_algos.method`),
with each method's budgets.

Budgets: ``"quick"`` (the benchmark's smoke run on 2 CPU cores) and ``"full"`` (the
budgets to report); on the MLS-MPM tasks (:data:`dax_algos.method.HEAVY_TASKS`) a method
may give smaller ones (``quick_heavy``, ``full_heavy``). See README.md for the numbers.
"""

from __future__ import annotations

from .il import ild, transporter
from .il.ild import ILDConfig
from .il.transporter import TransporterConfig
from .method import LearnerMethod, Method, PlannerMethod
from .planning import cem_mpc, diff_cem_mpc, diff_mpc, reference
from .planning.cem_mpc import CEMConfig
from .planning.diff_cem_mpc import DiffCEMConfig
from .planning.diff_mpc import DiffMPCConfig
from .rl import apg, ppo, shac
from .rl.apg import APGConfig
from .rl.ppo import PPOConfig
from .rl.shac import SHACConfig

_CEM_QUICK = dict(population=16, elites=4, iterations=2, horizon=1)
_CEM_QUICK_HEAVY = dict(population=6, elites=2, iterations=1, horizon=1)
_CEM_FULL = dict(population=64, elites=8, iterations=5, horizon=3)
# on the MLS-MPM tasks the full CEM's H * 961 env steps per episode do not fit a 2-core
# machine (README, "Budgets (planners)"): a tenth of it
_CEM_FULL_HEAVY = dict(population=16, elites=4, iterations=3, horizon=2)

#: Budgets of the planners: CEM's samples and iterations, diff-MPC's gradient steps.
PLANNING_BUDGETS = {
    "cem_mpc": {"quick": _CEM_QUICK, "quick_heavy": _CEM_QUICK_HEAVY, "full": _CEM_FULL,
                "full_heavy": _CEM_FULL_HEAVY},
    "diff_mpc": {"quick": dict(steps=5, horizon=1, learning_rate=0.1),
                 "quick_heavy": dict(steps=1, horizon=1, learning_rate=0.1),
                 "full": dict(steps=50, horizon=3, learning_rate=0.05),
                 "full_heavy": dict(steps=10, horizon=2, learning_rate=0.05)},
    "diff_cem_mpc": {
        "quick": dict(cem=_CEM_QUICK, diff=dict(steps=3, learning_rate=0.05)),
        "quick_heavy": dict(cem=_CEM_QUICK_HEAVY, diff=dict(steps=1, learning_rate=0.05)),
        "full": dict(cem=_CEM_FULL, diff=dict(steps=10, learning_rate=0.02)),
        "full_heavy": dict(cem=_CEM_FULL_HEAVY, diff=dict(steps=2, learning_rate=0.02))},
}

# PPO's, APG's and SHAC's full budgets on the MLS-MPM tasks; the ones measured for a task
# change them
_PPO_FULL = dict(total_env_steps=2304, num_envs=64, unroll_length=3)
_PPO_FULL_HEAVY = dict(total_env_steps=960, num_envs=32, unroll_length=3)
_PPO_POUR = dict(total_env_steps=1920, num_envs=8, unroll_length=12)
_APG_FULL_HEAVY = dict(total_env_steps=280, num_envs=4, window=10, learning_rate=1e-3)
_SHAC_FULL_HEAVY = dict(total_env_steps=320, num_envs=4, window=10)

#: Training budgets of the RL methods in environment steps (with their batch shapes). The
#: quick ones are sized for the demo grid on 2 CPU cores; see README.md for the full ones.
RL_BUDGETS = {
    "ppo": {"quick": dict(total_env_steps=192, num_envs=16, unroll_length=3, n_eval=4),
            "quick_heavy": dict(total_env_steps=48, num_envs=8, unroll_length=3, n_eval=2,
                                minibatches=2),
            "full": _PPO_FULL,
            "full_heavy": _PPO_FULL_HEAVY,
            # Unfold-Cloth-3: observations and picks in the object's frame (the same
            # unfold wherever and however the cloth lies), for 4x the updates: measured
            # better than the table frame's 12 updates (benchmarks.ablate
            # object_frame_long; README, the PPO cloth ablations)
            "full@unfold_cloth3": {**_PPO_FULL, "frame": "object", "total_env_steps": 9216},
            # Whip-Rope: 32 x 3 steps never end an episode and give a gradient with no
            # direction; 64 whole episodes per update measured better (benchmarks.ablate
            # big_batch, benchmarks.gradient_noise), and its evaluation score falls after
            # the first such update (benchmarks.ablate updates_1..3; README, "RL budgets")
            "full@whip_rope": dict(total_env_steps=3200, num_envs=64, unroll_length=50),
            # the pours (100-step episodes): 32 x 3 steps x 10 updates is 30 steps per env,
            # never an episode's end (no curve); 8 envs x 12 steps x 20 updates ends 2.4
            # per env (benchmarks.ablate whole_episodes on Pour-Water)
            "full@pour_water": _PPO_POUR,
            # Pour-Soup: 4.8x those updates (11.5 episodes per env) measured better
            # (benchmarks.ablate long; README, the PPO pour ablations)
            "full@pour_soup": {**_PPO_POUR, "total_env_steps": 9216},
            # Push-Rope: as APG's and SHAC's, the heavy budget's step walks the policy
            # under its untrained one; a tenth of it measured better (benchmarks.ablate
            # lr_low; README, the Push-Rope ablations): it does not learn the task
            "full@push_rope": {**_PPO_FULL_HEAVY, "learning_rate": 1e-4}},
    "apg": {"quick": dict(total_env_steps=48, num_envs=4, learning_rate=1e-3, n_eval=4),
            "quick_heavy": dict(total_env_steps=8, num_envs=2, window=4,
                                learning_rate=1e-3, n_eval=2),
            "full": dict(total_env_steps=480, num_envs=4, learning_rate=1e-3),
            "full_heavy": _APG_FULL_HEAVY,
            # the pours: the heavy budget stops 70 steps into the first 100-step episode;
            # 5x its updates (3.5 episodes per env) measured better (benchmarks.ablate long
            # on Pour-Water), a curve too short to read; at 10 episode ends per env each
            # pour's is flat and scores above it by more than 2 SE (benchmarks.ablate
            # to_read; README, the budget reads)
            **{f"full@{t}": {**_APG_FULL_HEAVY, "total_env_steps": 4000}
               for t in ("pour_water", "pour_soup")},
            # Push-Rope: ascending the summed r_gt + aux spoils the starts the policy
            # pushes; the final step's r_gt measured better (benchmarks.ablate
            # final_reward), still under the untrained policy; a tenth of the step on it
            # leaves the policy where it started, which measured better again
            # (benchmarks.ablate lr_low; README, the Push-Rope ablations): it does not
            # learn the task
            "full@push_rope": {**_APG_FULL_HEAVY, "objective": "final",
                               "learning_rate": 1e-4}},
    "shac": {"quick": dict(total_env_steps=48, num_envs=4, critic_minibatches=2, n_eval=4),
             "quick_heavy": dict(total_env_steps=8, num_envs=2, window=4,
                                 critic_minibatches=2, n_eval=2),
             # window 1 on the cloth tasks: each step's value closed by the critic
             # (measured better than the whole 3-5 step episode, benchmarks.ablate)
             "full": dict(total_env_steps=480, num_envs=8, window=1),
             "full_heavy": _SHAC_FULL_HEAVY,
             # the pours: training rollouts near the deterministic policy that is scored
             # (pre-tanh std 0.05, not 0.37) measured better (benchmarks.ablate std_low
             # on Pour-Water; Pour-Soup by analogy); the 8-update budget ended no episode,
             # and at 10 episode ends per env each pour scores above it by more than 2 SE
             # (benchmarks.ablate to_read; README, the budget reads)
             **{f"full@{t}": {**_SHAC_FULL_HEAVY, "init_log_std": -3.0,
                              "total_env_steps": 4000}
                for t in ("pour_water", "pour_soup")},
             # Push-Rope: the budget's step walks the policy into pushes that spoil the
             # starts it pushes (its first gradient is mostly noise); a tenth of the actor
             # step leaves the policy where it started, which measured better
             # (benchmarks.ablate lr_low; README): it does not learn the task
             "full@push_rope": {**_SHAC_FULL_HEAVY, "actor_learning_rate": 1e-4}},
}

#: Training budgets of the imitation methods: Transporter in Adam steps on the 10
#: demonstrations (no environment steps), ILD in environment steps (one episode per env and
#: update). See README.md for what they cost.
_ILD_FULL_HEAVY = dict(total_env_steps=1000, num_envs=2, window=10)
_TRANSPORTER = {"quick": dict(train_steps=200, n_eval=4), "full": dict(train_steps=1000)}
IL_BUDGETS = {
    "transporter": _TRANSPORTER,
    "transporter_rgb": {k: {**v, "rgb": True} for k, v in _TRANSPORTER.items()},
    # ILD: every update is one whole episode per env (in windows on the MPM tasks), so a
    # budget below num_envs * horizon still runs one update
    "ild": {"quick": dict(total_env_steps=48, num_envs=4, learning_rate=3e-4, n_eval=4),
            "quick_heavy": dict(total_env_steps=1, num_envs=2, window=4, n_eval=2),
            # the demonstration moved onto each start on the cloth tasks (their distance
            # aligns the goal to the cloth; measured better, benchmarks.ablate)
            "full": dict(total_env_steps=480, num_envs=4, learning_rate=3e-4,
                         align="start"),
            "full_heavy": _ILD_FULL_HEAVY,
            # Push-Rope: the budget ends under its untrained policy; a tenth of the step
            # leaves the policy where it started, which measured better (benchmarks.ablate
            # lr_low; README, "ILD on Push-Rope"): it does not learn the task
            "full@push_rope": {**_ILD_FULL_HEAVY, "learning_rate": 1e-4},
            # Whip-Rope: the rope's states, differentiated through the whip, lead the
            # policy to lower scores with more starts per update or more updates; matching
            # the gripper's path alone measured better (benchmarks.ablate effector_only;
            # README, "ILD on Whip-Rope")
            "full@whip_rope": {**_ILD_FULL_HEAVY, "object_weight": 0.0},
            # Pour-Water: the 5-update curve is too short to read; at 10 updates (10
            # episode ends per env) it is flat and scores above the 5-update budget by
            # more than 2 SE (benchmarks.ablate to_read; README, the budget reads)
            "full@pour_water": {**_ILD_FULL_HEAVY, "total_env_steps": 2000}},
}

_METHODS: dict[str, Method] = {}


def register(method: Method, overwrite: bool = False) -> None:
    """Add ``method`` to the registry (``overwrite`` to replace one of the same name)."""
    if method.name in _METHODS and not overwrite:
        raise ValueError(f"method {method.name!r} is already registered")
    _METHODS[method.name] = method


def unregister(name: str) -> None:
    """Remove the method called ``name`` (nothing if there is none)."""
    _METHODS.pop(name, None)


def names() -> tuple:
    """The registered method names, in registration order."""
    return tuple(_METHODS)


def get(name: str) -> Method:
    """The method called ``name`` (ValueError listing the valid names if none)."""
    if name not in _METHODS:
        raise ValueError(f"unknown method {name!r}; valid names: {', '.join(_METHODS)}")
    return _METHODS[name]


for _m in (
    PlannerMethod(name="random", family="reference", config_cls=reference.RandomConfig,
                  make_planner=reference.make_random),
    PlannerMethod(name="expert", family="reference", config_cls=reference.ExpertConfig,
                  make_planner=reference.make_expert),
    PlannerMethod(name="cem_mpc", family="planning", config_cls=CEMConfig,
                  make_planner=cem_mpc.make_planner, budgets=PLANNING_BUDGETS["cem_mpc"]),
    PlannerMethod(name="diff_mpc", family="planning", config_cls=DiffMPCConfig,
                  make_planner=diff_mpc.make_planner, budgets=PLANNING_BUDGETS["diff_mpc"],
                  uses_gradients=True),
    PlannerMethod(name="diff_cem_mpc", family="planning", config_cls=DiffCEMConfig,
                  make_planner=diff_cem_mpc.make_planner,
                  budgets=PLANNING_BUDGETS["diff_cem_mpc"], uses_gradients=True),
    LearnerMethod(name="ppo", family="rl", config_cls=PPOConfig, learner=ppo.LEARNER,
                  budgets=RL_BUDGETS["ppo"]),
    LearnerMethod(name="apg", family="rl", config_cls=APGConfig, learner=apg.LEARNER,
                  budgets=RL_BUDGETS["apg"], uses_gradients=True),
    LearnerMethod(name="shac", family="rl", config_cls=SHACConfig, learner=shac.LEARNER,
                  budgets=RL_BUDGETS["shac"], uses_gradients=True),
    LearnerMethod(name="transporter", family="il", config_cls=TransporterConfig,
                  learner=transporter.LEARNER, budgets=IL_BUDGETS["transporter"]),
    LearnerMethod(name="transporter_rgb", family="il", config_cls=TransporterConfig,
                  learner=transporter.LEARNER, budgets=IL_BUDGETS["transporter_rgb"]),
    LearnerMethod(name="ild", family="il", config_cls=ILDConfig, learner=ild.LEARNER,
                  budgets=IL_BUDGETS["ild"], uses_gradients=True),
):
    register(_m)
