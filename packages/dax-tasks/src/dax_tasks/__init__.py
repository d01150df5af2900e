"""Deformable-object manipulation tasks for DaX, built on dax-physics.

``env = dax_tasks.make(name, **overrides)`` builds a pure environment (:class:`Env`)::

    obs, state = env.reset(key, params)
    obs, state, reward, done, info = env.step(state, action, params)

with ``params = env.default_params`` (an :class:`EnvParams` pytree: goal, λ, auxiliary
weight, the task's physics numbers) when omitted. ``dax_tasks.TASKS`` lists the nine
benchmark names; :mod:`dax_tasks.wrappers` batches, auto-resets, records episode
statistics and selects observation modes; :mod:`dax_tasks.gym` holds the Gymnasium ids.
See README.md, and docs/ARCHITECTURE.md in the repository.
"""

import importlib.abc
import importlib.util
import sys
from importlib.metadata import PackageNotFoundError, version

from . import checks, goals, io, render, rewards, wrappers
from .env import Env, EnvParams, EnvState
from .goals import GoalFileError
from .registry import (
    RESOLUTIONS,
    TASKS,
    available,
    check_overrides,
    env_class,
    get_spec,
    make,
    spec_from_json,
)
from .rewards import auxiliary_reward, chamfer, ground_truth_reward, l2_correspondence
from .spec import Box, TaskSpec

try:
    __version__: str = version("dax-tasks")
except PackageNotFoundError:  # imported from a source tree that was never installed
    __version__ = "0+unknown"


class _GymnasiumLoader(importlib.abc.Loader):
    """Runs gymnasium's own loader, then registers the dax/... ids."""

    def __init__(self, loader):
        self._loader = loader

    def __getattr__(self, name):  # is_package, get_resource_reader, ...: the real loader's
        return getattr(self._loader, name)

    def create_module(self, spec):
        return self._loader.create_module(spec)

    def exec_module(self, module):
        self._loader.exec_module(module)
        importlib.import_module("dax_tasks.gym")


class _GymnasiumHook(importlib.abc.MetaPathFinder):
    """A one-shot import hook: when gymnasium is first imported, register the ids."""

    def find_spec(self, fullname, path, target=None):
        if fullname != "gymnasium":
            return None
        sys.meta_path.remove(self)
        spec = importlib.util.find_spec("gymnasium")
        if spec is not None and spec.loader is not None:
            spec.loader = _GymnasiumLoader(spec.loader)
        return spec


def _register_gym_ids() -> None:
    """Make ``gymnasium.make("dax/...")`` work without importing gymnasium here: register
    the ids now if gymnasium is already imported, else as soon as it is (an import hook)."""
    if "gymnasium" in sys.modules:
        importlib.import_module("dax_tasks.gym")
    elif importlib.util.find_spec("gymnasium") is not None:
        if not any(isinstance(f, _GymnasiumHook) for f in sys.meta_path):
            sys.meta_path.insert(0, _GymnasiumHook())


_register_gym_ids()

__all__ = [
    "RESOLUTIONS", "TASKS", "Box", "Env", "EnvParams", "EnvState", "GoalFileError", "TaskSpec",
    "__version__",
    "auxiliary_reward", "available", "chamfer", "check_overrides", "checks", "env_class",
    "get_spec", "goals", "ground_truth_reward", "io", "l2_correspondence", "make", "render",
    "rewards", "spec_from_json", "wrappers",
]
