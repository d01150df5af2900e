"""Deformable-object manipulation tasks for DaX, built on dax-physics.

``env = dax_tasks.make(name, **overrides)`` builds a pure environment (:class:`Env`)::

    obs, state = env.reset(key, params)
    obs, state, reward, done, info = env.step(state, action, params)

with ``params = env.default_params`` (an :class:`EnvParams` pytree: goal, λ, auxiliary
weight, the task's physics numbers) when omitted. ``dax_tasks.TASKS`` lists the nine
benchmark names; :func:`register` adds a task of your own under a name ``make`` builds.

Subpackages by role: :mod:`dax_tasks.core` (the env, spec, params, rewards, registry,
wrappers, checks, goal files, sharding), :mod:`dax_tasks.tasks` (the nine tasks, registered
on import), :mod:`dax_tasks.viz` (pictures); :mod:`dax_tasks.io` writes files atomically
under a lock; :mod:`dax_tasks.gym` registers the Gymnasium ids when imported
(``gymnasium.make("dax_tasks.gym:dax/FoldCloth1-v0")`` imports it for you).
"""

from importlib.metadata import PackageNotFoundError, version

from . import core, io, tasks, viz
from .core import (
    RESOLUTIONS,
    AutoReset,
    Box,
    Env,
    EnvParams,
    EnvState,
    EpisodeStatistics,
    GoalFileError,
    ObjectFrame,
    ObservationMode,
    TaskSpec,
    VmapWrapper,
    auxiliary_reward,
    available,
    chamfer,
    check_overrides,
    env_class,
    get_spec,
    ground_truth_reward,
    l2_correspondence,
    make,
    register,
    shard_batch,
    spec_from_json,
    training_env,
)
from .tasks import TASKS

try:
    __version__: str = version("dax-tasks")
except PackageNotFoundError:  # imported from a source tree that was never installed
    __version__ = "0+unknown"

__all__ = [
    "RESOLUTIONS", "TASKS", "AutoReset", "Box", "Env", "EnvParams", "EnvState",
    "EpisodeStatistics", "GoalFileError", "ObjectFrame", "ObservationMode", "TaskSpec",
    "VmapWrapper", "__version__", "auxiliary_reward", "available", "chamfer",
    "check_overrides", "core", "env_class", "get_spec", "ground_truth_reward", "io",
    "l2_correspondence", "make",
    "register", "shard_batch", "spec_from_json", "tasks", "training_env", "viz",
]
