"""The task registry and ``make``: task names -> the :class:`Env` subclass that implements
each and its default :class:`TaskSpec`.

A task is registered once, by name, with :func:`register`: its env class, its default spec
and optionally its spec at the original benchmark's resolution (``resolution=
"reference"``). Each is the object itself or a ``"module:attribute"`` string (Gymnasium's
entry-point convention) that is imported the first time the task is used, so registering
imports nothing. :mod:`dax_tasks.tasks` registers the nine benchmark tasks when
``dax_tasks`` is imported; a user's own task is registered the same way and is then built
by :func:`make` like them::

    dax_tasks.register("nudge_block", Nudge, spec)
    env = dax_tasks.make("nudge_block", horizon=2)

This module names no task and imports no task module: it holds what was registered.
"""

from __future__ import annotations

import dataclasses
import importlib

import numpy as np

from . import goals
from .checks import check_params, check_spec
from .env import Env, EnvParams
from .spec import TaskSpec, checked_fields
from .wrappers import ObservationMode

#: The :class:`EnvParams` fields ``make`` accepts as overrides of the default params.
PARAM_OVERRIDES = ("lam", "aux_weight")

#: ``make(name, resolution=...)``: ``"default"`` (the task's own resolution, chosen for
#: speed at the accuracy its README states) or ``"reference"`` (the original DaXBench
#: benchmark's particle or vertex count and substeps per step as closely as the scene
#: allows, for speed comparisons at equal work; each task module says how it matches).
RESOLUTIONS = ("default", "reference")


@dataclasses.dataclass(frozen=True)
class TaskEntry:
    """One registered task. ``env``, ``spec`` and ``reference`` are the objects or
    ``"module:attribute"`` strings given to :func:`register`; ``reference`` is ``None``
    for a task without a reference resolution."""

    name: str
    env: type[Env] | str
    spec: TaskSpec | str
    reference: TaskSpec | str | None = None


_REGISTRY: dict[str, TaskEntry] = {}


def _check_target(name: str, what: str, target, kind: type) -> None:
    """``ValueError`` unless ``target`` is a ``"module:attribute"`` string or, for ``kind``
    :class:`Env`, a subclass of it, else an instance of ``kind``."""
    wanted = "an Env subclass" if kind is Env else f"a {kind.__name__}"
    if isinstance(target, str):
        module, sep, attr = target.partition(":")
        ok = bool(module and sep and attr)
    elif kind is Env:
        ok = isinstance(target, type) and issubclass(target, Env)
    else:
        ok = isinstance(target, kind)
    if not ok:
        raise ValueError(f"task {name!r}: {what} must be {wanted} or a 'module:attribute' "
                         f"string, got {type(target).__name__} {target!r}")


def register(name: str, env: type[Env] | str, spec: TaskSpec | str,
             reference: TaskSpec | str | None = None, replace: bool = False) -> None:
    """Register task ``name``: ``env`` its :class:`Env` subclass, ``spec`` its default
    :class:`TaskSpec` (named ``name``), ``reference`` its spec at ``resolution=
    "reference"`` (optional). Each may be a ``"module:attribute"`` string, imported when
    the task is first used. Registering the same entry again does nothing; another entry
    under a registered name raises ``ValueError`` unless ``replace=True``."""
    if not isinstance(name, str) or not name:
        raise ValueError(f"a task name must be a non-empty string, got {name!r}")
    _check_target(name, "env", env, Env)
    _check_target(name, "spec", spec, TaskSpec)
    if reference is not None:
        _check_target(name, "reference", reference, TaskSpec)
    for what, value in (("spec", spec), ("reference", reference)):
        if isinstance(value, TaskSpec) and value.name != name:
            raise ValueError(f"task {name!r}: its {what} is named {value.name!r}")
    entry = TaskEntry(name, env, spec, reference)
    old = _REGISTRY.get(name)
    if old is not None and old != entry and not replace:
        raise ValueError(f"task {name!r} is already registered ({old.env}); pass "
                         f"replace=True to register another task under its name")
    _REGISTRY[name] = entry


def available() -> tuple:
    """The names of the registered tasks, in the order they were registered (the nine
    benchmark tasks first)."""
    return tuple(_REGISTRY)


def _load(target):
    """``target``, or the attribute a ``"module:attribute"`` string names (imported)."""
    if not isinstance(target, str):
        return target
    module, _, attr = target.partition(":")
    return getattr(importlib.import_module(module), attr)


def _entry(name: str) -> TaskEntry:
    entry = _REGISTRY.get(name) if isinstance(name, str) else None
    if entry is None:
        raise ValueError(f"unknown task {name!r}; registered: {', '.join(_REGISTRY)}")
    return entry


def get_spec(name: str, resolution: str = "default") -> TaskSpec:
    """The :class:`TaskSpec` of task ``name`` at ``resolution`` (:data:`RESOLUTIONS`)."""
    if resolution not in RESOLUTIONS:
        raise ValueError(f"unknown resolution {resolution!r}; valid: {', '.join(RESOLUTIONS)}")
    entry = _entry(name)
    if resolution == "default":
        return _load(entry.spec)
    if entry.reference is None:
        raise ValueError(f"task {name!r} has no reference resolution")
    return _load(entry.reference)


def spec_from_json(data: dict) -> TaskSpec:
    """:meth:`TaskSpec.from_json` with the scene class of the registered task named in
    ``data``."""
    scene_type = type(get_spec(data["name"]).scene) if data.get("scene") is not None else None
    return TaskSpec.from_json(data, scene_type)


def env_class(name: str) -> type[Env]:
    """The :class:`Env` subclass that implements task ``name``."""
    cls = _load(_entry(name).env)
    if not (isinstance(cls, type) and issubclass(cls, Env)):
        raise ValueError(f"task {name!r}: its env {cls!r} is not an Env subclass")
    return cls


def check_overrides(name: str, overrides: dict) -> dict:
    """The :func:`make` overrides of task ``name``, checked before anything is built:
    :class:`TaskSpec` fields against the default spec's field types (a ``scene`` field by
    field against the default scene's; :func:`dax_tasks.core.spec.checked_fields`) and ``lam`` /
    ``aux_weight`` as real numbers. ``ValueError`` naming the key and the value (an unknown
    key lists the valid ones); returns the overrides with ints made floats for float
    fields and lists made tuples."""
    default = get_spec(name)
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
    cls = env_class(name)
    base = get_spec(name, resolution)
    overrides = check_overrides(name, overrides)
    param_changes = {k: overrides.pop(k) for k in PARAM_OVERRIDES if k in overrides}
    spec = dataclasses.replace(base, **overrides)
    check_spec(spec, image_size if obs_mode != "state" else None)  # sizes, before building
    env = cls(spec)
    points, provenance = goals.resolve_goal(env, goal_path, use_cache=cache_goal,
                                            allow_mismatch=allow_goal_mismatch)
    env = env.with_goal(points, provenance)
    if param_changes:
        env = env.with_default_params(_checked_params(env, param_changes))
    if obs_mode != "state":
        return ObservationMode(env, obs_mode, image_size)
    return env


def _checked_params(env: Env, changes: dict) -> EnvParams:
    params = env.default_params.replace(**changes)
    check_params(env, params)
    return params
