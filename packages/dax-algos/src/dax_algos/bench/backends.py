"""Running the benchmark grid on a Ray cluster (``dax-bench run --backend ray``).

Every (task, method, seed) still to run is one Ray task,
:func:`dax_algos.bench.execute.run_one`, called with plain data (names, seed, budget,
overrides): the worker builds the task and the method itself, compiles and runs that one
seed, writes nothing and returns a :class:`dax_algos.bench.execute.SeedResult` (the row,
the episode's actions, the learning curve, the policy's arrays). The driver, which holds
the output directory's lock, records each result as its task finishes (the ``finished``
callback of :func:`run_ray`; :func:`dax_algos.bench.grid.record`: one atomic append per
row), so a killed driver loses no finished row and the same command resumes. The pictures of the
results page are drawn by the driver at the end, from the recorded episodes.

Ray is an optional dependency (``pip install 'dax-algos[ray]'``), imported only here and
only when this backend is asked for. Each worker needs dax-algos and its siblings installed
(the same versions as the driver) and imports them; a method registered only in the
driver's process (``registry.register``) is unknown there and its rows fail.
"""

from __future__ import annotations

import itertools
import os
import sys
from collections.abc import Callable, Mapping

from .execute import error_text, failed, run_one

#: environment variables of the driver that the workers get too (when set): JAX's
#: persistent compilation cache, so that workers reuse compiled programs
WORKER_ENV = ("JAX_COMPILATION_CACHE_DIR", "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS")

INSTALL_HINT = "pip install 'dax-algos[ray]'"
#: the most runs submitted to the cluster and not yet finished at a time (the grid's runs
#: are enumerated as they are submitted, never listed whole)
IN_FLIGHT = 256


def require_ray():
    """The ``ray`` module; ``ValueError`` saying how to install it if it is missing."""
    try:
        import ray
    except ImportError as err:
        raise ValueError(f"--backend ray needs Ray, which is not installed ({err}); "
                         f"install it with: {INSTALL_HINT}") from None
    return ray


def worker_env() -> dict:
    """The ``env_vars`` of the workers' runtime environment (:data:`WORKER_ENV`)."""
    return {k: os.environ[k] for k in WORKER_ENV if os.environ.get(k)}


def run_ray(todo, budget: str, task_overrides: Mapping, method_overrides: Mapping,
            cache_goal: bool, demo_dir, finished: Callable, address: str | None = None,
            num_cpus: float = 1, stop: Callable[[], bool] | None = None,
            window: int = IN_FLIGHT) -> None:
    """Run ``todo`` (an iterable of ``(task, method, seed)`` triples, consumed lazily) as
    Ray tasks, at most ``window`` submitted and unfinished at a time, and call
    ``finished(result)`` in this process for each as it finishes. Uses Ray as it is if it is
    initialised already, else ``ray.init(address=address)`` (``None``: ``RAY_ADDRESS`` or
    a new local instance), shut down again at the end. A run whose worker raised is a
    ``failed`` row; one lost to the cluster (a worker or node died) is not recorded, so
    that running the same command again retries it. Once ``stop()`` is true no more runs
    are submitted (those under way finish). Interrupted, it cancels the tasks still
    pending."""
    todo = iter(todo)
    first = next(todo, None)
    if first is None:
        return
    todo = itertools.chain([first], todo)
    ray = require_ray()
    started = not ray.is_initialized()
    if started:
        ray.init(address=address)
    env_vars = worker_env()
    remote = ray.remote(run_one).options(
        num_cpus=num_cpus, **({"runtime_env": {"env_vars": env_vars}} if env_vars else {}))
    stop = stop or (lambda: False)
    pending: dict = {}
    lost: list = []

    def submit():
        while len(pending) < window and not stop():
            nxt = next(todo, None)
            if nxt is None:
                return
            t, m, s = nxt
            ref = remote.remote(t, m, s, budget, dict(task_overrides.get(t, {})),
                                dict(method_overrides.get(m, {})), cache_goal,
                                None if demo_dir is None else str(demo_dir))
            pending[ref] = (t, m, s)

    try:
        submit()
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1)
            for ref in ready:
                result = _collect(ray, ref, pending.pop(ref), budget, lost)
                if result is not None:
                    finished(result)
            submit()
        if lost:
            print(f"dax-bench: {len(lost)} runs lost by the Ray cluster are not in "
                  f"results.csv; the same command runs them again", file=sys.stderr)
    finally:
        for ref in pending:  # interrupted: the rest would run for nobody
            ray.cancel(ref, force=True)
        if started:
            ray.shutdown()


def _collect(ray, ref, run, budget, lost):
    """The result of a finished Ray task: its :class:`SeedResult`, a failed one if it
    raised, ``None`` (and the run added to ``lost``) if the cluster lost it."""
    t, m, s = run
    try:
        return ray.get(ref)
    except ray.exceptions.RayTaskError as err:  # raised in run_one itself
        return failed(t, m, s, budget, getattr(err, "cause", None) or err)
    except ray.exceptions.RayError as err:  # the cluster lost it: not recorded
        lost.append(run)
        print(f"dax-bench: {t} / {m} / seed {s} was lost ({error_text(err)}); run again to "
              f"retry it", file=sys.stderr)
        return None
