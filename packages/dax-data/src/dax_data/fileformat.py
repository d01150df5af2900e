"""The demonstration file format (HDF5, h5py): writing, reading and checking.

The layout is documented in the package README ("File format"). In short::

    /                      file attributes: format, format_version, task, fingerprint,
                           versions, spec, params, images, units, scene_doc, generator,
                           created_utc (version 1 files have no ``params``, version 1
                           and 2 files no ``images``)
    /goal                  (N, 3) float32 [m], attribute ``provenance`` (JSON)
                           (chunked and checksummed like every dataset since version 4)
    /episodes/000000       group per episode, attributes seed, policy, length, score
        actions            (T, A) float32
        observations       (T + 1, O) float32   (the reset observation first)
        rewards            (T,) float32
        r_gt               (T,) float32
        points             (K, N, 3) float32 [m] object points at steps ``point_steps``
        point_steps        (K,) int32           0, k, 2k, ... and always T
        end_effector       (T + 1, 3) float32 [m]
        height             (T + 1, S, S) float32 [m]  top-down height maps  } if the
        rgb                (T + 1, S, S, 3) uint8     top-down pictures     } images
                                                                            attribute
                                                                            lists them

Every write goes to a temporary file in the same directory that is flushed, fsynced and
renamed into place (:func:`append_episode`, with :func:`dax_tasks.io.atomic_path`, the one
atomic-write helper of DaX), so the file on disk is always complete: an interrupted run
loses at most the episode it was recording. Nothing is pickled: metadata
is JSON text in string attributes, data are plain numeric datasets (chunked, gzip with the
shuffle filter, and a Fletcher-32 checksum per chunk so a corrupted chunk is detected).
Every dataset of a version 4 file carries that checksum, ``/goal`` included (versions 1 to 3
stored ``/goal`` contiguous, without one: such files open with an
:class:`UncheckedDataWarning`). HDF5's own structural metadata (object headers, chunk
indexes) carries checksums in the 1.10 formats used here, but attribute *values* need not
(text attributes live in HDF5's global heap, which has none): a version 4 file therefore
also stores ``checksum``, a SHA-256 over every attribute of the file
(:func:`attrs_digest`), updated by every write and checked on open.

Checksums catch bit rot, not edits: rewriting a dataset with h5py recomputes its chunks'
Fletcher-32 sums. Since version 5 every dataset therefore carries ``digest``, a SHA-256
of its dtype, shape and values (:func:`array_digest`), and every episode group a
``digest`` over its datasets' digests and its attributes (:func:`episode_digest`); both
are attributes, so the file's ``checksum`` covers them. Reading checks them (the goal on
:attr:`DemoFile.goal`, an episode's datasets on :meth:`DemoFile.episode`; ``verify=False``
skips it) and so does :meth:`DemoFile.verify`, with the checks a value-level edit cannot
hide from: finite values, actions inside the spec's action box, ``point_steps``, the score
the last ``r_gt``, ``r_gt`` in (0, 1]. What needs the task itself (the goal equal to the
task's, ``r_gt`` recomputed from the stored object points) is in
:mod:`dax_data.semantics`. A version 5 file also records the float ``precision`` its
episodes ran in, and holds nothing the layout does not name.

Every failure to read a file (HDF5's own errors included) is a :class:`DataFileError`
naming the file.
"""

from __future__ import annotations

import dataclasses
import datetime
import functools
import hashlib
import inspect
import json
import os
import warnings
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any

import h5py
import numpy as np

#: Identifies a dax-data demonstration file (the ``format`` attribute).
FORMAT_NAME = "dax-data/demonstrations"
#: The layout this version writes; it reads versions 1 up to it and refuses larger ones.
#: Version 2: ``spec`` is the spec's own JSON (:meth:`dax_tasks.TaskSpec.to_json`: the
#: scene's class by name, no module path), ``fingerprint`` the spec's own, and ``params``
#: holds the numbers the episodes ran with (λ, the auxiliary weight, the physics numbers),
#: which version 1 kept in the spec. Version 1 files are still read, validated and
#: exported, but not extended (:func:`check_extendable`).
#: Version 3: the ``images`` attribute (the image modes stored, their size and the camera)
#: and the optional per-episode datasets ``height`` and ``rgb`` (:data:`IMAGE_DATASETS`).
#: Version 4: ``/goal`` is chunked, compressed and checksummed like the episode datasets
#: (every dataset of the file carries a Fletcher-32 checksum; :meth:`DemoFile.verify`
#: refuses a version 4 file with a dataset that does not).
#: Version 5: a content ``digest`` on every dataset and every episode group, the
#: ``precision`` attribute, and no object the layout does not name.
FORMAT_VERSION = 5
#: The first version whose every dataset and every attribute is checksummed.
CHECKSUMMED_SINCE = 4
#: The first version whose datasets and episodes carry content digests.
DIGESTED_SINCE = 5
#: The file attribute holding :func:`attrs_digest` (version 4).
CHECKSUM_ATTR = "checksum"
#: The attribute of a dataset (:func:`array_digest`) or episode group
#: (:func:`episode_digest`) holding its content digest (version 5).
DIGEST_ATTR = "digest"
#: Float precisions a file records (the physics state's float type while recording).
PRECISIONS = ("float32", "float64")

