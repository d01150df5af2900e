"""The checks of a demonstration file that need its task (dax-tasks and JAX), run by
``dax-data validate`` after :meth:`dax_data.DemoFile.verify`:

* the goal (``/goal``) equals the goal of the task the file names, built as the file's
  spec and params say (``dax_tasks.make``: the goal cache or the task's canonical
  motion);
* ``r_gt`` is recomputable from the stored object points: at every stored step ``t > 0``
  the task's ``exp(-lam D)`` of the points (in the state ``reset`` gives for the
  episode's seed, its object points replaced by the stored ones) equals ``r_gt[t - 1]``
  within :data:`R_GT_TOLERANCE`.

Both need the code that recorded the file: a file whose spec fingerprint (the dax-tasks
and dax-physics sources) or params differ from what this installation builds is not
compared, and :func:`check_semantics` says so instead of failing.
"""

from __future__ import annotations

import dataclasses
import functools
import json

import numpy as np

from . import fileformat as ff
from .fileformat import DataFileError

#: Largest difference allowed between a stored ``r_gt`` and the one recomputed from the
#: stored points: the recording's step and the recomputation are different XLA programs,
#: so their float32 results may differ in the last bits; an edit is far larger.
R_GT_TOLERANCE = 1e-4


def task_env(meta: dict):
    """The env a file's episodes ran in: ``dax_tasks.make(task, **changes)`` with the spec
    fields that differ from the task's default spec and the file's ``lam`` and
    ``aux_weight``."""
    import dax_tasks

    spec = ff.spec_from_meta(meta)
    default = dax_tasks.get_spec(meta["task"])
    changes = {f.name: getattr(spec, f.name) for f in dataclasses.fields(spec)
               if f.name != "name" and getattr(spec, f.name) != getattr(default, f.name)}
    env = dax_tasks.make(meta["task"], **changes)
    params = meta.get("params") or {}
    numbers = {k: params[k] for k in ("lam", "aux_weight")
               if isinstance(params.get(k), (int, float))}
    current = ff.params_to_json(env.default_params)
    if any(current[k] != v for k, v in numbers.items()):
        env = dax_tasks.make(meta["task"], **changes, **numbers)
    return env


def check_semantics(f: ff.DemoFile, env=None) -> list:
    """Check the goal and every episode's ``r_gt`` of the open file ``f`` against its task
    (``env``: default :func:`task_env` of the file). Raises :class:`DataFileError`
    naming the file for a goal that is not the task's or an ``r_gt`` that the stored
    points do not give; returns notes on what could not be checked (empty when all
    was)."""
    meta = f.meta
    if env is None:
        try:
            env = task_env(meta)
        except (ValueError, KeyError, TypeError, NotImplementedError) as err:
            return [f"goal and r_gt not checked: the task cannot be built here "
                    f"({' '.join(str(err).split())[:160]})"]
    if meta["fingerprint"] != env.spec.fingerprint():
        return ["goal and r_gt not checked: recorded by other dax-tasks/dax-physics code "
                f"(fingerprint {meta['fingerprint']}, here {env.spec.fingerprint()})"]
    if "params" in meta and meta["params"] != json.loads(json.dumps(
            ff.params_to_json(env.default_params))):
        return ["goal and r_gt not checked: recorded with physics params this task does "
                "not build by default"]
    goal = f.goal
    want = np.asarray(env.goal, np.float32)
    if goal.shape != want.shape or not np.array_equal(goal, want):
        gap = float(np.max(np.abs(goal - want))) if goal.shape == want.shape else None
        raise DataFileError(f"{f.path}: /goal is not the task's goal ("
                            + (f"up to {gap:.3g} m from it" if gap is not None else
                               f"shape {goal.shape}, the task's {want.shape}") + ")")
    recompute = _r_gt_function(env)
    notes = []
    for k in range(len(f)):
        note = _check_episode_r_gt(f, k, env, recompute)
        if note and note not in notes:
            notes.append(note)
    return notes


@functools.lru_cache(maxsize=4)
def _r_gt_function(env):
    """``(reset, r)``: the env's jitted ``reset`` and ``r(physics, points (K, N, 3), goal)
    -> ((K,), (K,))``, ``exp(-lam D)`` of each frame of points put into ``physics`` and
    whether the env's object points of that physics are the given ones (both jitted once
    per env)."""
    import jax
    import jax.numpy as jnp

    from dax_tasks.core import rewards

    lam = env.default_params.lam

    def one(physics, x, goal):
        physics = physics.replace(x=x.astype(physics.x.dtype))
        same = jnp.all(env.object_points(physics) == x.astype(physics.x.dtype))
        return rewards.ground_truth_reward(env.distance(physics, goal), lam), same

    return jax.jit(env.reset), jax.jit(jax.vmap(one, in_axes=(None, 0, None)))


def _check_episode_r_gt(f: ff.DemoFile, k: int, env, recompute):
    """``r_gt`` of episode ``k`` recomputed at its stored frames (``DataFileError`` if one
    differs); a note if the task's state has no object positions ``x`` to put them in."""
    import jax

    reset, recompute = recompute
    ep = f.episode(k)
    _, state = reset(jax.random.PRNGKey(ep.seed))
    if not hasattr(state.physics, "x"):
        return f"r_gt not recomputed: {env.spec.name}'s state holds no positions x"
    steps = ep.point_steps
    frames = steps > 0
    if not np.any(frames):
        return None
    r, same = recompute(state.physics, ep.points[frames], f.goal)
    if not bool(np.all(np.asarray(same))):
        return f"r_gt not recomputed: {env.spec.name}'s object points are not its x"
    stored = ep.r_gt[steps[frames] - 1]
    gap = np.abs(np.asarray(r, np.float64) - stored)
    if np.any(gap > R_GT_TOLERANCE):
        i = int(np.argmax(gap))
        raise DataFileError(
            f"{f.path}: episode {k}: r_gt after step {int(steps[frames][i])} is "
            f"{float(stored[i]):.6g}, but the stored object points give "
            f"{float(np.asarray(r)[i]):.6g}: the data were changed")
    return None
