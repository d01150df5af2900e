"""Goal particle sets on disk: where they are looked up, how they are stored, how they are
checked.

A task's goal is fixed per task (and per scene: a finer cloth has more vertices). Some
goals are defined directly (Push-Rope's straight rope); others are the end state of a
canonical scripted motion (a fold), which costs a simulation. :func:`resolve_goal` looks a
goal up, in this order:

1. an explicit ``path`` (``dax_tasks.make(name, goal_path=...)``): used as it is; a
   missing, corrupted or mismatched file is an error (:class:`GoalFileError`);
2. the cache directory (:func:`cache_dir`: ``$DAX_CACHE_DIR/goals``, default
   ``~/.cache/dax/goals``), file ``<task>-<fingerprint>.npz`` where the fingerprint hashes
   the parts of the spec the goal depends on and the source code of dax-tasks and
   dax-physics (:func:`fingerprint`); an unreadable cache file is regenerated, with a
   warning;
3. the task's own ``goal(spec)`` (its canonical motion), whose result is then written to
   the cache (atomically; a read-only cache only costs a warning).

File format: a NumPy ``.npz`` (read with ``allow_pickle=False``, so nothing is unpickled)
holding ``points`` (N, 3) float32 [m] and ``provenance``, a JSON string (task, spec
fingerprint, package versions, creation time, how the goal was made). dax-data's
``dax-data goals`` writes the same files with :func:`save_goal`.
"""

from __future__ import annotations

import dataclasses
import datetime
import functools
import hashlib
import json
import os
import tempfile
import warnings
import zipfile
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import numpy as np

#: Spec fields a goal never depends on (they change rewards and observations only).
_IGNORED_FIELDS = ("lam", "aux_reward", "obs_stride", "horizon")


class GoalFileError(ValueError):
    """A goal file is missing, unreadable, truncated or does not match the task."""


def cache_dir() -> Path:
    """``$DAX_CACHE_DIR/goals`` if ``DAX_CACHE_DIR`` is set, else ``~/.cache/dax/goals``."""
    root = os.environ.get("DAX_CACHE_DIR")
    base = Path(root) if root else Path.home() / ".cache" / "dax"
    return base / "goals"


@functools.lru_cache(maxsize=1)
def code_digest() -> str:
    """SHA-256 of the Python sources of dax_tasks and dax_physics: a goal computed by one
    version of the code is not reused by another (a changed fold or settling time changes
    the goal without changing the spec)."""
    import dax_physics

    h = hashlib.sha256()
    for package in (Path(__file__).parent, Path(dax_physics.__file__).parent):
        for src in sorted(package.rglob("*.py")):
            h.update(src.relative_to(package.parent).as_posix().encode())
            h.update(src.read_bytes())
    return h.hexdigest()


def fingerprint(spec) -> str:
    """12 hex digits identifying everything a goal can depend on: the fields of ``spec``
    (the scene, the substeps, the action kind and bounds, contact adjustment) and the
    simulator and task code (:func:`code_digest`)."""
    fields = {f.name: getattr(spec, f.name) for f in dataclasses.fields(spec)
              if f.name not in _IGNORED_FIELDS}
    text = repr(sorted(fields.items())) + code_digest()
    return hashlib.sha256(text.encode()).hexdigest()[:12]


def goal_file(spec, directory: str | os.PathLike | None = None) -> Path:
    """The file name the goal of ``spec`` has in ``directory`` (default :func:`cache_dir`)."""
    directory = cache_dir() if directory is None else Path(directory)
    return directory / f"{spec.name}-{fingerprint(spec)}.npz"


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
    return {"task": spec.name, "fingerprint": fingerprint(spec), "method": method,
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


def atomic_write(path: str | os.PathLike, write) -> Path:
    """Call ``write(f)`` on a binary file that becomes ``path`` only once complete: a
    temporary file in the same directory, flushed and fsynced, then renamed into place
    (removed if ``write`` fails). Creates the directory if needed."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def load_goal(path: str | os.PathLike, spec=None, n_points: int | None = None):
    """``(points, provenance)`` from a goal file, checked: readable, ``points`` a finite
    (N, 3) array, N equal to ``n_points`` when given and the task equal to ``spec.name``
    when given. Raises :class:`GoalFileError` naming the file and the problem."""
    path = Path(path)
    if not path.is_file():
        raise GoalFileError(f"{path}: goal file not found")
    try:
        with np.load(path, allow_pickle=False) as data:
            if "points" not in data.files:
                raise GoalFileError(f"{path}: not a goal file (no 'points' array; "
                                    f"has {sorted(data.files)})")
            pts = np.asarray(data["points"])
            prov = json.loads(str(data["provenance"])) if "provenance" in data.files else {}
    except GoalFileError:
        raise
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, KeyError) as err:
        raise GoalFileError(f"{path}: unreadable or truncated goal file ({err})") from None
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise GoalFileError(f"{path}: goal points must have shape (N, 3), got {pts.shape}")
    if not np.all(np.isfinite(pts)):
        raise GoalFileError(f"{path}: goal points contain NaN or inf")
    if n_points is not None and pts.shape[0] != n_points:
        raise GoalFileError(f"{path}: goal has {pts.shape[0]} points but the task's object "
                            f"has {n_points} (made for another scene resolution?)")
    if spec is not None and prov.get("task", spec.name) != spec.name:
        raise GoalFileError(f"{path}: goal of task {prov['task']!r}, not {spec.name!r}")
    return pts.astype(np.float32), prov


def compute_goal(defn, spec):
    """The goal from the task's own ``goal(spec)`` (its canonical motion), as NumPy."""
    pts = np.asarray(defn.goal(spec), np.float32)
    if pts.ndim != 2 or pts.shape[1] != 3 or not np.all(np.isfinite(pts)):
        raise ValueError(f"{spec.name}: goal(spec) must return a finite (N, 3) array, "
                         f"got shape {pts.shape}")
    return pts


def resolve_goal(defn, spec, path=None, use_cache: bool = True, n_points: int | None = None):
    """``(points, provenance)`` of the goal of ``spec``: from ``path``, else the cache, else
    computed (and cached). See the module docstring."""
    if path is not None:
        return load_goal(path, spec, n_points)
    cached = goal_file(spec)
    if use_cache and cached.is_file():
        try:
            return load_goal(cached, spec, n_points)
        except GoalFileError as err:
            warnings.warn(f"ignoring a bad cached goal, regenerating it: {err}", stacklevel=3)
    pts = compute_goal(defn, spec)
    prov = provenance(spec, "goal(spec) of dax_tasks." + spec.name)
    if use_cache:
        try:
            save_goal(cached, pts, prov)
        except OSError as err:
            warnings.warn(f"could not cache the goal of {spec.name} in {cached}: {err}",
                          stacklevel=3)
    return pts, prov