#: Per-episode datasets: name -> (dtype, dimensions) where the dimensions name the sizes
#: checked against each other: T steps, A action dim, O observation dim, K point frames,
#: N object points; integers are fixed sizes.
EPISODE_DATASETS = {
    "actions": ("float32", ("T", "A")),
    "observations": ("float32", ("T+1", "O")),
    "rewards": ("float32", ("T",)),
    "r_gt": ("float32", ("T",)),
    "points": ("float32", ("K", "N", 3)),
    "point_steps": ("int32", ("K",)),
    "end_effector": ("float32", ("T+1", 3)),
}
#: Optional per-episode image datasets (the observation modes of
#: :class:`dax_tasks.core.wrappers.ObservationMode` a file holds; ``S`` the image size): one
#: picture per observation, the reset one first, rendered by the camera in the ``images``
#: attribute.
IMAGE_DATASETS = {
    "height": ("float32", ("T+1", "S", "S")),
    "rgb": ("uint8", ("T+1", "S", "S", 3)),
}
#: Observation modes a file can hold: the task's ``state`` observation (always) and images.
OBS_MODES = ("state", *IMAGE_DATASETS)
EPISODE_ATTRS = ("seed", "policy", "length", "score")
FILE_ATTRS = ("format", "format_version", "task", "fingerprint", "versions", "spec", "units",
              "scene_doc", "generator", "created_utc")
#: Attributes a file of a given version has beyond :data:`FILE_ATTRS`.
VERSION_ATTRS = {1: (), 2: ("params",), 3: ("params", "images"),
                 4: ("params", "images", CHECKSUM_ATTR),
                 5: ("params", "images", CHECKSUM_ATTR, "precision")}
JSON_ATTRS = ("versions", "spec", "params", "images", "units", "generator")

#: Units of the :class:`dax_tasks.TaskSpec` fields and of the datasets (the ``units``
#: attribute). Scene fields are SI; their units are in the scene class docstring, stored
#: as the ``scene_doc`` attribute.
UNITS = {
    "spec.action_low": "m for push / pick_place actions (x, y, z, x', y', z'); "
                       "m/s for velocity actions",
    "spec.action_high": "as spec.action_low",
    "params.lam": "1/m",
    "params.aux_weight": "1",
    "params.physics": "SI (kg/m^3 or kg/m^2, Pa or N/m, Pa s or N s/m; friction 1)",
    "spec.horizon": "environment steps",
    "spec.substeps": "physics substeps per environment step",
    "spec.scene": "SI (m, kg, s, N, Pa, rad); see the scene_doc attribute",
    "goal": "m",
    "actions": "as spec.action_low",
    "observations": "m (object points then end-effector position, unless the task "
                    "defines its own observe)",
    "rewards": "1 (r_gt + params.aux_weight * r_aux)",
    "r_gt": "1 (exp(-lam * D))",
    "points": "m",
    "end_effector": "m",
    "height": "m above the camera's base height images.window[4]",
    "rgb": "0-255 (sRGB)",
    "score": "1 (r_gt after the last step)",
}


class DataFileError(ValueError):
    """A demonstration file is missing, unreadable, truncated, of another format or a newer
    format version, or does not match what was asked. The message names the file."""


class UncheckedDataWarning(UserWarning):
    """A demonstration file of a format version before 5: its datasets carry no content
    digest, so an edit goes unnoticed; before version 4 its ``/goal`` and attributes carry
    no checksum either, so their corruption goes unnoticed too (the message names the
    file)."""


@dataclasses.dataclass(frozen=True)
class Episode:
    """One recorded episode (NumPy arrays; see the module docstring for shapes)."""

    index: int
    seed: int
    policy: str
    score: float
    actions: Any
    observations: Any
    rewards: Any
    r_gt: Any
    points: Any
    point_steps: Any
    end_effector: Any
    #: (T + 1, S, S) height maps [m] and (T + 1, S, S, 3) uint8 pictures, or ``None`` when
    #: the file holds no such images
    height: Any = None
    rgb: Any = None

    @property
    def length(self) -> int:
        return int(self.actions.shape[0])


def package_versions() -> dict:
    """Versions of the packages a file depends on."""
    out = {}
    for dist in ("dax-data", "dax-tasks", "dax-physics", "jax", "numpy", "h5py"):
        try:
            out[dist] = version(dist)
        except PackageNotFoundError:
            out[dist] = "unknown"
    return out


