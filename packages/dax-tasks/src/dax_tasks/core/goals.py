"""Goal particle sets on disk: where they are looked up, how they are stored, how they are
checked (host-side: the pure env only ever sees the goal as ``params.goal``).

A task's goal is fixed per task (and per scene: a finer cloth has more vertices). Some
goals are defined directly (Push-Rope's straight rope); others are the end state of a
canonical scripted motion (a fold), which costs a simulation. :func:`resolve_goal` looks a
goal up, in this order:

1. an explicit ``path`` (``dax_tasks.make(name, goal_path=...)``): a missing, corrupted
   or mismatched file is an error (:class:`GoalFileError`), and so is a goal made for
   another spec or by other code (its provenance's fingerprint is not the spec's; the
   message gives both): pass ``allow_goal_mismatch=True`` to use it anyway, with a
   warning;
2. the cache directory (:func:`cache_dir`: ``$DAX_CACHE_DIR/goals``, default
   ``~/.cache/dax/goals``), file ``<task>-<fingerprint>.npz`` where the fingerprint is the
   spec's own (:meth:`dax_tasks.TaskSpec.fingerprint`: every spec field and the source code
   of dax-tasks and dax-physics); an unreadable cache file is regenerated, with a warning;
3. the env's ``canonical_goal()`` (its canonical motion), whose result is then written to
   the cache (atomically; a read-only cache only costs a warning).

File format: a NumPy ``.npz`` (read with ``allow_pickle=False``, so nothing is unpickled)
holding ``points`` (N, 3) float32 [m] and ``provenance``, a JSON string (task, spec
fingerprint, package versions, creation time, how the goal was made). dax-data's
``dax-data goals`` writes the same files with :func:`save_goal`.
"""

from __future__ import annotations

import datetime
import json
import os
import warnings
import zipfile
import zlib
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import numpy as np

from ..io import atomic_write


class GoalFileError(ValueError):
    """A goal file is missing, unreadable, truncated or does not match the task."""


def cache_dir() -> Path:
    """``$DAX_CACHE_DIR/goals`` if ``DAX_CACHE_DIR`` is set, else ``~/.cache/dax/goals``."""
    root = os.environ.get("DAX_CACHE_DIR")
    base = Path(root) if root else Path.home() / ".cache" / "dax"
    return base / "goals"


def goal_file(spec, directory: str | os.PathLike | None = None) -> Path:
    """The file name the goal of ``spec`` has in ``directory`` (default :func:`cache_dir`)."""
    directory = cache_dir() if directory is None else Path(directory)
    return directory / f"{spec.name}-{spec.fingerprint()}.npz"


def _versions() -> dict:
    out = {}
    for dist in ("dax-physics", "dax-tasks", "jax", "numpy"):
        try:
            out[dist] = version(dist)
        except PackageNotFoundError:
            out[dist] = "unknown"
    return out


def provenance(spec, method: str, **extra) -> dict:
    """A provenance record: task, fingerprint, versions, UTC time, ``method`` and extras."""
    return {"task": spec.name, "fingerprint": spec.fingerprint(), "method": method,
            "created_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(),
            "versions": _versions(), "units": "m", **extra}


def save_goal(path: str | os.PathLike, points, prov: dict) -> Path:
    """Write ``points`` (N, 3) [m] and ``prov`` to ``path`` atomically: a temporary file in
    the same directory, flushed and fsynced, then renamed into place."""
    path = Path(path)
    pts = np.asarray(points, np.float32)
    if pts.ndim != 2 or pts.shape[1] != 3 or not np.all(np.isfinite(pts)):
        raise ValueError(f"a goal must be a finite (N, 3) array, got shape {pts.shape}")
    return atomic_write(path, lambda f: np.savez(f, points=pts,
                                                 provenance=np.asarray(json.dumps(prov))))


def load_goal(path: str | os.PathLike, spec=None, n_points: int | None = None,
              allow_mismatch: bool = False):
    """``(points, provenance)`` from a goal file, checked: a readable ``.npz`` whose
    ``points`` are a finite real (N, 3) array and whose ``provenance`` is a JSON object; N
    equal to ``n_points`` when given; when ``spec`` is given, the task equal to
    ``spec.name`` and the provenance's fingerprint equal to ``spec.fingerprint()`` (a goal
    made for another spec or by other code: refused, or only warned about with
    ``allow_mismatch``). Raises :class:`GoalFileError` naming the file and the problem."""
    path = Path(path)
    pts, text = _read_goal_file(path)
    prov = None
    if text.shape == () and text.dtype.kind == "U":
        try:
            prov = json.loads(str(text))
        except ValueError:
            prov = None
    if not isinstance(prov, dict):
        raise GoalFileError(f"{path}: 'provenance' must be a JSON object (text), got a "
                            f"{text.dtype} array of shape {text.shape}")
    if pts.dtype.kind not in "fiu":  # complex points lost their imaginary part silently
        raise GoalFileError(f"{path}: goal points must be real numbers, got dtype {pts.dtype}")
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise GoalFileError(f"{path}: goal points must have shape (N, 3), got {pts.shape}")
    if not np.all(np.isfinite(pts)):
        raise GoalFileError(f"{path}: goal points contain NaN or inf")
    if n_points is not None and pts.shape[0] != n_points:
        raise GoalFileError(f"{path}: goal has {pts.shape[0]} points but the task's object "
                            f"has {n_points} (made for another scene resolution?)")
    if spec is not None:
        _check_made_for(path, prov, spec, allow_mismatch)
    return pts.astype(np.float32), prov


