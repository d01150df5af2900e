"""The static half of a task: :class:`TaskSpec`, and :class:`Box` bounds.

A spec holds only what fixes array shapes and the compiled program: the scene's
resolution and geometry, particle counts, horizon, action box, substeps, the distance's
kind. Changing a field recompiles. Every number that may change without recompiling
(λ, friction, material constants, the goal) is in the environment's params
(:class:`dax_tasks.EnvParams`).

A spec serialises itself (:meth:`TaskSpec.to_json` / :meth:`TaskSpec.from_json`: plain
JSON, no module paths) and fingerprints itself (:meth:`TaskSpec.fingerprint`: the spec
and the source code of dax-tasks and dax-physics its program can reach, so a goal or a
demonstration made by other code is never mistaken for this one's).
"""

from __future__ import annotations

import ast
import dataclasses
import functools
import hashlib
import json
import math
from pathlib import Path
from typing import Any

import jax
import numpy as np

import dax_physics

from . import rewards

ACTION_KINDS = ("push", "pick_place", "velocity")


@dataclasses.dataclass(frozen=True)
class TaskSpec:
    """Static, hashable description of a task (changing it recompiles).

    name: task name.
    horizon: episode length in environment steps; ``done`` once the counter reaches it.
    action_kind: ``push`` / ``pick_place`` (macro actions (x, y, z, x', y', z') [m]) or
        ``velocity`` (low-level velocity commands).
    action_low, action_high: per-dimension bounds (tuples of floats). Actions are clipped to
        them inside ``step`` (the gradient is zero across a clipped dimension).
    substeps: physics substeps per environment step.
    distance: ``"l2"`` (index correspondence) or ``"chamfer"``; see :mod:`dax_tasks.core.rewards`
        (a task may define its own distance instead, e.g. the pour tasks).
    contact_adjustment: for macro actions, snap the push/pick start to the object.
    obs_stride: the ``state`` observation holds every ``obs_stride``-th object particle.
    scene: task-specific static data (a frozen dataclass: resolution, geometry, ...).
    """

    name: str
    horizon: int
    action_kind: str
    action_low: tuple
    action_high: tuple
    substeps: int
    distance: str = "l2"
    contact_adjustment: bool = True
    obs_stride: int = 1
    scene: Any = None

    def __post_init__(self):
        low = tuple(float(v) for v in self.action_low)
        high = tuple(float(v) for v in self.action_high)
        object.__setattr__(self, "action_low", low)
        object.__setattr__(self, "action_high", high)
        if not low or len(low) != len(high):
            raise ValueError(f"action bounds must be non-empty and of equal length, got "
                             f"{len(low)} low and {len(high)} high values")
        if not all(math.isfinite(a) and math.isfinite(b) and a <= b
                   for a, b in zip(low, high, strict=True)):
            raise ValueError(f"action bounds must be finite with low <= high, got {low}, {high}")
        if self.action_kind not in ACTION_KINDS:
            raise ValueError(f"unknown action kind {self.action_kind!r}; "
                             f"valid: {', '.join(ACTION_KINDS)}")
        if self.distance not in rewards.DISTANCES:
            raise ValueError(f"unknown distance {self.distance!r}; "
                             f"valid: {', '.join(rewards.DISTANCES)}")
        for field in ("horizon", "substeps", "obs_stride"):
            value = getattr(self, field)
            if not (isinstance(value, int) and not isinstance(value, bool) and value > 0):
                raise ValueError(f"{field} must be a positive int, got {value!r}")
        if not isinstance(self.contact_adjustment, bool):
            raise ValueError(f"contact_adjustment must be a bool, got "
                             f"{self.contact_adjustment!r}")
        hash(self.scene)  # a scene that is not hashable cannot be a static argument

    @property
    def action_dim(self) -> int:
        return len(self.action_low)

    # ------------------------------------------------------------------ serialisation
    def to_json(self) -> dict:
        """The spec as JSON-compatible data: its fields, the scene's fields under
        ``scene`` and the scene class's name under ``scene_type`` (no module path)."""
        out = {f.name: _jsonable(getattr(self, f.name)) for f in dataclasses.fields(self)}
        if self.scene is not None:
            out["scene_type"] = type(self.scene).__name__
        return out

    @classmethod
    def from_json(cls, data: dict, scene_type: type | None = None) -> TaskSpec:
        """The spec :meth:`to_json` wrote, its scene built as a ``scene_type``
        (:func:`dax_tasks.spec_from_json` finds the class of a registered task).
        ``ValueError`` if the stored ``scene_type`` names another class, a scene comes
        without a class, or a field is unknown."""
        data = dict(data)
        stored_type = data.pop("scene_type", None)
        scene = data.pop("scene", None)
        if scene is not None:
            if scene_type is None:
                raise ValueError(f"spec of task {data.get('name')!r} has a {stored_type} "
                                 f"scene: pass its class (dax_tasks.spec_from_json finds "
                                 f"the class of a registered task)")
            if stored_type is not None and stored_type != scene_type.__name__:
                raise ValueError(f"spec of task {data.get('name')!r} has a {stored_type} "
                                 f"scene, not a {scene_type.__name__}")
            scene = _build(scene_type, scene)
        return _build(cls, {**data, "scene": scene})

    def fingerprint(self) -> str:
        """12 hex digits identifying the task program: every field of the spec (with the
        scene) and the source code of dax-tasks and dax-physics that its program can reach
        (:func:`code_digest`: all of it but the other kinds of tasks' own files)."""
        text = json.dumps(self.to_json(), sort_keys=True) + code_digest(scene_module(self))
        return hashlib.sha256(text.encode()).hexdigest()[:12]


