"""The standard demonstration sets the imitation-learning methods train on.

Two sets per task, each one ``generate`` run of the task's scripted expert:

=============== ========== ================= ============================== ===========
set             episodes   seeds             observations                   tasks
=============== ========== ================= ============================== ===========
``transporter`` 10         10000 .. 10009    state, height, rgb (64 px)     macro-action
``ild``         1          10000             state                          all
=============== ========== ================= ============================== ===========

Episode ``i`` starts from ``reset(PRNGKey(10000 + i))``; the benchmark runner evaluates
from keys derived from its seeds ``0 .. K-1`` (``fold_in(PRNGKey(k), 0)``), so no evaluation
episode starts where a demonstration did. Transporter networks need pictures and apply only
to the macro-action tasks (pick-and-place, push); ILD follows one demonstration's states.

A set's file is named by what determines its contents (:func:`standard_path`): the task,
the set, and a digest of the task spec's fingerprint (every spec field and the dax-tasks
and dax-physics code), the params the episodes run with, and the image size. So a set made
by other code, another spec or other params is never reused; one made by the same is
(:func:`ensure_standard` generates it once, extends or resumes it like ``generate``).
``dax-data standard --task T --out DIR`` writes a task's sets; the runner keeps them in
``$DAX_CACHE_DIR/demos`` (default ``~/.cache/dax/demos``, :func:`cache_dir`).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from pathlib import Path

from . import fileformat as ff


@dataclasses.dataclass(frozen=True)
class StandardSet:
    """name; episodes and the first ``seed`` (episode ``i`` uses ``seed + i``); ``obs``: the
    observation modes stored; ``macro_only``: the set applies only to macro-action tasks."""

    name: str
    episodes: int
    seed: int
    obs: tuple
    macro_only: bool = False


STANDARD_SETS = {
    "transporter": StandardSet("transporter", 10, 10_000, ("state", "height", "rgb"),
                               macro_only=True),
    "ild": StandardSet("ild", 1, 10_000, ("state",)),
}
#: Picture size [pixels] of the image sets, unless asked otherwise.
IMAGE_SIZE = 64
#: Seconds :func:`ensure_standard` waits for another process making the same set before
#: it gives up (``dax-data standard --lock-timeout``).
LOCK_TIMEOUT = 300.0
MACRO_KINDS = ("push", "pick_place")


def get_set(name: str) -> StandardSet:
    if name not in STANDARD_SETS:
        raise ValueError(f"unknown standard set {name!r}; valid: {', '.join(STANDARD_SETS)}")
    return STANDARD_SETS[name]


def applies(env, name: str) -> bool:
    """Whether set ``name`` applies to ``env``'s task (image sets: macro actions only)."""
    return not get_set(name).macro_only or env.spec.action_kind in MACRO_KINDS


def cache_dir() -> Path:
    """``$DAX_CACHE_DIR/demos`` if ``DAX_CACHE_DIR`` is set, else ``~/.cache/dax/demos``."""
    root = os.environ.get("DAX_CACHE_DIR")
    return (Path(root) if root else Path.home() / ".cache" / "dax") / "demos"


def standard_path(env, name: str, directory=None, image_size: int = IMAGE_SIZE) -> Path:
    """The file of set ``name`` for ``env`` (a :class:`dax_tasks.Env`) in ``directory``
    (default :func:`cache_dir`): ``<task>-<set>-<digest>.h5``, the digest over the spec's
    fingerprint, the default params, the file format version and (for image sets) the image
    size."""
    s = get_set(name)
    images = [m for m in s.obs if m in ff.IMAGE_DATASETS]
    key = {"fingerprint": env.spec.fingerprint(),
           "params": ff.params_to_json(env.default_params),
           "set": dataclasses.asdict(s), "image_size": image_size if images else None,
           "format_version": ff.FORMAT_VERSION}
    digest = hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:16]
    directory = cache_dir() if directory is None else Path(directory)
    return directory / f"{env.spec.name}-{name}-{digest}.h5"


def ensure_standard(task: str, name: str, directory=None, overrides: dict | None = None,
                    image_size: int = IMAGE_SIZE, progress: bool = False,
                    lock_wait: float = LOCK_TIMEOUT) -> Path:
    """The path of set ``name`` of ``task`` (``dax_tasks.make(task, **overrides)``) in
    ``directory``, recorded now if it is missing or incomplete (a complete file is opened
    and its schema checked, nothing recorded). ``ValueError`` if the set does not apply to
    the task or the task has no scripted expert. Another process making the same set is
    waited for up to ``lock_wait`` seconds (saying once on stderr who it is), then
    :class:`dax_tasks.io.FileLockedError`."""
    from .record import generate, make_task

    env = make_task(task, overrides)
    s = get_set(name)
    if not applies(env, name):
        raise ValueError(f"standard set {name!r} needs a macro-action task "
                         f"({', '.join(MACRO_KINDS)}); {task} has {env.spec.action_kind} "
                         f"actions")
    if not env.has_expert:
        raise ValueError(f"task {task!r} has no scripted expert to demonstrate it")
    path = standard_path(env, name, directory, image_size)
    if path.is_file():
        with ff.DemoFile(path) as f:
            if len(f) >= s.episodes:
                return path
    path.parent.mkdir(parents=True, exist_ok=True)
    # another process making the same set: wait for it (the kernel frees its lock when it
    # exits), then find the set complete
    generate(task, s.episodes, s.seed, path, policy="expert", overrides=overrides,
             progress=progress, obs=s.obs, image_size=image_size, lock_wait=lock_wait)
    return path
