"""The task registry: ``TASKS``, ``get_spec(name)`` and the entry point ``make(name, ...)``."""

from __future__ import annotations

import dataclasses
import importlib
from types import MappingProxyType

import numpy as np

from . import goals
from .env import Env, EnvParams
from .spec import TaskSpec

#: The nine benchmark tasks, in the literature's order.
TASKS = (
    "pour_water", "pour_soup", "push_rope", "whip_rope", "fold_cloth1", "fold_cloth3",
    "fold_tshirt", "unfold_cloth1", "unfold_cloth3",
)

# Where each task lives: name -> (module, Env subclass, default TaskSpec attribute).
# Imported on first use.
_MODULES = MappingProxyType({
    "pour_water": ("dax_tasks.tasks.pour", "Pour", "POUR_WATER"),
    "pour_soup": ("dax_tasks.tasks.pour", "Pour", "POUR_SOUP"),
    "push_rope": ("dax_tasks.tasks.push_rope", "PushRope", "PUSH_ROPE"),
    "whip_rope": ("dax_tasks.tasks.whip_rope", "WhipRope", "WHIP_ROPE"),
    "fold_cloth1": ("dax_tasks.tasks.cloth", "ClothTask", "FOLD_CLOTH1"),
    "fold_cloth3": ("dax_tasks.tasks.cloth", "ClothTask", "FOLD_CLOTH3"),
    "fold_tshirt": ("dax_tasks.tasks.cloth", "ClothTask", "FOLD_TSHIRT"),
    "unfold_cloth1": ("dax_tasks.tasks.cloth", "ClothTask", "UNFOLD_CLOTH1"),
    "unfold_cloth3": ("dax_tasks.tasks.cloth", "ClothTask", "UNFOLD_CLOTH3"),
})

#: The :class:`EnvParams` fields ``make`` accepts as overrides of the default params.
PARAM_OVERRIDES = ("lam", "aux_weight")

#: ``make(name, resolution=...)``: ``"default"`` (the task's own resolution, chosen for
#: speed at the accuracy its README states) or ``"reference"`` (the original DaXBench
#: benchmark's particle or vertex count and substeps per step as closely as the scene
#: allows, for speed comparisons at equal work; each task module says how it matches).
RESOLUTIONS = ("default", "reference")


def _implemented(name: str) -> bool:
    module, cls, attr = _MODULES[name]
    try:
        mod = importlib.import_module(module)
    except ModuleNotFoundError as err:
        if err.name != module:  # the task module exists but one of its imports does not
            raise
        return False
    return hasattr(mod, cls) and hasattr(mod, attr)


def available() -> tuple:
    """The names of the tasks implemented in this version."""
    return tuple(n for n in TASKS if _implemented(n))


def _entry(name: str):
    if name not in TASKS:
        raise ValueError(f"unknown task {name!r}; valid names: {', '.join(TASKS)}")
    if not _implemented(name):
        raise NotImplementedError(
            f"task {name!r} is declared but not implemented yet in dax-tasks; "
            f"available now: {', '.join(available())}")
    module, cls, attr = _MODULES[name]
    mod = importlib.import_module(module)
    return getattr(mod, cls), getattr(mod, attr)


def get_spec(name: str, resolution: str = "default") -> TaskSpec:
    """The :class:`TaskSpec` of task ``name`` at ``resolution`` (:data:`RESOLUTIONS`)."""
    if resolution not in RESOLUTIONS:
        raise ValueError(f"unknown resolution {resolution!r}; valid: {', '.join(RESOLUTIONS)}")
    spec = _entry(name)[1]
    if resolution == "reference":
        module, _, attr = _MODULES[name]
        spec = getattr(importlib.import_module(module), f"{attr}_REFERENCE")
    return spec


def spec_from_json(data: dict) -> TaskSpec:
    """:meth:`TaskSpec.from_json` with the scene class of the registered task named in
    ``data``."""
    scene_type = type(get_spec(data["name"]).scene) if data.get("scene") is not None else None
    return TaskSpec.from_json(data, scene_type)