_KINDS = {"bool": bool, "int": int, "float": float, "str": str, "tuple": tuple}


def checked_fields(default, changes: dict, prefix: str = "") -> dict:
    """``changes`` to the fields of the dataclass instance ``default`` (a spec or a scene),
    each checked against its field's type (the annotation, else the default value's type):
    a bool for a bool field, an int (not a bool, not 6.5) for an int field, a finite real
    number for a float field (unless its default is not finite), a string for a string
    field, a list or tuple of as many entries as the default, each checked the same way,
    for a tuple field (any number of entries, each shaped like the default's first, when
    the default is a tuple of tuples: a throw's phases); a dataclass field (a spec's
    scene) takes an instance of the default's class with fields of the right types.
    Returns the changes with ints made floats for float fields and lists made tuples;
    ``ValueError`` naming ``prefix + field`` and the value otherwise, before anything is
    built from them. Unknown fields are refused."""
    fields = {f.name: f for f in dataclasses.fields(default)}
    unknown = sorted(set(changes) - set(fields))
    if unknown:
        raise ValueError(f"unknown {type(default).__name__} field(s) "
                         f"{[prefix + u for u in unknown]}; valid: {sorted(fields)}")
    return {name: _checked(prefix + name, value, getattr(default, name),
                           _KINDS.get(fields[name].type if isinstance(fields[name].type, str)
                                      else getattr(fields[name].type, "__name__", None)))
            for name, value in changes.items()}


def _checked(where: str, value, default, kind=None):
    """``value`` checked against the type ``kind`` (or that of ``default``); see
    :func:`checked_fields`."""
    if kind is None:
        if default is None:
            return value
        if dataclasses.is_dataclass(default) and not isinstance(default, type):
            if type(value) is not type(default):
                raise ValueError(f"{where} must be a {type(default).__name__}, got "
                                 f"{type(value).__name__} {value!r}")
            checked_fields(default, {f.name: getattr(value, f.name)
                                     for f in dataclasses.fields(value)}, where + ".")
            return value
        kind = next((k for k in (bool, int, float, str, tuple) if type(default) is k), None)
        if kind is None:
            return value
    got = f"got {type(value).__name__} {value!r}"
    if kind is bool:
        if not isinstance(value, (bool, np.bool_)):
            raise ValueError(f"{where} must be true or false, {got}")
        return bool(value)
    if kind is int:
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
            raise ValueError(f"{where} must be an integer, {got}")
        return int(value)
    if kind is float:
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer,
                                                                         np.floating)):
            raise ValueError(f"{where} must be a number, {got}")
        number = float(value)
        if not math.isfinite(number) and (not isinstance(default, (int, float))
                                          or math.isfinite(default)):
            raise ValueError(f"{where} must be a finite number, got {number}")
        return number
    if kind is str:
        if not isinstance(value, str):
            raise ValueError(f"{where} must be a string, {got}")
        return value
    if not isinstance(value, (tuple, list)):
        raise ValueError(f"{where} must be a list of {len(default)} entries, {got}"
                         if isinstance(default, tuple) else f"{where} must be a list, {got}")
    if isinstance(default, tuple) and default and all(isinstance(d, tuple) for d in default):
        # a list of records (a throw's phases, an outline's pairs): any number of them,
        # each shaped like the default's first
        return tuple(_checked(f"{where}[{i}]", v, default[0]) for i, v in enumerate(value))
    if isinstance(default, tuple) and default:
        if len(value) != len(default):
            raise ValueError(f"{where} must have {len(default)} entries like its default "
                             f"{list(default)}, got {len(value)}: {list(value)}")
        return tuple(_checked(f"{where}[{i}]", v, d) for i, (v, d) in
                     enumerate(zip(value, default, strict=True)))
    return tuple(value)


def _jsonable(value):
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: _jsonable(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    raise TypeError(f"cannot serialise a {type(value).__name__} spec field: {value!r}")


def _tuples(value):
    """JSON lists back to tuples (spec and scene fields are hashable)."""
    if isinstance(value, list):
        return tuple(_tuples(v) for v in value)
    return value


def _build(cls, fields: dict):
    known = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(fields) - known)
    if unknown:
        raise ValueError(f"unknown {cls.__name__} field(s) {unknown}; valid: {sorted(known)}")
    return cls(**{k: _tuples(v) for k, v in fields.items()})


