"""Demonstrations for the imitation-learning methods: dax-data files, checked against the env
they are to teach.

A method that learns from demonstrations names a standard set of dax-data
(:mod:`dax_data.standard`: ``transporter``, 10 expert episodes with pictures; ``ild``, one
expert episode) in its :class:`DemoSpec`; the runner makes or reuses the set's file
(:func:`locate`) and the method's ``load`` reads it with :func:`load_episodes`, which
refuses, in one line naming the file, a file that is truncated, corrupted or not a
demonstration file, that was recorded for another task, another task spec or other code
(the spec's fingerprint), other params or another goal, whose pictures another camera
rendered, or that holds too few episodes.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable
from pathlib import Path

import numpy as np

import dax_data
from dax_data import fileformat as ff
from dax_data.standard import IMAGE_SIZE

DataFileError = dax_data.DataFileError


@dataclasses.dataclass(frozen=True)
class DemoSpec:
    """What a method trains on: the standard set ``set_name`` with pictures of
    ``image_size`` pixels, read by ``load(path) -> data`` (a pytree of arrays, the
    method's training data)."""

    set_name: str
    load: Callable
    image_size: int = IMAGE_SIZE


def locate(env, demo: DemoSpec, directory=None, overrides: dict | None = None,
           progress: bool = False) -> Path:
    """The file of ``demo``'s standard set for ``env`` in ``directory`` (default
    ``$DAX_CACHE_DIR/demos``), recorded now (by the task's scripted expert, through
    dax-data) unless a complete one is there. ``overrides``: the ``dax_tasks.make`` overrides
    ``env`` was built with."""
    return dax_data.ensure_standard(env.spec.name, demo.set_name, directory,
                                    overrides=overrides, image_size=demo.image_size,
                                    progress=progress)


def load_episodes(path, env, episodes: int, image_modes=(), image_size: int | None = None,
                  camera=None) -> list:
    """The first ``episodes`` episodes of the demonstration file ``path`` (NumPy), after
    checking that it was recorded for ``env``: same task, spec fingerprint, params and goal,
    and, for ``image_modes``, pictures of ``image_size`` pixels rendered by ``camera`` (a
    :class:`dax_tasks.viz.Camera`). Raises :class:`dax_data.DataFileError` (a
    ``ValueError``) naming the file and the mismatch."""
    path = Path(path)
    with dax_data.open_file(path) as f:
        meta = f.meta
        if meta["task"] != env.spec.name:
            raise DataFileError(f"{path}: demonstrations of task {meta['task']!r}, not "
                                f"{env.spec.name!r}")
        fp = env.spec.fingerprint()
        if meta["fingerprint"] != fp:
            raise DataFileError(f"{path}: recorded for another task spec or other "
                                f"dax-tasks/dax-physics code (fingerprint "
                                f"{meta['fingerprint']}, this env {fp})")
        if "params" in meta and meta["params"] != json.loads(json.dumps(
                ff.params_to_json(env.default_params))):
            raise DataFileError(f"{path}: recorded with other params (lam, aux_weight or "
                                f"the physics numbers) than this env's")
        if not np.array_equal(f.goal, np.asarray(env.goal, np.float32)):
            raise DataFileError(f"{path}: recorded for another goal than this env's")
        missing = [m for m in image_modes if m not in f.image_modes]
        if missing:
            raise DataFileError(f"{path}: holds no {', '.join(missing)} pictures (it has: "
                                f"{', '.join(f.image_modes) or 'none'}); record them with "
                                f"dax-data generate --obs state,{','.join(image_modes)}")
        if image_modes:
            images = meta["images"]
            want = ff.images_meta(image_modes, image_size, camera)
            if images["size"] != want["size"]:
                raise DataFileError(f"{path}: pictures of {images['size']} pixels, "
                                    f"expected {want['size']}")
            if images["window"] != want["window"] or images["radius"] != want["radius"]:
                raise DataFileError(f"{path}: pictures rendered by another camera (window "
                                    f"{images['window']}, this env's {want['window']})")
        if len(f) < episodes:
            raise DataFileError(f"{path}: holds {len(f)} episodes, {episodes} needed")
        return [f.episode(k) for k in range(episodes)]