def env_class(name: str) -> type[Env]:
    """The :class:`Env` subclass that implements task ``name``."""
    return _entry(name)[0]


def check_overrides(name: str, overrides: dict) -> dict:
    """The :func:`make` overrides of task ``name``, checked before anything is built:
    :class:`TaskSpec` fields against the default spec's field types (a ``scene`` field by
    field against the default scene's; :func:`dax_tasks.core.spec.checked_fields`) and ``lam`` /
    ``aux_weight`` as real numbers. ``ValueError`` naming the key and the value (an unknown
    key lists the valid ones); returns the overrides with ints made floats for float
    fields and lists made tuples."""
    from .spec import checked_fields

    default = _entry(name)[1]
    spec_fields = {f.name for f in dataclasses.fields(TaskSpec)} - {"name"}
    unknown = sorted(set(overrides) - spec_fields - set(PARAM_OVERRIDES))
    if unknown:
        raise ValueError(f"unknown override(s) {unknown}; valid: TaskSpec fields "
                         f"{sorted(spec_fields)} and params {list(PARAM_OVERRIDES)}")
    params = {k: v for k, v in overrides.items() if k in PARAM_OVERRIDES}
    out = checked_fields(default, {k: v for k, v in overrides.items() if k not in params})
    for key, value in params.items():
        if isinstance(value, bool) or not isinstance(value, (int, float)) and not (
                hasattr(value, "dtype") and getattr(value, "shape", None) == ()
                and np.dtype(value.dtype).kind in "fiu"):
            raise ValueError(f"{key} must be a number, got {type(value).__name__} {value!r}")
        out[key] = value
    return out


def make(name: str, obs_mode: str = "state", image_size: int = 64, goal_path=None,
         cache_goal: bool = True, allow_goal_mismatch: bool = False,
         resolution: str = "default", **overrides) -> Env:
    """Build task ``name`` as a pure environment (:class:`dax_tasks.Env`).

    resolution: ``"default"`` or ``"reference"`` (:data:`RESOLUTIONS`): the spec the
        overrides apply to; ``"reference"`` is the original benchmark's particle or
        vertex count and substeps per step (``get_spec(name, "reference")``).

    overrides: :class:`TaskSpec` fields (``horizon=3``, ``substeps=50``, a new ``scene``,
        ``contact_adjustment=False``: a new program) and the default-params fields ``lam``
        and ``aux_weight`` (numbers: no new program; the same as
        ``env.default_params.replace(...)``).
    obs_mode: ``"state"`` (the task's own observation, default), ``"particles"``,
        ``"height"``, ``"rgb"`` or ``"rgbd"``: any other mode wraps the env in
        :class:`dax_tasks.core.wrappers.ObservationMode` with images of ``image_size`` pixels.
    goal_path / cache_goal: where the goal comes from (:mod:`dax_tasks.core.goals`).
    allow_goal_mismatch: use a ``goal_path`` made for another spec or by other code (its
        fingerprint is not this spec's) with a warning instead of refusing it.

    Overrides are checked against the types of the fields they change before anything is
    built (:func:`check_overrides`).

    Batching, auto-reset and episode statistics are wrappers the caller chooses
    (:mod:`dax_tasks.core.wrappers`); the Gymnasium ids are in :mod:`dax_tasks.gym`.
    """
    cls, _ = _entry(name)
    base = get_spec(name, resolution)
    overrides = check_overrides(name, overrides)
    param_changes = {k: overrides.pop(k) for k in PARAM_OVERRIDES if k in overrides}
    spec = dataclasses.replace(base, **overrides)
    env = cls(spec)
    points, provenance = goals.resolve_goal(env, goal_path, use_cache=cache_goal,
                                            allow_mismatch=allow_goal_mismatch)
    env = env.with_goal(points, provenance)
    if param_changes:
        env = env.with_default_params(_checked_params(env, param_changes))
    if obs_mode != "state":
        from .wrappers import ObservationMode

        return ObservationMode(env, obs_mode, image_size)
    return env


def _checked_params(env: Env, changes: dict) -> EnvParams:
    from .checks import check_params

    params = env.default_params.replace(**changes)
    check_params(env, params)
    return params