#: Source files that only some tasks' programs reach (paths from the packages' parent
#: directory, a directory with a trailing ``/``), each with the modules that define those
#: tasks' scene classes; filled by the package that defines the tasks (importing
#: dax_tasks imports :mod:`dax_tasks.tasks`, which names the nine's files here before any
#: fingerprint can be asked for). A task whose scene class is defined in one of the
#: modules named here leaves out of its fingerprint the files named for other modules
#: only, so an edit of the cloth solver does not stale a pour's goals, demonstrations or
#: benchmark rows. Every file not named counts for every task, and a task whose scene is
#: defined anywhere else (a user's task) counts every file.
ONLY_FOR: dict[str, tuple] = {}


def scene_module(spec) -> str | None:
    """The module that defines the class of ``spec``'s scene (``None`` without a scene):
    what selects the files of its fingerprint (:data:`ONLY_FOR`)."""
    return None if spec.scene is None else type(spec.scene).__module__


@functools.cache
def code_digest(module: str | None = None) -> str:
    """SHA-256 of the programs of dax_tasks and dax_physics that the tasks whose scene
    class ``module`` defines can reach (:func:`code_files`): each module's syntax tree
    with its docstrings left out (:func:`_program_text`), so a goal, demonstration or
    benchmark row computed by one version of the code is not taken for another's (a
    changed fold or settling time changes the result without changing the spec), while an
    edit of comments, docstrings or layout changes nothing."""
    h = hashlib.sha256()
    for package, src in code_files(module):
        h.update(src.relative_to(package.parent).as_posix().encode())
        h.update(_program_text(src.read_bytes()).encode())
    return h.hexdigest()


def code_files(module: str | None = None) -> list:
    """``[(package dir, source file)]``: the ``.py`` files of the dax_tasks and dax_physics
    packages (the tasks' modules included) in a fixed order, less those :data:`ONLY_FOR`
    names for other modules when ``module`` (a scene class's module) is one it names;
    what :func:`code_digest` digests. ``module=None``: every file."""
    packages = (Path(__file__).resolve().parent.parent,  # dax_tasks, not only its core
                Path(dax_physics.__file__).resolve().parent)
    known = {m for modules in ONLY_FOR.values() for m in modules}
    left_out = (() if module not in known else
                tuple(path for path, modules in ONLY_FOR.items() if module not in modules))
    return [(package, src) for package in packages for src in sorted(package.rglob("*.py"))
            if not src.relative_to(package.parent).as_posix().startswith(left_out)]


def _program_text(source: bytes) -> str:
    """The syntax tree of ``source`` as text (:func:`_tree_text`: no line numbers, and the
    same text on every Python from 3.10 on) without docstrings (the first statement of a
    module, class or function body when it is a string constant); the source itself if it
    does not parse."""
    try:
        tree = ast.parse(source)
    except SyntaxError:
        return source.decode("utf-8", "replace")
    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        if (isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef))
                and body and isinstance(body[0], ast.Expr)
                and isinstance(body[0].value, ast.Constant)
                and isinstance(body[0].value.value, str)):
            node.body = body[1:] or [ast.Pass()]
    return _tree_text(tree)


def _tree_text(node) -> str:
    """``node`` as ``Name(field=value, ...)``, recursively, leaving out every field that is
    ``None``, an empty list or absent. ``ast.dump`` differs between Python versions on the
    same source (3.12 adds ``type_params=[]`` to every function and class, 3.13 drops empty
    fields by default), which made one checkout's fingerprints depend on the interpreter;
    this text does not, as long as the node and field names stay."""
    if isinstance(node, ast.AST):
        fields = ", ".join(f"{name}={_tree_text(value)}" for name in node._fields
                           if (value := getattr(node, name, None)) is not None
                           and not (isinstance(value, list) and not value))
        return f"{type(node).__name__}({fields})"
    if isinstance(node, list):
        return "[" + ", ".join(_tree_text(x) for x in node) + "]"
    return repr(node)


@dataclasses.dataclass(frozen=True)
class Box:
    """Bounds of an action or observation array (a minimal stand-in for Gymnasium's Box,
    so the core does not import gymnasium)."""

    low: np.ndarray
    high: np.ndarray
    shape: tuple
    dtype: Any = np.float32

    def sample(self, key):
        """A uniform sample (jax array); infinite bounds are replaced by [-1, 1]."""
        low = np.where(np.isfinite(self.low), self.low, -1.0)
        high = np.where(np.isfinite(self.high), self.high, 1.0)
        return jax.random.uniform(key, self.shape, np.float32, low, high).astype(self.dtype)

    def contains(self, x) -> bool:
        x = np.asarray(x)
        return (x.shape == self.shape and bool(np.all(np.isfinite(x)))
                and bool(np.all((x >= self.low) & (x <= self.high))))

    @staticmethod
    def unbounded(shape, dtype=np.float32) -> Box:
        return Box(np.full(shape, -np.inf, np.float32), np.full(shape, np.inf, np.float32),
                   tuple(shape), dtype)
