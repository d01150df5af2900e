"""Recording episodes of a policy (the task's scripted expert, or uniform random actions)
into a demonstration file, resumably; and scoring policies over seeds.

Episode ``i`` of a run with ``seed=S`` uses seed ``S + i``: the task is reset with
``jax.random.PRNGKey(S + i)``; the random policy draws step ``t``'s action uniformly within
the action bounds with key ``fold_in(fold_in(PRNGKey(S + i), 1), t)``. So every episode can
be regenerated from (task, spec, seed, policy, package versions), all stored in the file.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from . import fileformat as ff
from .fileformat import DataFileError

POLICIES = ("expert", "random")
#: The largest episode seed: ``jax.random.PRNGKey`` holds 32 bits of a seed, so seed
#: ``2**32 + s`` would give the episodes of seed ``s`` (and a seed beyond 64 bits overflows).
MAX_SEED = 2**32 - 1


def check_seeds(seed, count: int = 1) -> int:
    """``seed`` if seeds ``seed .. seed + count - 1`` are all ints in ``0 ..``
    :data:`MAX_SEED`; ``ValueError`` naming the range otherwise."""
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)):
        raise ValueError(f"seed must be an integer, got {type(seed).__name__} {seed!r}")
    seed = int(seed)
    last = seed + count - 1
    if seed < 0 or last > MAX_SEED:
        span = f"seeds {seed}..{last}" if count > 1 else f"seed {seed}"
        raise ValueError(f"{span} outside 0..{MAX_SEED}: a PRNGKey holds 32 bits of a seed "
                         f"(seed 2**32 + s would repeat seed s)")
    return seed


def make_task(name: str, overrides: dict | None = None):
    """``dax_tasks.make(name, **overrides)`` (``ValueError`` for an unknown task or a bad
    override)."""
    import dax_tasks

    return dax_tasks.make(name, **(overrides or {}))


def _from_json(value):
    """JSON lists become tuples (spec and scene fields are hashable jit static args)."""
    if isinstance(value, list):
        return tuple(_from_json(v) for v in value)
    return value


def parse_overrides(task_name: str, items) -> dict:
    """``dax_tasks.make`` overrides from ``KEY=VALUE`` strings (the CLI's ``--override``).

    ``KEY`` is a :class:`dax_tasks.TaskSpec` field (``substeps=160``, ``horizon=2``), a
    params number (``lam=5``, ``aux_weight=1``) or ``scene.FIELD`` for a field of the
    task's scene (``scene.n=6``); ``VALUE`` is read as
    JSON (``6``, ``0.5``, ``true``, ``[1, 2]``) and kept as a string when it is not JSON.
    Scene fields are applied with ``dataclasses.replace`` to the task's default scene.
    Every value is checked against its field's type (:func:`dax_tasks.check_overrides`:
    ``scene.n=6.5``, ``lam=abc``, ``horizon=true`` or ``action_low=5`` are refused with a
    ``ValueError`` naming the key).
    """
    import dataclasses

    import dax_tasks

    top, scene = {}, {}
    for item in items or ():
        key, sep, text = str(item).partition("=")
        key = key.strip()
        if not sep or not key:
            raise ValueError(f"override {item!r} is not of the form KEY=VALUE")
        try:
            value = _from_json(json.loads(text))
        except json.JSONDecodeError:
            value = text
        if key.startswith("scene."):
            scene[key[len("scene."):]] = value
        elif key == "scene":
            raise ValueError("override the scene field by field: scene.FIELD=VALUE")
        else:
            top[key] = value
    if scene:
        default = dax_tasks.get_spec(task_name).scene
        fields = {f.name for f in dataclasses.fields(default)}
        unknown = sorted(set(scene) - fields)
        if unknown:
            raise ValueError(f"unknown scene override(s) {unknown} for task {task_name!r}; "
                             f"valid: {sorted(fields)}")
        # types first: the scene's own checks compare values (6 < "abc" is a TypeError)
        from dax_tasks.core.spec import checked_fields

        checked_fields(default, scene, "scene.")
        try:
            top["scene"] = dataclasses.replace(default, **scene)
        except TypeError as err:
            raise ValueError(f"scene overrides for task {task_name!r}: {err}") from None
    dax_tasks.check_overrides(task_name, top)  # types, before anything runs (kept as given:
    # the file's generator attribute records them as written)
    return top


def _check_policy(env, policy: str) -> None:
    if policy not in POLICIES:
        raise ValueError(f"unknown policy {policy!r}; valid: {', '.join(POLICIES)}")
    if policy == "expert" and not env.has_expert:
        raise ValueError(f"task {env.spec.name!r} has no scripted expert; "
                         f"use --policy random")


def _random_action(spec, episode_key, t):
    low = jnp.asarray(spec.action_low, jnp.float32)
    high = jnp.asarray(spec.action_high, jnp.float32)
    key = jax.random.fold_in(jax.random.fold_in(episode_key, 1), t)
    return jax.random.uniform(key, low.shape, jnp.float32, low, high)


def check_obs(obs) -> tuple:
    """The observation modes to store, from a list or a comma-separated string
    (``"state,height,rgb"``): ``state`` always (the task's own observation), plus the image
    modes of :data:`dax_data.fileformat.IMAGE_DATASETS` asked for, in a fixed order."""
    items = [o.strip() for o in obs.split(",")] if isinstance(obs, str) else list(obs)
    unknown = [o for o in items if o not in ff.OBS_MODES]
    if unknown:
        raise ValueError(f"unknown observation mode(s) {unknown}; valid: "
                         f"{', '.join(ff.OBS_MODES)}")
    return tuple(m for m in ff.OBS_MODES if m == "state" or m in items)


def check_image_size(size) -> int:
    if not (isinstance(size, int) and not isinstance(size, bool) and size >= 8):
        raise ValueError(f"image size must be an int >= 8 (pixels), got {size!r}")
    return size


class Recorder:
    """Runs single episodes of one env (a pure :class:`dax_tasks.Env`, unbatched) with its
    default params and returns their arrays; reset, step and the policy are jitted once.

    ``obs``: the observation modes to record (:func:`check_obs`): the image modes are
    rendered at ``image_size`` pixels by the env's camera (:class:`dax_tasks.viz.Camera`,
    the one :class:`dax_tasks.core.wrappers.ObservationMode` uses, so a recorded picture equals
    the observation a policy sees in that mode)."""

    def __init__(self, env, policy: str = "expert", point_stride: int = 1,
                 obs=("state",), image_size: int = 64):
        _check_policy(env, policy)
        if not (isinstance(point_stride, int) and point_stride > 0):
            raise ValueError(f"point_stride must be a positive int, got {point_stride!r}")
        self.env, self.policy, self.point_stride = env, policy, point_stride
        self.obs, self.image_size = check_obs(obs), check_image_size(image_size)
        self.params = env.default_params
        spec = env.spec
        self._reset = jax.jit(env.reset)
        self._step = jax.jit(env.step)
        self._expert = jax.jit(env.expert_action) if policy == "expert" else None
        self.image_modes = tuple(m for m in self.obs if m in ff.IMAGE_DATASETS)
        from dax_tasks.core.checks import check_run_memory

        # before anything is compiled or allocated: an episode's states and its pictures
        check_run_memory(env, image_size=self.image_size if self.image_modes else None,
                         frames=(env.horizon + 1) if self.image_modes else 0)
        self.camera = None
        if self.image_modes:
            from dax_tasks.viz import Camera

            self.camera = Camera.for_env(env)
        self._probe = jax.jit(self._points_and_images)
        self._random = jax.jit(lambda k, t: _random_action(spec, k, t))

    def _points_and_images(self, state):
        env, camera, size = self.env, self.camera, self.image_size
        pts, ee = env.object_points(state.physics), env.end_effector(state.physics)
        images = {}
        if "height" in self.image_modes:
            images["height"] = camera.height(pts, size)
        if "rgb" in self.image_modes:
            images["rgb"] = camera.rgb(pts, ee, size, env.object_colors)
        return pts, ee, images

    @property
    def images_meta(self) -> dict:
        """The file's ``images`` attribute (:func:`dax_data.fileformat.images_meta`)."""
        return ff.images_meta(self.image_modes, self.image_size, self.camera)

    def point_steps(self, length: int) -> np.ndarray:
        steps = list(range(0, length + 1, self.point_stride))
        if steps[-1] != length:
            steps.append(length)
        return np.asarray(steps, np.int32)

    def action(self, state, episode_key, t: int):
        if self.policy == "expert":
            return self._expert(state, self.params)
        return self._random(episode_key, t)

    def episode(self, seed: int) -> dict:
        """The arrays of one episode from seed ``seed`` (see :mod:`dax_data.fileformat`)."""
        env, params = self.env, self.params
        key = jax.random.PRNGKey(seed)
        obs, state = self._reset(key, params)
        observations, actions, rewards, r_gt, ee, points = [np.asarray(obs)], [], [], [], [], {}
        pts, e, img = self._probe(state)
        points[0], ee0 = np.asarray(pts), np.asarray(e)
        ee.append(ee0)
        images = {k: [np.asarray(v)] for k, v in img.items()}
        for t in range(env.horizon):
            action = self.action(state, key, t)
            obs, state, reward, done, info = self._step(state, action, params)
            actions.append(np.asarray(action))
            observations.append(np.asarray(obs))
            rewards.append(np.asarray(reward))
            r_gt.append(np.asarray(info["r_gt"]))
            pts, e, img = self._probe(state)
            ee.append(np.asarray(e))
            for k, v in img.items():
                images[k].append(np.asarray(v))
            if (t + 1) % self.point_stride == 0 or bool(done):
                points[t + 1] = np.asarray(pts)
            if bool(done):
                break
        length = len(actions)
        steps = self.point_steps(length)
        return {"actions": np.stack(actions), "observations": np.stack(observations),
                "rewards": np.stack(rewards), "r_gt": np.stack(r_gt),
                "points": np.stack([points[int(s)] for s in steps]), "point_steps": steps,
                "end_effector": np.stack(ee), **{k: np.stack(v) for k, v in images.items()}}