def _jsonable(value):
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: _jsonable(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    return repr(value)


def _json_number(x):
    """A float as JSON allows it: non-finite values (a non-plastic material's yield stress
    is inf) become the strings ``"inf"``, ``"-inf"`` and ``"nan"``."""
    x = float(x)
    return x if np.isfinite(x) else str(x)


def params_to_json(params) -> dict:
    """The numbers of a :class:`dax_tasks.EnvParams` but the goal (stored as ``/goal``):
    ``lam``, ``aux_weight`` and the physics numbers by field name, as (nested) JSON lists
    of numbers (see :func:`_json_number`)."""
    physics = params.physics
    fields = ({f.name: getattr(physics, f.name) for f in dataclasses.fields(physics)}
              if dataclasses.is_dataclass(physics) else {"value": physics})

    def numbers(a):
        a = np.asarray(a, np.float64)
        return _json_number(a) if a.ndim == 0 else [numbers(v) for v in a]

    return {"lam": _json_number(params.lam), "aux_weight": _json_number(params.aux_weight),
            "physics_type": type(physics).__name__,
            "physics": {k: numbers(v) for k, v in fields.items() if v is not None}}


def images_meta(modes=(), size: int | None = None, camera=None) -> dict:
    """The ``images`` attribute: the image modes stored (of :data:`IMAGE_DATASETS`), their
    size in pixels, and the camera that rendered them (``window`` ``(x0, x1, y0, y1, z0)``
    [m] and the points' splat ``radius`` [m], a :class:`dax_tasks.viz.Camera`)."""
    modes = [m for m in IMAGE_DATASETS if m in modes]
    if not modes:
        return {"modes": []}
    return {"modes": modes, "size": int(size), "window": [float(v) for v in camera.window],
            "radius": float(camera.radius)}


def current_precision() -> str:
    """The float type a recording runs in now: ``"float64"`` when JAX's
    ``jax_enable_x64`` is on (the tasks' physics then runs in float64), else
    ``"float32"``. The stored datasets are float32 either way."""
    import jax

    return "float64" if jax.config.jax_enable_x64 else "float32"


def header(env, generator: dict, images: dict | None = None) -> dict:
    """The file attributes of a new file for ``env`` (a :class:`dax_tasks.Env` built by
    ``dax_tasks.make``); ``images`` from :func:`images_meta` (default: none)."""
    spec = env.spec
    scene_doc = inspect.getdoc(type(spec.scene)) if spec.scene is not None else ""
    return {
        "format": FORMAT_NAME,
        "format_version": FORMAT_VERSION,
        "task": spec.name,
        "fingerprint": spec.fingerprint(),
        "versions": package_versions(),
        "spec": spec.to_json(),
        "params": params_to_json(env.default_params),
        "images": images if images is not None else images_meta(),
        "units": UNITS,
        "scene_doc": scene_doc or "",
        "generator": generator,
        "created_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(),
        "precision": current_precision(),
    }


def spec_from_meta(meta: dict):
    """The :class:`dax_tasks.TaskSpec` a file was recorded with. Version 1 files stored
    ``lam``/``aux_reward`` in the spec and the scene's class by module path, and their
    scenes had fields that later versions keep in the params: those are dropped (they do
    not change the scene's geometry)."""
    import dax_tasks

    data = dict(meta["spec"])
    if meta["format_version"] == 1:
        for key in ("lam", "aux_reward", "scene_class"):
            data.pop(key, None)
        scene_type = type(dax_tasks.get_spec(meta["task"]).scene)
        names = {f.name for f in dataclasses.fields(scene_type)}
        data["scene"] = {k: v for k, v in (data.get("scene") or {}).items() if k in names}
        return dax_tasks.TaskSpec.from_json(data, scene_type)
    return dax_tasks.spec_from_json(data)


def check_extendable(path, meta: dict) -> None:
    """Refuse to add episodes to a file of an older format version, or recorded in another
    float precision than the current one (:func:`current_precision`)."""
    if meta["format_version"] != FORMAT_VERSION:
        raise DataFileError(
            f"{path}: written in format version {meta['format_version']} by an older "
            f"dax-data; it can be read, validated and exported, but new episodes go to a new "
            f"file (format version {FORMAT_VERSION}): choose another --out")
    now = current_precision()
    if meta["precision"] != now:
        raise DataFileError(
            f"{path}: its episodes ran in {meta['precision']}, this process runs in {now} "
            f"(JAX_ENABLE_X64={'1' if now == 'float64' else '0'}); resume it in "
            f"{meta['precision']}, or choose another --out")


# ---------------------------------------------------------------------- writing
#: HDF5 1.10 object formats (readable by HDF5 >= 1.10): compact chunk indexes, so a short
#: episode's many small datasets take less room than with the 1.8-compatible default.
LIBVER = ("v110", "v110")
_COMPRESSION = {"compression": "gzip", "compression_opts": 4, "shuffle": True,
                "fletcher32": True}


def _attr_value(value):
    """An attribute's value as JSON-able Python (for :func:`attrs_digest`)."""
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, np.ndarray):
        return [_attr_value(v) for v in value.tolist()] if value.ndim else \
            _attr_value(value.item())
    if isinstance(value, bytes):
        return value.decode(errors="replace")
    return value if isinstance(value, (str, int, float, bool, list)) or value is None \
        else repr(value)


def attrs_digest(f: h5py.File) -> str:
    """``"sha256:<hex>"`` over every attribute of the file (path, name and value of each,
    in name order), but the checksum attribute itself: what the ``checksum`` attribute of a
    version 4 file holds."""
    names = []
    f.visit(names.append)
    h = hashlib.sha256()
    for path in ["", *sorted(names)]:
        obj = f[path] if path else f
        for key in sorted(obj.attrs):
            if not path and key == CHECKSUM_ATTR:
                continue
            h.update(json.dumps(["/" + path, key, _attr_value(obj.attrs[key])]).encode())
            h.update(b"\n")
    return "sha256:" + h.hexdigest()


def array_digest(data) -> str:
    """``"sha256:<hex>"`` of an array's dtype, shape and C-order bytes: the ``digest``
    attribute of a version 5 dataset."""
    a = np.ascontiguousarray(data)
    h = hashlib.sha256(f"{a.dtype.str}|{list(a.shape)}|".encode())
    h.update(a.tobytes())
    return "sha256:" + h.hexdigest()


