"""The task registry: ``TASKS`` and ``make(name, batch_size=None, seed=0, **overrides)``."""

from __future__ import annotations

import dataclasses
import importlib
from types import MappingProxyType

from .template import Task, TaskDef, TaskSpec

#: The nine benchmark tasks (issue 4), in the literature's order.
TASKS = (
    "pour_water", "pour_soup", "push_rope", "whip_rope", "fold_cloth1", "fold_cloth3",
    "fold_tshirt", "unfold_cloth1", "unfold_cloth3",
)

# Where each task lives: name -> (module, TaskDef attribute). Imported on first use.
_MODULES = MappingProxyType({
    "pour_water": ("dax_tasks.pour", "POUR_WATER"),
    "pour_soup": ("dax_tasks.pour", "POUR_SOUP"),
    "push_rope": ("dax_tasks.push_rope", "PUSH_ROPE"),
    "whip_rope": ("dax_tasks.whip_rope", "WHIP_ROPE"),
    "fold_cloth1": ("dax_tasks.cloth_tasks", "FOLD_CLOTH1"),
    "fold_cloth3": ("dax_tasks.cloth_tasks", "FOLD_CLOTH3"),
    "fold_tshirt": ("dax_tasks.cloth_tasks", "FOLD_TSHIRT"),
    "unfold_cloth1": ("dax_tasks.cloth_tasks", "UNFOLD_CLOTH1"),
    "unfold_cloth3": ("dax_tasks.cloth_tasks", "UNFOLD_CLOTH3"),
})


def _implemented(name: str) -> bool:
    module, attr = _MODULES[name]
    try:
        return hasattr(importlib.import_module(module), attr)
    except ModuleNotFoundError as err:
        if err.name != module:  # the task module exists but one of its imports does not
            raise
        return False


def available() -> tuple:
    """The names of the tasks implemented in this version."""
    return tuple(n for n in TASKS if _implemented(n))


def get_definition(name: str) -> TaskDef:
    """The :class:`TaskDef` (default spec and functions) of task ``name``."""
    if name not in TASKS:
        raise ValueError(f"unknown task {name!r}; valid names: {', '.join(TASKS)}")
    if not _implemented(name):
        raise NotImplementedError(
            f"task {name!r} is declared but not implemented yet in dax-tasks; "
            f"available now: {', '.join(available())}")
    module, attr = _MODULES[name]
    return getattr(importlib.import_module(module), attr)


def get_spec(name: str) -> TaskSpec:
    """The default :class:`TaskSpec` of task ``name``."""
    return get_definition(name).spec


def make(name: str, batch_size: int | None = None, seed: int = 0, goal_path=None,
         cache_goal: bool = True, **overrides) -> Task:
    """Build task ``name``. ``overrides`` replace :class:`TaskSpec` fields, e.g.
    ``aux_reward=True``, ``contact_adjustment=False``, ``horizon=3`` or a new ``scene``.
    ``goal_path`` / ``cache_goal``: where the goal comes from (:mod:`dax_tasks.goals`)."""
    defn = get_definition(name)
    fields = {f.name for f in dataclasses.fields(TaskSpec)} - {"name"}
    unknown = sorted(set(overrides) - fields)
    if unknown:
        raise ValueError(f"unknown TaskSpec override(s) {unknown}; valid: {sorted(fields)}")
    spec = dataclasses.replace(defn.spec, **overrides)
    return Task(defn, spec, batch_size=batch_size, seed=seed, goal_path=goal_path,
                cache_goal=cache_goal)
