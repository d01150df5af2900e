"""The runs themselves: one method on one task for some seeds (:func:`run_method`, the local
backend) or one (task, method, seed) from plain data in a process of its own
(:func:`run_one`, a Ray worker). Each finished seed is a :class:`SeedResult`, plain data
(its results row and what is recorded beside it); nothing here writes a file, the driver
records the results (:func:`dax_algos.bench.grid.record`).

A seed fails (``status=failed``, the cause in ``error``) when it raises, when a state,
action or reward turns non-finite (the task's ``finite`` flag), or when a gradient is
non-finite (unless the method handles that by design); ``status=skipped``: the method does
not apply to the task (:class:`dax_algos.method.NotApplicable`).
"""

from __future__ import annotations

import dataclasses
import math
import os
import time
from collections.abc import Mapping
from pathlib import Path

import jax
import numpy as np

import dax_tasks

from .. import registry
from ..il import demos
from ..method import LearnerRunnable, NotApplicable, Runnable
from . import episodes, provenance, trained
from .rows import make_row


@dataclasses.dataclass
class SeedResult:
    """One finished (task, method, seed) as plain data (NumPy arrays, dicts), so that it can
    come back from another process: its results row and what is recorded beside it."""

    row: dict
    #: :func:`episodes.save_episode`'s arguments after the path
    episode: dict | None = None
    #: the learning curve's rows (:func:`learning.append_curve`)
    curve: list | None = None
    #: ``(tree, meta)`` of the trained policy (:func:`trained.trained_record`)
    policy: tuple | None = None


def error_text(err: BaseException) -> str:
    """The first line of ``err`` with its type, at most 300 characters (the ``error``
    column)."""
    text = f"{type(err).__name__}: {err}".strip().splitlines()[0]
    return text[:300]


def failed(task, method, seed, budget, err: BaseException, prefix: str = "",
           **values) -> SeedResult:
    """The :class:`SeedResult` of a seed that raised ``err`` (``status=failed``; the
    provenance that ``values`` does not give is what this process knows without the task
    and the config, :func:`dax_algos.bench.provenance.of_run`)."""
    return SeedResult(make_row(task, method, seed, budget, status="failed",
                               error=prefix + error_text(err),
                               **{**provenance.of_run(), **values}))


def row_values(out, run: Runnable) -> dict:
    """Row values of an :class:`dax_algos.episode.EpisodeOutput` (NumPy), with the failure
    checks (see the module docstring)."""
    score = float(out.score)
    finite = np.asarray(out.finite)
    stats = out.stats
    values = dict(score=score, final_distance=float(np.asarray(out.distance)[-1]),
                  env_steps=run.env_steps, backprop_steps=run.backprop_steps)
    status, error = "ok", ""
    bad_grads = int(np.sum(stats.nonfinite_grads))
    if run.uses_gradients:
        steps = int(np.sum(stats.grad_steps))
        gmax = np.asarray(stats.grad_norm_max, np.float64)
        values.update(grad_norm=float(np.max(gmax)) if gmax.size else math.nan,
                      grad_norm_mean=float(np.sum(stats.grad_norm_sum))
                      / max(steps - bad_grads, 1),
                      nonfinite_grads=bad_grads)
        if bad_grads and not run.nan_grads_zeroed:
            status = "failed"
            error = (f"non-finite gradient in {bad_grads} of {steps} gradient steps "
                     f"(first at env step {int(np.argmax(np.asarray(stats.nonfinite_grads)))})")
    if not finite.all():
        status = "failed"
        error = "; ".join(e for e in (f"non-finite action, state or reward from env step "
                                      f"{int(np.argmin(finite))}", error) if e)
    elif not math.isfinite(score):
        status, error = "failed", f"non-finite score {score}"
    values.update(status=status, error=error)
    return values


def use_default_compilation_cache() -> None:
    """Use the persistent XLA cache ``~/.cache/dax/jax`` (as the test sessions do) unless
    one is configured, so a second run does not recompile."""
    if os.environ.get("JAX_COMPILATION_CACHE_DIR") or jax.config.jax_compilation_cache_dir:
        return
    cache = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "dax" / "jax"
    jax.config.update("jax_compilation_cache_dir", str(cache))


def run_one(task: str, method: str, seed: int, budget: str, task_overrides: Mapping,
            method_overrides: Mapping, cache_goal: bool = True,
            demo_dir: str | None = None) -> SeedResult:
    """One (task, method, seed) from plain data, in a process of its own (a Ray worker):
    builds the task and the method, compiles and runs the seed; writes nothing (the driver
    records the result)."""
    use_default_compilation_cache()
    try:
        env = dax_tasks.make(task, cache_goal=cache_goal, **task_overrides)
    except Exception as err:  # noqa: BLE001
        return failed(task, method, seed, budget, err, prefix="building the task: ")
    (result,) = run_method(env, task, method, [seed], budget, method_overrides, demo_dir,
                           task_overrides or None)
    return result