def episode_digest(digests: dict, attrs: dict) -> str:
    """``"sha256:<hex>"`` over an episode's dataset digests (name -> :func:`array_digest`)
    and its other attributes (``seed``, ``policy``, ``length``, ``score``): the ``digest``
    attribute of a version 5 episode group."""
    doc = {"datasets": dict(sorted(digests.items())),
           "attrs": {k: _attr_value(attrs[k]) for k in sorted(attrs) if k != DIGEST_ATTR}}
    return "sha256:" + hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()


def seal(f: h5py.File) -> None:
    """Store :func:`attrs_digest` in a version 4 file opened for writing (after any change
    to an attribute, an episode or the goal)."""
    if int(f.attrs.get("format_version", 0)) >= CHECKSUMMED_SINCE:
        f.attrs[CHECKSUM_ATTR] = attrs_digest(f)


def _write_array(group: h5py.Group, name: str, data, chunks=True) -> str:
    """Write dataset ``name`` (chunked, compressed, checksummed unless empty) with its
    ``digest`` attribute; returns the digest."""
    data = np.ascontiguousarray(data)
    if data.size == 0:
        ds = group.create_dataset(name, data=data)
    else:
        ds = group.create_dataset(name, data=data, chunks=chunks, **_COMPRESSION)
    ds.attrs[DIGEST_ATTR] = digest = array_digest(data)
    return digest


def stale_temporaries(path: str | os.PathLike) -> list:
    """Temporary files a killed writer of ``path`` left behind."""
    from dax_tasks.io import temporaries  # imported here: reading files needs no JAX

    return temporaries(path)


def create(path: str | os.PathLike, attrs: dict, goal, goal_provenance: dict) -> Path:
    """Write a new file with ``attrs`` (see :func:`header`), the goal and no episodes,
    atomically (replacing any file at ``path``)."""
    path = Path(path)
    from dax_tasks.io import atomic_path  # imported here: reading files needs no JAX

    with (atomic_path(path, copy_existing=False) as tmp,
          h5py.File(tmp, "w", libver=LIBVER) as f):
        for key, value in attrs.items():
            f.attrs[key] = json.dumps(value, allow_nan=False) if key in JSON_ATTRS else value
        _write_array(f, "goal", np.asarray(goal, np.float32))  # checksummed (version 4)
        ds = f["goal"]
        ds.attrs["provenance"] = json.dumps(_jsonable(goal_provenance))
        ds.attrs["units"] = "m"
        f.create_group("episodes")
        seal(f)
    return path


def episode_name(index: int) -> str:
    return f"{index:06d}"


def append_episode(path: str | os.PathLike, index: int, seed: int, policy: str,
                   arrays: dict) -> None:
    """Add episode ``index`` to the file at ``path``: copy the file to a temporary file,
    add the group there, fsync, rename over ``path``. ``arrays`` holds the datasets of
    :data:`EPISODE_DATASETS` and those of :data:`IMAGE_DATASETS` the file's ``images``
    attribute lists (one chunk per picture)."""
    path = Path(path)
    missing = sorted(set(EPISODE_DATASETS) - set(arrays))
    if missing:
        raise ValueError(f"episode arrays missing: {missing}")
    r_gt = np.asarray(arrays["r_gt"], np.float32)
    from dax_tasks.io import atomic_path

    with (atomic_path(path, copy_existing=True) as tmp,
          h5py.File(tmp, "a", libver=LIBVER) as f):
        name = episode_name(index)
        if name in f["episodes"]:
            raise DataFileError(f"{path}: episode {index} is already in the file")
        g = f["episodes"].create_group(name)
        g.attrs["seed"] = int(seed)
        g.attrs["policy"] = str(policy)
        g.attrs["length"] = int(r_gt.shape[0])
        g.attrs["score"] = float(r_gt[-1]) if r_gt.size else float("nan")
        digests = {key: _write_array(g, key, np.asarray(arrays[key], dtype))
                   for key, (dtype, _) in EPISODE_DATASETS.items()}
        modes = json.loads(_text(f.attrs["images"]))["modes"] if "images" in f.attrs else []
        missing = sorted(set(modes) - set(arrays))
        if missing:
            raise ValueError(f"episode arrays missing the file's image datasets {missing}")
        for key in modes:
            data = np.asarray(arrays[key], IMAGE_DATASETS[key][0])
            digests[key] = _write_array(g, key, data, chunks=(1, *data.shape[1:]))
        g.attrs[DIGEST_ATTR] = episode_digest(digests, dict(g.attrs))
        seal(f)


# ---------------------------------------------------------------------- reading
#: What reading a damaged or edited file can raise beneath the schema checks: HDF5's own
#: errors (``OSError``; ``RuntimeError`` such as "Object visitation failed"; ``KeyError``
#: for a member that vanished), decoding errors (``ValueError``, ``TypeError``) and absurd
#: sizes (``OverflowError``, ``MemoryError``). :class:`DemoFile` turns each into a
#: :class:`DataFileError` naming the file.
READ_ERRORS = (OSError, RuntimeError, LookupError, ValueError, TypeError, OverflowError,
               MemoryError)


def _named(what: str):
    """Decorator of :class:`DemoFile` methods: a :data:`READ_ERRORS` error becomes a
    :class:`DataFileError` naming the file and ``what`` was being read."""
    def wrap(fn):
        @functools.wraps(fn)
        def method(self, *args, **kwargs):
            try:
                return fn(self, *args, **kwargs)
            except DataFileError:
                raise
            except READ_ERRORS as err:
                raise DataFileError(f"{self.path}: {what} unreadable, truncated or corrupted "
                                    f"({_short(err)})") from None
        return method
    return wrap