def _say(message: str) -> None:
    """One line on stderr (what :func:`generate` says while it waits for a lock)."""
    import sys

    print(f"dax-data: {message}", file=sys.stderr, flush=True)


def _generator_args(task_name, seed, policy, point_stride, overrides, obs,
                    image_size) -> dict:
    return {"task": task_name, "seed": int(seed), "policy": policy,
            "point_stride": int(point_stride), "overrides": ff._jsonable(overrides or {}),
            "obs": list(obs), "image_size": int(image_size)}


def _check_args(path: Path, f: ff.DemoFile, args: dict, episodes: int) -> None:
    """Refuse to resume ``f`` if it was made with other generator arguments."""
    old = dict(f.meta["generator"])
    old_n = old.pop("episodes", None)
    for key, value in args.items():
        if old.get(key) != value:
            raise DataFileError(
                f"{path}: exists with {key}={json.dumps(old.get(key))}, not "
                f"{json.dumps(value)}; rerun with the file's arguments to resume, or choose "
                f"another --out")
    if len(f) > episodes:
        raise DataFileError(f"{path}: already holds {len(f)} episodes, more than the "
                            f"{episodes} asked for (the file was made with --episodes "
                            f"{old_n})")


def _check_task(path: Path, f: ff.DemoFile, env) -> None:
    """Refuse to resume ``f`` if it was made with another format, spec, code, params or
    goal."""
    ff.check_extendable(path, f.meta)
    if f.meta["spec"] != json.loads(json.dumps(env.spec.to_json())):
        raise DataFileError(f"{path}: was made with another task spec; choose another --out")
    fp = env.spec.fingerprint()
    if f.meta["fingerprint"] != fp:
        raise DataFileError(
            f"{path}: was made by other dax-tasks/dax-physics code (fingerprint "
            f"{f.meta['fingerprint']}, now {fp}); its episodes could not be reproduced, "
            f"so it is not extended; choose another --out")
    if f.meta["params"] != json.loads(json.dumps(ff.params_to_json(env.default_params))):
        raise DataFileError(f"{path}: was made with other params (lam, aux_weight or the "
                            f"physics numbers); choose another --out")
    if not np.array_equal(f.goal, np.asarray(env.goal, np.float32)):
        raise DataFileError(f"{path}: was made with another goal than the task's current "
                            f"one ({(env.goal_provenance or {}).get('method', '?')})")