#: What reading a damaged archive can raise (a flipped bit in a zip header can name an
#: unsupported compression method: ``NotImplementedError``).
_READ_ERRORS = (OSError, ValueError, EOFError, zipfile.BadZipFile, KeyError,
                NotImplementedError, RuntimeError, zlib.error, OverflowError, MemoryError)


def _read_goal_file(path: Path):
    """``(points, provenance text)`` as stored in goal file ``path`` (the text ``"{}"``
    when it has none); :class:`GoalFileError` if it is missing, unreadable, not an
    ``.npz`` archive or holds no ``points``."""
    if not path.is_file():
        raise GoalFileError(f"{path}: goal file not found")
    try:
        data = np.load(path, allow_pickle=False)
    except _READ_ERRORS as err:
        raise GoalFileError(f"{path}: unreadable or truncated goal file ({err})") from None
    if not isinstance(data, np.lib.npyio.NpzFile):  # a bare .npy array
        raise GoalFileError(f"{path}: not a goal file: a single NumPy array, not an .npz "
                            f"archive with 'points' and 'provenance' (write goal files with "
                            f"dax_tasks.core.goals.save_goal)")
    try:
        with data:
            if "points" not in data.files:
                raise GoalFileError(f"{path}: not a goal file (no 'points' array; "
                                    f"has {sorted(data.files)})")
            extra = sorted(set(data.files) - {"points", "provenance"})
            if extra:  # a flipped bit in the archive's directory renames a member
                raise GoalFileError(f"{path}: not a goal file, or a corrupted one: "
                                    f"unexpected member(s) {extra}")
            pts = np.asarray(data["points"])
            text = data["provenance"] if "provenance" in data.files else np.asarray("{}")
    except GoalFileError:
        raise
    except _READ_ERRORS as err:
        raise GoalFileError(f"{path}: unreadable or truncated goal file ({err})") from None
    return pts, text


def _check_made_for(path: Path, prov: dict, spec, allow_mismatch: bool) -> None:
    """:class:`GoalFileError` unless provenance ``prov`` names ``spec``'s task and its
    fingerprint (a mismatched fingerprint only warns with ``allow_mismatch``)."""
    if prov.get("task", spec.name) != spec.name:
        raise GoalFileError(f"{path}: goal of task {prov['task']!r}, not {spec.name!r}")
    made_for, fp = prov.get("fingerprint"), spec.fingerprint()
    if made_for == fp:
        return
    what = (f"made for fingerprint {made_for}" if made_for is not None
            else "its provenance names no fingerprint")
    problem = (f"{path}: goal {what}, not this task's {fp} (another spec of "
               f"{spec.name} or other dax-tasks/dax-physics code)")
    if not allow_mismatch:
        raise GoalFileError(f"{problem}; pass allow_goal_mismatch=True to "
                            f"dax_tasks.make to use it anyway")
    warnings.warn(f"using a mismatched goal: {problem}", stacklevel=4)


def compute_goal(env):
    """The goal from the env's own ``canonical_goal()`` (its canonical motion), as NumPy."""
    pts = np.asarray(env.canonical_goal(), np.float32)
    if pts.ndim != 2 or pts.shape[1] != 3 or not np.all(np.isfinite(pts)):
        raise ValueError(f"{env.spec.name}: canonical_goal() must return a finite (N, 3) "
                         f"array, got shape {pts.shape}")
    return pts


def resolve_goal(env, path=None, use_cache: bool = True, allow_mismatch: bool = False):
    """``(points, provenance)`` of the goal of ``env`` (an :class:`dax_tasks.Env` without
    one yet): from ``path`` (checked against the spec, see :func:`load_goal`), else the
    cache, else computed (and cached). See the module docstring."""
    spec = env.spec
    n_points = env.n_goal_points
    if path is not None:
        return load_goal(path, spec, n_points, allow_mismatch=allow_mismatch)
    cached = goal_file(spec)
    if use_cache and cached.is_file():
        try:
            return load_goal(cached, spec, n_points)
        except GoalFileError as err:
            warnings.warn(f"ignoring a bad cached goal, regenerating it: {err}", stacklevel=3)
    pts = compute_goal(env)
    prov = provenance(spec, f"canonical_goal() of dax_tasks {type(env).__name__}")
    if use_cache:
        try:
            save_goal(cached, pts, prov)
        except OSError as err:
            warnings.warn(f"could not cache the goal of {spec.name} in {cached}: {err}",
                          stacklevel=3)
    return pts, prov