class DemoFile:
    """A demonstration file opened for reading; the schema is checked on open.

    ``meta``: the file attributes (JSON ones decoded); ``goal``: (N, 3) [m];
    ``goal_provenance``: dict; ``len(f)``: the number of episodes; ``f[k]``: episode ``k``
    as an :class:`Episode` of NumPy arrays (``as_jax=True`` in :meth:`episode` gives JAX
    arrays). Use as a context manager or call :meth:`close`.

    ``verify`` (default true): check the content digests of what is read (version 5
    files: the goal on :attr:`goal`, an episode's datasets and the episode's digest on
    :meth:`episode`), so an edited value is refused; ``False`` skips it. Files of
    versions before 5 open with an :class:`UncheckedDataWarning` naming what they cannot
    check. Every error is a :class:`DataFileError` naming the file.
    """

    def __init__(self, path: str | os.PathLike, verify: bool = True):
        self.path = Path(path)
        self.check_digests = bool(verify)
        if not self.path.is_file():
            raise DataFileError(f"{self.path}: " + ("not a file" if self.path.exists()
                                                    else "file not found"))
        try:
            self._f = h5py.File(self.path, "r")
        except READ_ERRORS as err:
            raise DataFileError(f"{self.path}: not a readable HDF5 file, truncated or "
                                f"corrupted ({_short(err)})") from None
        try:
            self._check_schema()
        except DataFileError:
            self.close()
            raise
        except READ_ERRORS as err:
            self.close()
            raise DataFileError(f"{self.path}: unreadable metadata, truncated or corrupted "
                                f"({_short(err)})") from None

    # -- schema
    def _fail(self, problem: str):
        raise DataFileError(f"{self.path}: {problem}")

    def _check_schema(self) -> None:
        f = self._f
        ver = self._check_version()
        self.meta = meta = self._read_meta(ver)
        self._warn_unchecked(ver)
        self.image_modes = tuple(self._check_images(meta["images"]))
        n_goal = self._check_goal()
        names = self._episode_names()
        dims = {"A": None, "O": None, "N": None}
        for name in names:
            dims = self._check_episode(name, dims, meta["images"].get("size"), n_goal)
        self._names = names
        if ver >= DIGESTED_SINCE:
            self._check_members()
            if meta["precision"] not in PRECISIONS:
                self._fail(f"file attribute 'precision' must be one of {list(PRECISIONS)}, "
                           f"got {meta['precision']!r}")
        if ver >= CHECKSUMMED_SINCE:
            stored, computed = meta[CHECKSUM_ATTR], attrs_digest(f)
            if stored != computed:
                self._fail(f"metadata checksum mismatch: an attribute was changed or "
                           f"corrupted (stored {stored[:19]}..., computed {computed[:19]}...)")

    def _warn_unchecked(self, ver: int) -> None:
        """The :class:`UncheckedDataWarning` of a file older than version 5."""
        if ver < CHECKSUMMED_SINCE:
            warnings.warn(f"{self.path}: format version {ver}: /goal and the attributes "
                          f"carry no checksum, so their corruption goes unnoticed (the goal is "
                          f"unchecked), and no dataset carries a content digest, so an edit "
                          f"goes unnoticed; record the file again with this dax-data to "
                          f"check it", UncheckedDataWarning, stacklevel=4)
        elif ver < DIGESTED_SINCE:
            warnings.warn(f"{self.path}: format version {ver}: no dataset carries a content "
                          f"digest, so an edit that rewrites a dataset (its chunk checksums "
                          f"recomputed) goes unnoticed; record the file again with this "
                          f"dax-data to check it", UncheckedDataWarning, stacklevel=4)

    def _check_version(self) -> int:
        """The file's format version, checked: a dax-data file of a version this reads."""
        f = self._f
        fmt = f.attrs.get("format")
        if _text(fmt) != FORMAT_NAME:
            self._fail(f"not a dax-data demonstration file (format attribute {fmt!r})")
        ver = f.attrs.get("format_version")
        if ver is None or np.shape(ver) != () or \
                not np.issubdtype(np.asarray(ver).dtype, np.integer):
            self._fail(f"missing or non-integer format_version ({ver!r})")
        ver = int(ver)
        if ver > FORMAT_VERSION:
            self._fail(f"format version {ver} is newer than this dax-data reads "
                       f"(up to {FORMAT_VERSION}); upgrade dax-data")
        if ver not in VERSION_ATTRS:
            self._fail(f"invalid format version {ver}")
        return ver

    def _read_meta(self, ver: int) -> dict:
        """The file attributes of version ``ver``, JSON ones parsed; every one must be
        there."""
        meta = {}
        for key in FILE_ATTRS + VERSION_ATTRS[ver]:
            if key not in self._f.attrs:
                self._fail(f"missing file attribute {key!r}")
            value = self._f.attrs[key]
            if key in JSON_ATTRS:
                try:
                    value = json.loads(_text(value))
                except (TypeError, ValueError):
                    self._fail(f"file attribute {key!r} is not valid JSON")
                if not isinstance(value, dict):
                    self._fail(f"file attribute {key!r} must be a JSON object, got "
                               f"{type(value).__name__}")
            elif key == "format_version":
                value = int(value)
            else:
                value = _text(value)
            meta[key] = value
        meta.setdefault("images", images_meta())  # versions 1 and 2 hold no images
        return meta

    def _check_goal(self) -> int:
        """The number of goal points, after checking that ``/goal`` is an (N, 3) dataset."""
        f = self._f
        if "goal" not in f or not isinstance(f["goal"], h5py.Dataset):
            self._fail("missing dataset /goal")
        goal = f["goal"]
        if goal.ndim != 2 or goal.shape[1] != 3:
            self._fail(f"/goal must have shape (N, 3), got {goal.shape}")
        if goal.dtype != np.float32:
            self._fail(f"/goal has dtype {goal.dtype}, expected float32")
        return goal.shape[0]

    def _episode_names(self) -> list:
        """The episode groups' names, checked to be numbered from 000000 without gaps."""
        f = self._f
        if "episodes" not in f or not isinstance(f["episodes"], h5py.Group):
            self._fail("missing group /episodes")
        names = sorted(f["episodes"].keys())
        expected = [episode_name(i) for i in range(len(names))]
        if names != expected:
            self._fail(f"episode groups must be numbered 000000.. without gaps, got "
                       f"{names[:5]}{'...' if len(names) > 5 else ''}")
        return names

    def _check_members(self) -> None:
        """A version 5 file holds exactly the objects the layout names: ``/goal``,
        ``/episodes`` and in each episode group its datasets."""
        f = self._f
        extra = sorted(set(f.keys()) - {"goal", "episodes"})
        if extra:
            self._fail(f"unexpected object(s) {['/' + e for e in extra]} (not part of the "
                       f"format: the file was edited)")
        want = set(self._datasets())
        for name in self._names:
            extra = sorted(set(f["episodes"][name].keys()) - want)
            if extra:
                self._fail(f"episode {int(name)}: unexpected object(s) {extra} (not part of "
                           f"the format: the file was edited)")

    def _check_episode(self, name: str, dims: dict, image_size, n_goal: int) -> dict:
        """Check episode group ``name``: its attributes and every dataset's dtype and shape,
        the sizes named in :data:`EPISODE_DATASETS` agreeing within the episode, with the
        earlier episodes' ``dims`` (A, O, N: ``None`` before the first) and with the goal's
        ``n_goal`` points. Returns the episode's A, O and N."""
        g = self._f["episodes"][name]
        where = f"episode {int(name)}"
        if not isinstance(g, h5py.Group):
            self._fail(f"{where} is not a group")
        for key in EPISODE_ATTRS:
            if key not in g.attrs:
                self._fail(f"{where}: missing attribute {key!r}")
        length = g.attrs["length"]
        if np.shape(length) != () or not np.issubdtype(np.asarray(length).dtype, np.integer):
            self._fail(f"{where}: attribute 'length' must be an integer, got {length!r}")
        sizes = {"T": int(length), **dims, "S": image_size}
        for key, (dtype, shape) in self._datasets().items():
            if key not in g or not isinstance(g[key], h5py.Dataset):
                self._fail(f"{where}: missing dataset {key!r}")
            self._check_dataset(where, key, g[key], dtype, shape, sizes)
        if sizes["N"] != n_goal:
            self._fail(f"{where}: {sizes['N']} object points but the goal has {n_goal}")
        return {k: sizes[k] for k in dims}

    def _check_dataset(self, where: str, key: str, ds, dtype, dims, sizes: dict) -> None:
        """``ds`` has ``dtype`` and the shape ``dims`` names; a named size seen first here
        is recorded in ``sizes`` (``"T+1"``: one more than T)."""
        if ds.dtype != np.dtype(dtype):
            self._fail(f"{where}: dataset {key!r} has dtype {ds.dtype}, expected {dtype}")
        if ds.ndim != len(dims):
            self._fail(f"{where}: dataset {key!r} has {ds.ndim} dimensions, "
                       f"expected {len(dims)} {dims}")
        for size, dim in zip(ds.shape, dims, strict=True):
            want = dim
            if isinstance(dim, str):
                base = dim.removesuffix("+1")
                plus = 1 if dim.endswith("+1") else 0
                if sizes.get(base) is None:
                    sizes[base] = size - plus
                want = sizes[base] + plus
            if size != want:
                self._fail(f"{where}: dataset {key!r} has shape {ds.shape}, "
                           f"expected {dims} with {sizes}")

    def _check_images(self, images) -> list:
        """The image modes of a valid ``images`` attribute (see :func:`images_meta`)."""
        if not isinstance(images, dict) or not isinstance(images.get("modes"), list):
            self._fail(f"file attribute 'images' must hold a list 'modes', got {images!r}")
        modes = images["modes"]
        unknown = [m for m in modes if m not in IMAGE_DATASETS]
        if unknown:
            self._fail(f"unknown image mode(s) {unknown} in the 'images' attribute; known: "
                       f"{', '.join(IMAGE_DATASETS)}")
        if modes:
            size, window, radius = images.get("size"), images.get("window"), images.get("radius")
            if not (isinstance(size, int) and size > 0):
                self._fail(f"'images' size must be a positive int, got {size!r}")
            if not (isinstance(window, list) and len(window) == 5
                    and all(isinstance(v, (int, float)) for v in window)):
                self._fail(f"'images' window must be 5 numbers (x0, x1, y0, y1, z0), got "
                           f"{window!r}")
            if not isinstance(radius, (int, float)):
                self._fail(f"'images' radius must be a number, got {radius!r}")
        return modes

    def _datasets(self) -> dict:
        """The datasets every episode of this file has: name -> (dtype, dimensions)."""
        return {**EPISODE_DATASETS, **{m: IMAGE_DATASETS[m] for m in self.image_modes}}

    # -- digests
    @property
    def digested(self) -> bool:
        """Whether the file's datasets carry content digests (format version 5 on)."""
        return self.meta["format_version"] >= DIGESTED_SINCE

    def _checked_digest(self, ds, data, where: str) -> str:
        """The digest of ``data`` (the values just read from dataset ``ds``), checked
        against the one stored with it (``DataFileError`` if it is missing or differs)."""
        computed = array_digest(data)
        stored = ds.attrs.get(DIGEST_ATTR)
        if stored is None:
            self._fail(f"{where} carries no content digest (format version "
                       f"{self.meta['format_version']} stores one with every dataset)")
        if _text(stored) != computed:
            self._fail(f"{where}: content digest mismatch: its values were changed after it "
                       f"was written (stored {_text(stored)[:19]}..., computed "
                       f"{computed[:19]}...)")
        return computed

    def _check_episode_digest(self, k: int, g, arrays: dict) -> None:
        """Each dataset's digest and the episode group's over them and its attributes."""
        digests = {key: self._checked_digest(g[key], data, f"episode {k}: dataset {key!r}")
                   for key, data in arrays.items()}
        stored = g.attrs.get(DIGEST_ATTR)
        if stored is None or _text(stored) != episode_digest(digests, dict(g.attrs)):
            self._fail(f"episode {k}: episode digest mismatch or missing: its datasets or "
                       f"attributes were changed after it was recorded")

    # -- access
    @property
    @_named("/goal")
    def goal(self) -> np.ndarray:
        ds = self._f["goal"]
        data = ds[()]
        if self.check_digests and self.digested:
            self._checked_digest(ds, data, "/goal")
        return np.asarray(data, np.float32)

    @property
    @_named("/goal provenance")
    def goal_provenance(self) -> dict:
        return json.loads(_text(self._f["goal"].attrs["provenance"]))

    def __len__(self) -> int:
        return len(self._names)

    def __getitem__(self, k: int) -> Episode:
        return self.episode(k)

    def __iter__(self):
        for k in range(len(self)):
            yield self.episode(k)

    def episode(self, k: int, as_jax: bool = False) -> Episode:
        """Episode ``k`` (its content digests checked unless the file was opened with
        ``verify=False``)."""
        if not (isinstance(k, (int, np.integer)) and 0 <= k < len(self)):
            raise DataFileError(f"{self.path}: no episode {k!r} (the file has {len(self)}: "
                                f"0..{len(self) - 1})")
        return self._episode(int(k), as_jax, self.check_digests)

    def _episode(self, k: int, as_jax: bool, digests: bool) -> Episode:
        try:
            g = self._f["episodes"][episode_name(k)]
            arrays = {key: g[key][()] for key in self._datasets()}
            if digests and self.digested:
                self._check_episode_digest(k, g, arrays)
            attrs = dict(index=k, seed=int(g.attrs["seed"]), policy=_text(g.attrs["policy"]),
                         score=float(g.attrs["score"]))
        except DataFileError:
            raise
        except READ_ERRORS as err:
            raise DataFileError(f"{self.path}: episode {k}: data unreadable, truncated or "
                                f"corrupted ({_short(err)})") from None
        if as_jax:
            import jax.numpy as jnp

            arrays = {key: jnp.asarray(v) for key, v in arrays.items()}
        return Episode(**attrs, **arrays)

    @_named("episode shapes")
    def episode_shapes(self, k: int) -> dict:
        """The shapes of episode ``k``'s datasets, by name (read from the file's metadata,
        not its data)."""
        g = self._f["episodes"][episode_name(int(k))]
        return {key: list(g[key].shape) for key in self._datasets()}

    @_named("metadata")
    def summary(self) -> dict:
        """A JSON-compatible summary: metadata, episode count and scores."""
        scores = [float(self._f["episodes"][n].attrs["score"]) for n in self._names]
        seeds = [int(self._f["episodes"][n].attrs["seed"]) for n in self._names]
        out = {"path": str(self.path), **{k: v for k, v in self.meta.items()
                                           if k != "scene_doc"},
               "episodes": len(self), "seeds": seeds, "scores": scores,
               "goal_points": int(self._f["goal"].shape[0]),
               "file_bytes": self.path.stat().st_size}
        if scores:
            out["score_mean"] = float(np.mean(scores))
            out["score_sem"] = sem(scores)
        return out

    # -- full check
    @_named("data")
    def verify(self) -> None:
        """Read every dataset (checking HDF5 checksums and, in a version 5 file, the content
        digests) and check the values: finite, actions inside the spec's action box,
        ``r_gt`` in [0, 1], the score the last ``r_gt``, the rewards equal to ``r_gt`` when
        the auxiliary weight is 0, ``point_steps`` increasing from 0 to the length. In a
        version 4 or later file every non-empty dataset must carry a checksum. The checks
        that need the task (the goal, ``r_gt`` from the stored points) are
        :func:`dax_data.semantics.check_semantics`."""
        for name in self._dataset_names():
            self._read_dataset(name)
        goal = self._goal_checked()
        if not np.all(np.isfinite(goal)):
            self._fail("/goal contains NaN or inf")
        box = self._action_box()
        aux = self.meta.get("params", {}).get("aux_weight")
        for k in range(len(self)):
            ep = self._episode(k, False, True)
            self._check_values(k, ep, box, aux)

    def _goal_checked(self) -> np.ndarray:
        check, self.check_digests = self.check_digests, True
        try:
            return self.goal
        finally:
            self.check_digests = check

    def _dataset_names(self) -> list:
        datasets = []
        self._f.visititems(lambda name, obj: datasets.append(name)
                           if isinstance(obj, h5py.Dataset) else None)
        return datasets

    def _read_dataset(self, name: str) -> None:
        """Read dataset ``name`` whole (HDF5 checks its chunks' checksums)."""
        ds = self._f[name]
        if self.meta["format_version"] >= CHECKSUMMED_SINCE and ds.size and \
                not ds.fletcher32:
            self._fail(f"dataset /{name} carries no checksum (format version "
                       f"{self.meta['format_version']} checksums every dataset)")
        try:
            ds[()]
        except READ_ERRORS as err:
            parts = name.split("/")
            if len(parts) == 3 and parts[0] == "episodes" and parts[1].isdigit():
                self._fail(f"episode {int(parts[1])}: data unreadable, truncated or "
                           f"corrupted (dataset {parts[2]!r}: {_short(err)})")
            self._fail(f"/{name}: data unreadable, truncated or corrupted "
                       f"({_short(err)})")

    def _action_box(self):
        """``(low, high)`` float32 of the spec's action box (``None`` if the spec has none)."""
        spec = self.meta["spec"]
        if "action_low" not in spec or "action_high" not in spec:
            return None
        try:
            low = np.asarray(spec["action_low"], np.float32)
            high = np.asarray(spec["action_high"], np.float32)
        except (TypeError, ValueError):
            self._fail("the spec's action_low / action_high are not lists of numbers")
        return low, high

    def _check_values(self, k: int, ep: Episode, box, aux) -> None:
        """The value checks of :meth:`verify` for episode ``k``."""
        for key in ("actions", "observations", "rewards", "r_gt", "points",
                    "end_effector", *(["height"] if ep.height is not None else [])):
            if not np.all(np.isfinite(getattr(ep, key))):
                self._fail(f"episode {k}: dataset {key!r} contains NaN or inf")
        if box is not None:
            low, high = box
            if low.shape != ep.actions.shape[1:]:
                self._fail(f"episode {k}: actions of {ep.actions.shape[1]} entries, the "
                           f"spec's action box has {low.shape}")
            outside = np.nonzero(np.any((ep.actions < low) | (ep.actions > high), axis=1))[0]
            if outside.size:
                t = int(outside[0])
                self._fail(f"episode {k}: action {t} {ep.actions[t].tolist()} lies outside "
                           f"the task's action box (low {low.tolist()}, high {high.tolist()})")
        if np.any((ep.r_gt < 0) | (ep.r_gt > 1)):
            self._fail(f"episode {k}: r_gt outside [0, 1] (it is exp(-lam D))")
        if aux == 0 and not np.array_equal(ep.rewards, ep.r_gt):
            self._fail(f"episode {k}: rewards differ from r_gt although aux_weight is 0")
        steps = ep.point_steps
        if steps.size == 0 or steps[-1] != ep.length or np.any(np.diff(steps) <= 0) \
                or steps[0] != 0:
            self._fail(f"episode {k}: point_steps must increase from 0 to the episode "
                       f"length {ep.length}, got {steps.tolist()}")
        if ep.length and not np.float32(ep.score) == ep.r_gt[-1]:
            self._fail(f"episode {k}: score {ep.score} is not the last r_gt "
                       f"{float(ep.r_gt[-1])}")

    def close(self) -> None:
        """Close the file (errors closing a damaged file are ignored: nothing was
        written)."""
        f = getattr(self, "_f", None)
        if f is not None:
            try:
                f.close()
            except READ_ERRORS:
                pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def open_file(path: str | os.PathLike, verify: bool = True) -> DemoFile:
    """Open a demonstration file for reading (schema checked; content digests checked as
    values are read unless ``verify=False``); see :class:`DemoFile`."""
    return DemoFile(path, verify=verify)


def load(path: str | os.PathLike, as_jax: bool = False,
         verify: bool = True) -> tuple[dict, list[Episode]]:
    """``(meta, episodes)``: the file attributes and every episode, as NumPy (or JAX), each
    dataset's content digest checked, the goal's too (``verify=False`` skips that); a
    :class:`DataFileError` naming the file otherwise."""
    with DemoFile(path, verify=verify) as f:
        if verify:
            f.goal  # noqa: B018 - reading it checks its digest
        return f.meta, [f.episode(k, as_jax=as_jax) for k in range(len(f))]


def sem(values) -> float:
    """Standard error of the mean (sample standard deviation / sqrt(n); 0 for n < 2)."""
    v = np.asarray(values, np.float64)
    return float(v.std(ddof=1) / np.sqrt(v.size)) if v.size > 1 else 0.0


def _text(value) -> str:
    if isinstance(value, bytes):
        return value.decode()
    if isinstance(value, np.ndarray) and value.shape == ():
        return _text(value.item())
    return value if isinstance(value, str) else str(value)


def _short(err: BaseException) -> str:
    return " ".join(str(err).split())[:200]