def generate(task_name: str, episodes: int, seed: int, out, policy: str = "expert",
             point_stride: int = 1, overrides: dict | None = None,
             progress: bool = True, obs=("state",), image_size: int = 64,
             lock_wait: float = 0.0, notify=_say) -> dict:
    """Record ``episodes`` episodes (seeds ``seed .. seed + episodes - 1``) into ``out``.

    ``obs``: the observation modes to store besides the task's ``state`` observation:
    ``height`` and/or ``rgb`` pictures of ``image_size`` pixels (:class:`Recorder`). If
    ``out`` exists and was made with the same task, seed, policy, point stride, observation
    modes, image size, spec, code and goal, its episodes are kept and only the missing ones
    are recorded (an interrupted run resumes; a larger ``episodes`` extends the file). Each
    episode is committed atomically. Returns a summary: episodes recorded now, seconds per
    episode, file size, scores.

    One writer per real file: the run holds the file's lock (:func:`dax_tasks.io.exclusive`,
    ``.<name>.lock`` beside the real file: a symbolic link ``out`` is written through to
    its target, under the target's lock) from its first look at the file to its last
    episode, so a second ``generate`` of the same file is refused at once with
    :class:`dax_tasks.io.FileLockedError` naming the holder (or waits up to ``lock_wait``
    seconds for it, saying once who holds it); temporary files a killed writer left are
    removed only under the lock. Seeds must lie in ``0 ..`` :data:`MAX_SEED`. Arguments,
    the spec's sizes and the memory an episode needs (states and pictures,
    :func:`dax_tasks.core.checks.check_run_memory`) are checked before any file is
    created. A file is extended only in the float precision it was recorded in.
    """
    if not (isinstance(episodes, int) and not isinstance(episodes, bool) and episodes > 0):
        raise ValueError(f"episodes must be a positive int, got {episodes!r}")
    seed = check_seeds(seed, episodes)
    obs, image_size = check_obs(obs), check_image_size(image_size)
    path = Path(out)
    from dax_tasks.io import exclusive, real_path

    real = real_path(path)  # a link is written through to its target
    if real.exists() and not real.is_file():
        raise ValueError(f"{path}: exists and is not a file")
    if not real.parent.is_dir():
        raise ValueError(f"{path}: directory {real.parent} does not exist")
    with exclusive(path, wait=lock_wait, notify=notify):
        return _generate_locked(task_name, episodes, seed, path, policy, point_stride,
                                overrides, progress, obs, image_size)


