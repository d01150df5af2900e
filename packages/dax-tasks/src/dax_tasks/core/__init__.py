"""The env core: the task template and what every task shares.

:class:`~.env.Env` (pure ``reset``/``step`` over :class:`~.env.EnvParams` and
:class:`~.env.EnvState`), its static :class:`~.spec.TaskSpec`, the rewards, the registry and
``make``, the wrappers (batching, auto-reset, episode statistics, observation modes), eager
input checks, goal files, and splitting batches over devices and processes. It names no
task: tasks register themselves (:func:`~.registry.register`).
"""

from .env import Env, EnvParams, EnvState, MPMEnv
from .goals import GoalFileError
from .registry import (
    RESOLUTIONS,
    available,
    check_overrides,
    env_class,
    get_spec,
    make,
    register,
    spec_from_json,
)
from .rewards import auxiliary_reward, chamfer, ground_truth_reward, l2_correspondence
from .sharding import shard_batch
from .spec import Box, TaskSpec
from .wrappers import (
    AutoReset,
    EpisodeStatistics,
    ObjectFrame,
    ObservationMode,
    VmapWrapper,
    Wrapper,
    rgb_as_float,
    training_env,
)

__all__ = [
    "RESOLUTIONS", "AutoReset", "Box", "Env", "EnvParams", "EnvState", "EpisodeStatistics",
    "GoalFileError", "MPMEnv", "ObjectFrame", "ObservationMode", "TaskSpec", "VmapWrapper",
    "Wrapper",
    "auxiliary_reward", "available", "chamfer", "check_overrides", "env_class", "get_spec",
    "ground_truth_reward", "l2_correspondence", "make", "register", "rgb_as_float",
    "shard_batch", "spec_from_json", "training_env",
]
