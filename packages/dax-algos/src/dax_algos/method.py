"""The method protocol: what the registry holds and the benchmark runner calls.

A method is registered as a value: a :class:`PlannerMethod` (a planner builder,
``make_planner(env, config) -> Planner``) or a :class:`LearnerMethod` (a
:class:`dax_algos.learner.Learner`, the functions a learning module fills in). Both carry
the method's name, family, frozen config class and budgets, and ``build(env, config)``
turns them into what the runner runs: a :class:`Runnable` (a planner's episode) or a
:class:`LearnerRunnable` (train, then evaluate). Nothing here or in the runner probes a
module for attributes: a method is exactly the fields of its class.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from types import MappingProxyType
from typing import Any

from .checks import check_choice
from .learner import Learner, learner_episode
from .planning.planner import Planner, episode_env_steps, make_episode

#: The families of methods (the ``family`` field).
FAMILIES = ("reference", "planning", "rl", "il")
#: The budgets every method has: ``quick`` (the benchmark's smoke run) and ``full`` (the
#: budgets to report). A method's ``budgets`` may add ``quick_heavy`` / ``full_heavy``,
#: used on :data:`HEAVY_TASKS` instead, and ``"full@TASK"`` (or ``"quick@TASK"``), used
#: on that one task before either (a budget measured for it).
BUDGETS = ("quick", "full")
#: The tasks simulated with MLS-MPM, whose episodes cost more than a cloth task's: a
#: method's ``*_heavy`` budget applies to them.
HEAVY_TASKS = frozenset({"push_rope", "pour_water", "pour_soup", "whip_rope"})


class NotApplicable(ValueError):
    """A method does not apply to a task (the expert row on a task without a scripted
    expert, Transporter networks on a task without macro actions); raised by ``build``,
    the runner records ``status=skipped``, not a failure."""


@dataclasses.dataclass(frozen=True)
class Runnable:
    """What the runner runs for one (task, method, config).

    episode(key, params) -> :class:`dax_algos.episode.EpisodeOutput`: pure, jitted once
    and called per seed with ``PRNGKey(seed)`` and the env's default params; env_steps /
    backprop_steps: environment steps one call simulates / differentiates through;
    uses_gradients: the rows report gradient norms; nan_grads_zeroed: a non-finite
    gradient is handled by the method by design (zeroed or skipped and counted), so it
    does not fail the run.
    """

    episode: Callable
    env_steps: int
    backprop_steps: int
    uses_gradients: bool
    nan_grads_zeroed: bool = False


@dataclasses.dataclass(frozen=True)
class LearnerRunnable(Runnable):
    """A learner's :class:`Runnable`: ``episode(key, params, *data) ->
    :class:`dax_algos.learner.LearnOutput``` trains, then evaluates.

    train_env_steps: training environment steps of one call (the learning curve's end; 0
    for a method that learns from demonstrations only); demos: the demonstrations
    ``episode`` takes as ``data`` (a :class:`dax_algos.il.demos.DemoSpec`; the runner
    locates the file and passes ``demos.load(env, path)``), ``None`` for none.
    """

    train_env_steps: int = 0
    demos: Any = None


@dataclasses.dataclass(frozen=True, kw_only=True)
class Method:
    """What every registered method has. name: its command-line name; family: one of
    :data:`FAMILIES`; config_cls: its frozen config dataclass; budgets: ``{"quick" |
    "quick_heavy" | "full" | "full_heavy" | "full@TASK" | "quick@TASK": config keyword
    arguments}`` (see :data:`BUDGETS`); uses_gradients: whether it differentiates through
    the simulator."""

    name: str
    family: str
    config_cls: type
    budgets: Mapping[str, Mapping[str, Any]] = dataclasses.field(default_factory=dict)
    uses_gradients: bool = False

    def __post_init__(self):
        check_choice("method family", self.family, FAMILIES)
        object.__setattr__(self, "budgets", MappingProxyType(dict(self.budgets)))

    def config(self, budget: str = "full", task: str | None = None, **overrides):
        """The config for ``budget`` on ``task``, with ``overrides`` (nested configs take a
        dict of their own fields)."""
        check_choice("budget", budget, BUDGETS)
        heavy, own = f"{budget}_heavy", f"{budget}@{task}"
        key = (own if own in self.budgets
               else heavy if task in HEAVY_TASKS and heavy in self.budgets else budget)
        kwargs = dict(self.budgets.get(key, {}))
        kwargs.update(overrides)
        return _build_config(self.config_cls, kwargs)

    def build(self, env, config) -> Runnable:
        """The :class:`Runnable` of this method for ``env`` and ``config`` (raises
        :class:`NotApplicable` for a task the method does not apply to)."""
        raise NotImplementedError


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


@dataclasses.dataclass(frozen=True, kw_only=True)
class PlannerMethod(Method):
    """A planner (or a reference row): ``make_planner(env, config) ->
    :class:`dax_algos.planning.planner.Planner```. Its runnable is the receding-horizon
    episode; the steps counted are the planning rollouts plus the executed steps."""

    make_planner: Callable[[Any, Any], Planner]

    def build(self, env, config) -> Runnable:
        planner = self.make_planner(env, config)
        sims, back = episode_env_steps(env, planner)
        return Runnable(make_episode(env, planner), sims, back, self.uses_gradients,
                        planner.nan_grads_zeroed)


@dataclasses.dataclass(frozen=True, kw_only=True)
class LearnerMethod(Method):
    """A learning method: its :class:`dax_algos.learner.Learner`. One run trains from the
    seed's key and evaluates ``config.n_eval`` rollouts; the environment steps counted are
    training plus evaluation, the backpropagated ones (APG, SHAC, ILD) every training
    step. Non-finite gradients are skipped by the method and counted
    (``nonfinite_grads``), not a failure of the run."""

    learner: Learner

    def build(self, env, config) -> LearnerRunnable:
        episode = learner_episode(self.learner, env, config)
        train_steps = self.learner.train_env_steps(env, config)
        return LearnerRunnable(
            episode, train_steps + config.n_eval * env.horizon,
            train_steps if self.uses_gradients else 0, self.uses_gradients,
            nan_grads_zeroed=True, train_env_steps=train_steps,
            demos=self.learner.demo_spec(config))