def _generate_locked(task_name, episodes, seed, path, policy, point_stride, overrides,
                     progress, obs, image_size) -> dict:
    """:func:`generate` while holding the file's lock."""
    args = _generator_args(task_name, seed, policy, point_stride, overrides, obs, image_size)
    if path.exists():  # check the file and the arguments first: they fail fast
        with ff.DemoFile(path) as f:
            ff.check_extendable(path, f.meta)
            _check_args(path, f, args, episodes)
    env = make_task(task_name, overrides=overrides)
    recorder = Recorder(env, policy, point_stride, obs, image_size)
    for stale in ff.stale_temporaries(path):  # left by a killed writer of this file
        stale.unlink(missing_ok=True)
    if path.exists():
        with ff.DemoFile(path) as f:
            _check_task(path, f, env)
            if f.meta["images"] != recorder.images_meta:
                raise DataFileError(f"{path}: its pictures were rendered by another camera "
                                    f"({f.meta['images']}, now {recorder.images_meta}); "
                                    f"choose another --out")
            done = len(f)
    else:
        attrs = ff.header(env, {**args, "episodes": episodes}, recorder.images_meta)
        ff.create(path, attrs, env.goal, env.goal_provenance or {})
        done = 0
    times = []
    try:
        _set_target(path, args, episodes)
        _record(recorder, path, policy, seed, done, episodes, times, progress)
    except BaseException:
        if done == 0 and not times:  # this run made the file and committed nothing: a
            # corrected command must not find (and refuse) an empty file of other arguments
            from dax_tasks.io import real_path

            real_path(path).unlink(missing_ok=True)
        raise
    with ff.DemoFile(path) as f:
        summary = f.summary()
    summary.update(recorded_now=len(times), resumed_from=done,
                   seconds_per_episode=float(np.median(times)) if times else None,
                   first_episode_seconds=times[0] if times else None)
    return summary


