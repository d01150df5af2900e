"""The method registry: name -> :class:`Method` (config class, builder, budgets).

A method builds, for one env and config, a :class:`Runnable`: a pure ``episode(key, params)
-> EpisodeOutput`` (the runner jits it once per task and method and calls it per seed with
the env's default params) and the
number of simulated / differentiated environment steps one call costs. The planners and the
reference rows build it from a :class:`dax_algos.common.Planner`; a learning method (PPO,
APG, SHAC, Transporter, ILD) can register a builder whose ``episode(key)`` trains and then
evaluates, under the same interface (:func:`register`).

Budgets: ``"quick"`` (the benchmark's smoke run on 2 CPU cores) and ``"full"`` (the budgets to
report); the quick budget is smaller still on the MPM tasks (``HEAVY_TASKS``), whose
episode costs 10-100x a cloth episode. See README.md for the numbers.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from types import MappingProxyType
from typing import Any

from . import common, learner
from .il import ild, transporter
from .il.ild import ILDConfig
from .il.transporter import TransporterConfig
from .planning import cem_mpc, diff_cem_mpc, diff_mpc, reference
from .planning.cem_mpc import CEMConfig
from .planning.diff_cem_mpc import DiffCEMConfig
from .planning.diff_mpc import DiffMPCConfig
from .rl import apg, ppo, shac
from .rl.apg import APGConfig
from .rl.ppo import PPOConfig
from .rl.shac import SHACConfig

BUDGETS = ("quick", "full")
#: Tasks simulated with MLS-MPM (70-100 env steps of 10-25 ms, or 6 pushes of 0.13 s, on 2
#: CPU cores, against 3-10 cloth pick-and-places of 6 ms); the quick budget is smaller there.
HEAVY_TASKS = frozenset({"push_rope", "pour_water", "pour_soup", "whip_rope"})


@dataclasses.dataclass(frozen=True)
class Runnable:
    """episode(key, params) -> EpisodeOutput (pure); env_steps / backprop_steps per call;
    nan_grads_zeroed: non-finite gradients are zeroed by design (not a failure)."""

    episode: Callable
    env_steps: int
    backprop_steps: int
    uses_gradients: bool
    nan_grads_zeroed: bool = False
    #: a learning method: ``episode`` returns :class:`dax_algos.learner.LearnOutput` (the
    #: evaluation, the learning curve, the trained policy)
    learns: bool = False
    #: training environment steps of one run (the learning curve's end), for learners
    train_env_steps: int = 0
    #: the demonstrations an imitation method learns from (a :class:`dax_algos.il.demos.
    #: DemoSpec`): the runner locates the file and passes ``load(env, path)`` to
    #: ``episode`` as a third argument, ``episode(key, params, data)``
    demos: Any = None


@dataclasses.dataclass(frozen=True)
class Method:
    """name: command-line name; kind: ``reference`` / ``planning`` / ``rl`` / ``il``;
    config_cls: its frozen config dataclass; build(env, config) -> Runnable;
    budgets: {"quick" | "quick_heavy" | "full": config keyword arguments};
    uses_gradients: whether it differentiates through the simulator."""

    name: str
    kind: str
    config_cls: type
    build: Callable[[Any, Any], Runnable]
    budgets: Mapping[str, Mapping[str, Any]]
    uses_gradients: bool = False
    #: for a learning method, its module (``make_train(env, config)``, ``make_act(env,
    #: config)``)
    learner: Any = None

    def config(self, budget: str = "full", task: str | None = None, **overrides):
        """The config for ``budget`` on ``task``, with ``overrides`` (nested configs take a
        dict of their own fields)."""
        if budget not in BUDGETS:
            raise ValueError(f"unknown budget {budget!r}; valid: {', '.join(BUDGETS)}")
        heavy = f"{budget}_heavy"
        key = heavy if task in HEAVY_TASKS and heavy in self.budgets else budget
        kwargs = dict(self.budgets.get(key, {}))
        kwargs.update(overrides)
        return _build_config(self.config_cls, kwargs)


def _build_config(cls, kwargs):
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(kwargs) - set(fields))
    if unknown:
        raise ValueError(f"unknown {cls.__name__} option(s) {unknown}; valid: {sorted(fields)}")
    out = {}
    for name, value in kwargs.items():
        default = fields[name].default
        if isinstance(value, Mapping) and dataclasses.is_dataclass(default):
            value = dataclasses.replace(default, **value)
        out[name] = value
    return cls(**out)


def planner_method(name, kind, config_cls, make_planner, budgets, uses_gradients=False):
    """A :class:`Method` from a planner builder ``make_planner(env, config) -> Planner``."""

    def build(env, config):
        planner = make_planner(env, config)
        sims, back = common.episode_env_steps(env, planner)
        return Runnable(common.make_episode(env, planner), sims, back, uses_gradients,
                        planner.nan_grads_zeroed)

    return Method(name, kind, config_cls, build, MappingProxyType(dict(budgets)),
                  uses_gradients)


def learner_method(name, kind, config_cls, module, budgets, uses_gradients):
    """A :class:`Method` from a learning module with ``make_train(env, config) ->
    train(key, params[, data])`` and ``make_act(env, config)`` (see :mod:`dax_algos.learner`),
    and optionally ``make_evaluate(env, config)`` (its own evaluation rollouts, e.g. on
    pictures), ``demo_spec(config)`` (the demonstrations its ``train`` takes as ``data``)
    and ``train_env_steps(env, config)``. One run trains from the seed's key and evaluates
    ``config.n_eval`` rollouts; the environment steps counted are training plus evaluation,
    the backpropagated ones (APG, SHAC, ILD) every training step. Non-finite gradients are
    skipped by the method and counted (``nonfinite_grads``), not a failure of the run."""

    def build(env, config):
        act = module.make_act(env, config)
        evaluate = (module.make_evaluate(env, config) if hasattr(module, "make_evaluate")
                    else None)
        episode = learner.learner_episode(module.make_train, act, env, config, config.n_eval,
                                     evaluate)
        train_steps = _train_env_steps(module, env, config)
        demos = module.demo_spec(config) if hasattr(module, "demo_spec") else None
        return Runnable(episode, train_steps + config.n_eval * env.horizon,
                        train_steps if uses_gradients else 0, uses_gradients,
                        nan_grads_zeroed=True, learns=True, train_env_steps=train_steps,
                        demos=demos)

    return Method(name, kind, config_cls, build, MappingProxyType(dict(budgets)),
                  uses_gradients, learner=module)


def _train_env_steps(module, env, config) -> int:
    if hasattr(module, "train_env_steps"):
        return module.train_env_steps(env, config)
    if hasattr(config, "steps_per_update"):
        return config.steps_per_update * config.updates
    return config.num_envs * config.window_for(env) * config.updates_for(env)


_CEM_QUICK = dict(population=16, elites=4, iterations=2, horizon=1)
_CEM_QUICK_HEAVY = dict(population=6, elites=2, iterations=1, horizon=1)
_CEM_FULL = dict(population=64, elites=8, iterations=5, horizon=3)

#: Training budgets of the RL methods in environment steps (with their batch shapes). The
#: quick ones are sized for the demo grid on 2 CPU cores; see README.md for the full ones.
RL_BUDGETS = {
    "ppo": {"quick": dict(total_env_steps=192, num_envs=16, unroll_length=3, n_eval=4),
            "quick_heavy": dict(total_env_steps=48, num_envs=8, unroll_length=3, n_eval=2,
                                minibatches=2),
            "full": dict(total_env_steps=2304, num_envs=64, unroll_length=3),
            "full_heavy": dict(total_env_steps=960, num_envs=32, unroll_length=3)},
    "apg": {"quick": dict(total_env_steps=48, num_envs=4, learning_rate=1e-3, n_eval=4),
            "quick_heavy": dict(total_env_steps=8, num_envs=2, window=4,
                                learning_rate=1e-3, n_eval=2),
            "full": dict(total_env_steps=480, num_envs=4, learning_rate=1e-3),
            "full_heavy": dict(total_env_steps=280, num_envs=4, window=10,
                               learning_rate=1e-3)},
    "shac": {"quick": dict(total_env_steps=48, num_envs=4, critic_minibatches=2, n_eval=4),
             "quick_heavy": dict(total_env_steps=8, num_envs=2, window=4,
                                 critic_minibatches=2, n_eval=2),
             "full": dict(total_env_steps=480, num_envs=8),
             "full_heavy": dict(total_env_steps=320, num_envs=4, window=10)},
}

#: Training budgets of the imitation methods: Transporter in Adam steps on the 10
#: demonstrations (no environment steps), ILD in environment steps (one episode per env and
#: update). See README.md for what they cost.
_TRANSPORTER = {"quick": dict(train_steps=200, n_eval=4), "full": dict(train_steps=1000)}
IL_BUDGETS = {
    "transporter": _TRANSPORTER,
    "transporter_rgb": {k: {**v, "rgb": True} for k, v in _TRANSPORTER.items()},
    # ILD: every update is one whole episode per env (in windows on the MPM tasks), so a
    # budget below num_envs * horizon still runs one update
    "ild": {"quick": dict(total_env_steps=48, num_envs=4, learning_rate=3e-4, n_eval=4),
            "quick_heavy": dict(total_env_steps=1, num_envs=2, window=4, n_eval=2),
            "full": dict(total_env_steps=480, num_envs=4, learning_rate=3e-4),
            "full_heavy": dict(total_env_steps=1000, num_envs=2, window=10)},
}

_METHODS: dict[str, Method] = {}


def register(method: Method, overwrite: bool = False) -> None:
    """Add ``method`` to the registry (``overwrite`` to replace one of the same name)."""
    if method.name in _METHODS and not overwrite:
        raise ValueError(f"method {method.name!r} is already registered")
    _METHODS[method.name] = method


def unregister(name: str) -> None:
    _METHODS.pop(name, None)


def names() -> tuple:
    """The registered method names."""
    return tuple(_METHODS)


def get(name: str) -> Method:
    """The :class:`Method` called ``name`` (ValueError listing the valid names if none)."""
    if name not in _METHODS:
        raise ValueError(f"unknown method {name!r}; valid names: {', '.join(_METHODS)}")
    return _METHODS[name]


for _m in (
    planner_method("random", "reference", reference.RandomConfig, reference.make_random, {}),
    planner_method("expert", "reference", reference.ExpertConfig, reference.make_expert, {}),
    planner_method("cem_mpc", "planning", CEMConfig, cem_mpc.make_planner, {
        "quick": _CEM_QUICK, "quick_heavy": _CEM_QUICK_HEAVY, "full": _CEM_FULL}),
    planner_method("diff_mpc", "planning", DiffMPCConfig, diff_mpc.make_planner, {
        "quick": dict(steps=5, horizon=1, learning_rate=0.1),
        "quick_heavy": dict(steps=1, horizon=1, learning_rate=0.1),
        "full": dict(steps=50, horizon=3, learning_rate=0.05)}, uses_gradients=True),
    planner_method("diff_cem_mpc", "planning", DiffCEMConfig, diff_cem_mpc.make_planner, {
        "quick": dict(cem=_CEM_QUICK, diff=dict(steps=3, learning_rate=0.05)),
        "quick_heavy": dict(cem=_CEM_QUICK_HEAVY, diff=dict(steps=1, learning_rate=0.05)),
        "full": dict(cem=_CEM_FULL, diff=dict(steps=10, learning_rate=0.02))},
        uses_gradients=True),
    learner_method("ppo", "rl", PPOConfig, ppo, RL_BUDGETS["ppo"], uses_gradients=False),
    learner_method("apg", "rl", APGConfig, apg, RL_BUDGETS["apg"], uses_gradients=True),
    learner_method("shac", "rl", SHACConfig, shac, RL_BUDGETS["shac"], uses_gradients=True),
    learner_method("transporter", "il", TransporterConfig, transporter,
                   IL_BUDGETS["transporter"], uses_gradients=False),
    learner_method("transporter_rgb", "il", TransporterConfig, transporter,
                   IL_BUDGETS["transporter_rgb"], uses_gradients=False),
    learner_method("ild", "il", ILDConfig, ild, IL_BUDGETS["ild"], uses_gradients=True),
):
    register(_m)
