"""Deformable-object manipulation tasks for DaX, built on dax-physics.

``dax_tasks.make(name, batch_size=None, seed=0, **overrides)`` builds a task with a pure
``reset(key) -> (obs, state)`` and ``step(state, action) -> (obs, state, reward, done,
info)``; ``dax_tasks.TASKS`` lists the nine benchmark names. A task is a
:class:`TaskSpec` plus a few pure functions (:class:`TaskDef`); see README.md.
"""

from importlib.metadata import PackageNotFoundError, version

from . import goals, render, rewards
from .goals import GoalFileError
from .registry import TASKS, available, get_definition, get_spec, make
from .rewards import auxiliary_reward, chamfer, ground_truth_reward, l2_correspondence
from .template import Box, Task, TaskDef, TaskSpec, TaskState

try:  # Gymnasium ids (dax/PushRope-v0, ...); dax-tasks works without gymnasium installed
    from . import gym_envs
except ModuleNotFoundError as _err:  # pragma: no cover - depends on the environment
    if _err.name != "gymnasium":
        raise
else:
    gym_envs.register_all()

try:
    __version__: str = version("dax-tasks")
except PackageNotFoundError:  # imported from a source tree that was never installed
    __version__ = "0+unknown"

__all__ = [
    "TASKS", "Box", "GoalFileError", "Task", "TaskDef", "TaskSpec", "TaskState", "__version__",
    "auxiliary_reward", "available", "chamfer", "get_definition", "get_spec", "goals",
    "ground_truth_reward", "l2_correspondence", "make", "render", "rewards",
]