def _record(recorder, path: Path, policy: str, seed: int, done: int, episodes: int,
            times: list, progress: bool) -> None:
    """Record and commit episodes ``done .. episodes - 1``, appending each one's seconds to
    ``times``."""
    from tqdm.auto import tqdm

    with tqdm(total=episodes, initial=done, desc=f"{recorder.env.spec.name} ({policy})",
              unit="ep", disable=not progress, dynamic_ncols=True) as bar:
        for i in range(done, episodes):
            t0 = time.perf_counter()
            arrays = recorder.episode(seed + i)
            ff.append_episode(path, i, seed + i, policy, arrays)
            times.append(time.perf_counter() - t0)
            bar.set_postfix(score=f"{float(arrays['r_gt'][-1]):.3f}")
            bar.update(1)


def _set_target(path: Path, args: dict, episodes: int) -> None:
    """Record the requested episode count in the ``generator`` attribute (atomically)."""
    with ff.DemoFile(path) as f:
        current = f.meta["generator"].get("episodes")
    if current == episodes:
        return
    import h5py

    from dax_tasks.io import atomic_path

    with (atomic_path(path, copy_existing=True) as tmp,
          h5py.File(tmp, "a", libver=ff.LIBVER) as h):
        h.attrs["generator"] = json.dumps({**args, "episodes": episodes})
        ff.seal(h)


# ---------------------------------------------------------------------- scoring
def score(task_name: str, seeds: int = 20, seed: int = 0,
          policies: tuple = POLICIES, overrides: dict | None = None) -> dict:
    """Final-step ``r_gt`` of each policy over seeds ``seed .. seed + seeds - 1`` (the
    episode seeds of :func:`generate`), run as one batch: ``{policy: {"mean", "sem",
    "scores"}}`` plus timing. Policies without an implementation on this task are skipped
    (e.g. ``expert`` for a task without one) and listed under ``"skipped"``."""
    if not (isinstance(seeds, int) and seeds > 0):
        raise ValueError(f"seeds must be a positive int, got {seeds!r}")
    seed = check_seeds(seed, seeds)
    from dax_tasks.core.wrappers import VmapWrapper

    env = make_task(task_name, overrides=overrides)
    from dax_tasks.core.checks import check_run_memory

    check_run_memory(env, batch=seeds)  # all seeds run as one batch
    spec = env.spec
    batch = VmapWrapper(env, batch_size=seeds)
    reset, step = jax.jit(batch.reset), jax.jit(batch.step)
    keys = jnp.stack([jax.random.PRNGKey(seed + i) for i in range(seeds)])
    rand = jax.jit(jax.vmap(lambda k, t: _random_action(spec, k, t), in_axes=(0, None)))
    out = {"task": task_name, "seeds": list(range(seed, seed + seeds)),
           "horizon": env.horizon, "skipped": []}
    for policy in policies:
        try:
            _check_policy(env, policy)
        except ValueError:
            out["skipped"].append(policy)
            continue
        expert = jax.jit(batch.expert_action)
        t0 = time.perf_counter()
        _, state = reset(keys)
        r = None
        for t in range(env.horizon):
            action = expert(state) if policy == "expert" else rand(keys, t)
            _, state, _, done, info = step(state, action)
            r = np.asarray(info["r_gt"], np.float64)
            if bool(np.all(np.asarray(done))):
                break
        out[policy] = {"mean": float(r.mean()), "sem": ff.sem(r), "scores": r.tolist(),
                       "seconds": time.perf_counter() - t0}
    return out
