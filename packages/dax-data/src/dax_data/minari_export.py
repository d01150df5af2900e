"""Export a demonstration file as a Minari dataset (Farama's format for offline RL data).

``dax-data export FILE --format minari --out DIR [--dataset-id ID]`` writes the dataset
under ``DIR`` (Minari's ``MINARI_DATASETS_PATH``); load it with::

    import os, minari
    os.environ["MINARI_DATASETS_PATH"] = DIR
    ds = minari.load_dataset("dax/fold_cloth1/expert-v0")
    env = ds.recover_environment()  # a dax/FoldCloth1-v0 environment

The dataset stores the Gymnasium id's whole :class:`gymnasium.envs.registration.EnvSpec`,
whose entry point is the string ``"dax_tasks.gym:DaxEnv"``, so ``recover_environment()``
imports dax-tasks' adapter itself: it works in a fresh process with nothing imported first
(dax-tasks with its ``gym`` extra must be installed).

Each episode carries the file's observations (T + 1 of them, the reset observation first),
actions, rewards (the task reward the file recorded), ``terminations`` all false and
``truncations`` true at the last step (DaX episodes end at the horizon; see
``dax_tasks.gym``). The dax seeds (``env.reset(jax.random.PRNGKey(seed))``) are in the
dataset description; Minari's own per-episode seed is left unset because a Gymnasium
``reset(seed=s)`` of a ``dax/...`` env draws its key differently. Object points and
end-effector tracks stay in the HDF5 file only.

Only files recorded with the default task spec can be exported: the dataset names a
registered Gymnasium id, and ``recover_environment`` must rebuild the env the data came
from. Minari is optional: ``pip install "dax-data[minari]"``.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

from . import fileformat as ff


def default_dataset_id(task: str, policy: str) -> str:
    """``dax/<task>/<policy>-v0``: namespace ``dax``, the task as Minari's env name."""
    return f"dax/{task}/{policy}-v0"


def export_minari(path, out_dir, dataset_id: str | None = None) -> Path:
    """Write the episodes of demonstration file ``path`` as Minari dataset ``dataset_id``
    under ``out_dir``; returns the dataset's directory. Raises ``DataFileError`` for a file
    that cannot be exported and ``ImportError`` when Minari is not installed."""
    try:
        import minari
        from minari.data_collector import EpisodeBuffer
    except ImportError as err:
        raise ImportError('the Minari export needs minari: pip install "dax-data[minari]"'
                          ) from err
    import gymnasium as gym

    from dax_tasks.gym import GYM_IDS

    path = Path(path)
    meta, episodes = _exportable(path, GYM_IDS)
    task, policy = meta["task"], meta["generator"].get("policy", "expert")
    dataset_id = dataset_id or default_dataset_id(task, policy)
    buffers = [EpisodeBuffer(**_episode_arrays(ep)) for ep in episodes]
    out_dir = Path(out_dir).resolve()
    final = out_dir.joinpath(*dataset_id.split("/"))
    if final.exists():
        raise ff.DataFileError(f"{final}: a Minari dataset {dataset_id!r} already exists there;"
                               f" remove it or pass another --dataset-id")
    out_dir.mkdir(parents=True, exist_ok=True)
    # Minari writes into MINARI_DATASETS_PATH piece by piece: build the dataset in a
    # temporary root beside the destination and rename it into place when it is complete.
    tmp_root = Path(tempfile.mkdtemp(prefix=".minari-", suffix=".tmp", dir=out_dir))
    old = os.environ.get("MINARI_DATASETS_PATH")
    os.environ["MINARI_DATASETS_PATH"] = str(tmp_root)
    try:
        env = gym.make(GYM_IDS[task])
        seeds = ", ".join(str(ep.seed) for ep in episodes)
        minari.create_dataset_from_buffers(
            dataset_id, buffers, env=env.spec, eval_env=env.spec,
            action_space=env.action_space,
            observation_space=env.observation_space,
            algorithm_name=f"dax-data {policy}",
            description=(f"{len(episodes)} {policy} episodes of the DaX task {task}, exported "
                         f"from {path.name} (dax-data format {meta['format_version']}, "
                         f"versions {meta['versions']}); dax seeds (env.reset("
                         f"jax.random.PRNGKey(seed))): {seeds}."))
        env.close()
        _merge(tmp_root, out_dir)  # the dataset directory moves in whole (one rename)
        return final
    finally:
        shutil.rmtree(tmp_root, ignore_errors=True)
        if old is None:
            os.environ.pop("MINARI_DATASETS_PATH", None)
        else:
            os.environ["MINARI_DATASETS_PATH"] = old


def _exportable(path: Path, gym_ids: dict):
    """``(meta, episodes)`` of file ``path``; ``DataFileError`` if it was recorded with task
    overrides (no Gymnasium id names its env) or holds no episode."""
    with ff.DemoFile(path) as f:
        meta = f.meta
        overrides = meta["generator"].get("overrides")
        if overrides:
            raise ff.DataFileError(
                f"{path}: recorded with task overrides {overrides}; the Minari export "
                f"needs the default task spec (the dataset names the Gymnasium id "
                f"{gym_ids.get(meta['task'])}, whose environment must match the data)")
        episodes = list(f)
    if not episodes:
        raise ff.DataFileError(f"{path}: holds no episodes to export")
    return meta, episodes


def _episode_arrays(ep) -> dict:
    """The arrays of a Minari episode buffer for episode ``ep``: T + 1 observations, T
    actions and rewards, no termination and a truncation at the last step."""
    T = ep.length
    trunc = np.zeros(T, bool)
    trunc[-1] = True
    return dict(id=ep.index, observations=np.asarray(ep.observations, np.float32),
                actions=np.asarray(ep.actions, np.float32),
                rewards=np.asarray(ep.rewards, np.float64).reshape(T),
                terminations=np.zeros(T, bool), truncations=trunc)


def _merge(src: Path, dst: Path) -> None:
    """Move every entry of ``src`` missing from ``dst`` into it (recursing into directories
    both have): namespace metadata Minari wrote is kept where ``dst`` already has it."""
    for entry in sorted(src.iterdir()):
        target = dst / entry.name
        if not target.exists():
            os.replace(entry, target)
        elif entry.is_dir() and target.is_dir():
            _merge(entry, target)