def run_method(env, t, m, seeds, budget, overrides, demo_dir=None, task_overrides=None,
               phase=None):
    """The :class:`SeedResult` of each of ``seeds`` (a generator; ``seeds`` is iterated
    once, lazily): the method's episode is built and compiled once, then called per seed
    with ``PRNGKey(seed)``. Every seed is computed the same way whichever seeds run with
    it (and under either backend), so its values do not depend on the grid: a learner's
    seeds are not batched under ``vmap``. ``phase(text)``, if given, is told what is
    under way (``"compiling"``, ``"seed 3"``) for a progress display."""
    phase = phase or (lambda text: None)
    params = env.default_params
    prov = provenance.of_run(env)
    try:  # (a method registered in the driver only is unknown to a Ray worker: a failed row)
        method = registry.get(m)
        config = method.config(budget, t, **overrides)
        prov = provenance.of_run(env, config)
        run = method.build(env, config)
        if isinstance(run, LearnerRunnable) and run.demos is not None:
            phase("demonstrations")
        data = demonstrations(env, run, demo_dir, task_overrides)
        phase("compiling")
        t0 = time.perf_counter()
        compiled = jax.jit(run.episode).lower(jax.random.PRNGKey(0), params,
                                              *data).compile()
        compile_s = time.perf_counter() - t0
    except Exception as err:  # noqa: BLE001
        status = "skipped" if isinstance(err, NotApplicable) else "failed"
        for s in seeds:
            yield SeedResult(make_row(t, m, s, budget, status=status, error=error_text(err),
                                      **prov))
        return
    for s in seeds:
        phase(f"seed {s}")
        try:
            t0 = time.perf_counter()
            out = jax.device_get(jax.block_until_ready(
                compiled(jax.random.PRNGKey(s), params, *data)))
            wall = time.perf_counter() - t0
            make = learner_result if isinstance(run, LearnerRunnable) else planner_result
            result = make(env, t, m, s, budget, config, run, out, wall, compile_s)
            result.row.update(prov)
        except Exception as err:  # noqa: BLE001
            result = failed(t, m, s, budget, err, compile_s=compile_s, **prov)
        yield result


def demonstrations(env, run: Runnable, demo_dir, task_overrides) -> tuple:
    """``()``, or ``(data,)`` for a learner that learns from demonstrations: their file
    made or reused (:func:`dax_algos.il.demos.locate`) and read."""
    if not isinstance(run, LearnerRunnable) or run.demos is None:
        return ()
    path = demos.locate(env, run.demos, demo_dir, task_overrides)
    return (run.demos.load(env, path),)


def planner_result(env, t, m, s, budget, config, run, out, wall, compile_s) -> SeedResult:
    """A planner's seed: its row and its episode (start key and actions)."""
    row = make_row(t, m, s, budget, wall_s=wall, compile_s=compile_s, **row_values(out, run))
    episode = dict(reset_key=episodes.planner_reset_key(s), actions=np.asarray(out.actions),
                   score=float(out.score), fingerprint=env.spec.fingerprint(), budget=budget)
    return SeedResult(row, episode)


def learner_result(env, t, m, s, budget, config, run, out, wall, compile_s) -> SeedResult:
    """A learner's seed: its row (with its untrained policy's score), its learning curve
    (``wall_s`` prorated over the updates, which all have the same shape), its first
    evaluation rollout and its trained policy
    (``policies/<task>/<method>/seed<k>.msgpack``, unless it is not finite)."""
    metrics = out.metrics
    n = len(metrics.env_steps)
    curve = None
    if run.train_env_steps:  # no curve for training on demonstrations only
        curve = [dict(task=t, method=m, seed=s, budget=budget, update=u,
                      env_steps=int(metrics.env_steps[u]), wall_s=wall * (u + 1) / n,
                      score=float(metrics.score[u])) for u in range(n)]
    ep = out.episode
    episode = dict(reset_key=episodes.learner_reset_key(s, config.n_eval),
                   actions=np.asarray(ep.actions), score=float(ep.actions_score),
                   fingerprint=env.spec.fingerprint(), rollout=0, n_rollouts=config.n_eval,
                   budget=budget)
    policy = None
    if all(np.all(np.isfinite(x)) for x in jax.tree_util.tree_leaves(out.policy)):
        policy = trained.trained_record(m, env, config, out.policy, seed=int(s),
                                        budget=budget)
    row = make_row(t, m, s, budget, wall_s=wall, compile_s=compile_s,
                   untrained_score=float(out.untrained_score), **row_values(ep, run))
    return SeedResult(row, episode, curve, policy)
