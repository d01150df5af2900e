"""The benchmark grid: every task x method x seed not yet in ``results.csv``, run by a
backend, each result recorded as it finishes, then the reports written.

For each task the local backend builds it once (``dax_tasks.make``), for each method it
builds and compiles the episode once (``jax.jit(...).lower(key, params).compile()``, timed
as ``compile_s``; the env's default params are an argument, not constants), then runs seeds
``0..K-1`` (:func:`dax_algos.bench.execute.run_method`): seed ``k`` uses ``PRNGKey(k)``
(the initial state comes from ``fold_in(key, 0)``, the same for every method). The
**episode score is the final-step ``r_gt``**. Every finished run is appended to
``results.csv`` at once (:func:`record`: one flushed, fsynced write per row); started again,
the grid skips the (task, method, seed, budget) rows already there but the failed ones,
which it runs again (:class:`Plan`). Beside each row it
records the episode (start key and actions, ``episodes/<task>/<method>/seed<k>.npz``,
:mod:`dax_algos.bench.episodes`). At the end it rewrites the reports
(:func:`dax_algos.bench.summary.write_reports`). ``backend="ray"`` runs every (task,
method, seed) as a Ray task instead (:mod:`dax_algos.bench.backends`); this process still
writes every file.
"""

from __future__ import annotations

import itertools
import json
import os
import shlex
import sys
import time
from collections import Counter
from collections.abc import Iterable, Mapping
from pathlib import Path

import jax

import dax_tasks
from dax_tasks.io import exclusive

from .. import registry
from . import backends, episodes, execute, learning, policy_io, provenance, rundir, summary
from .execute import SeedResult
from .progress import Clock
from .provenance import COLUMNS as PROVENANCE
from .rows import append_row, check_name, errors_of, key, latest, read_rows, upgrade

#: where the runs of a grid run (``--backend``)
BACKENDS = ("local", "ray")
#: the most seeds a grid can have: seeds 0 .. 2**32 - 1 are PRNGKey's distinct seeds
MAX_SEEDS = 2**32

#: While a grid runs, its reports (the page, ``results.md``, the charts) are rewritten
#: after a run finishes once this many minutes have passed since they were last written,
#: so that a grid of hours can be read as it goes (the reports take tens of seconds on a
#: paper-sized results file; a run of a full budget takes minutes). They are always
#: written when the grid ends.
REFRESH_MINUTES = 15.0


def resolve_tasks(spec: str | Iterable[str]) -> list[str]:
    """Task names from ``"all"`` (the available ones), ``"a,b"`` or a list; ValueError
    listing the valid names for an unknown or not yet implemented one."""
    declared, available = dax_tasks.TASKS, dax_tasks.available()
    names = _split(spec)
    if names == ["all"]:
        return [check_name("task", n) for n in available]
    for n in names:
        check_name("task", n)
        if n not in declared:
            raise ValueError(f"unknown task {n!r}; valid: {', '.join(declared)} or all")
        if n not in available:
            raise ValueError(f"task {n!r} is not implemented yet; available: "
                             f"{', '.join(available)}")
    return list(dict.fromkeys(names))


def resolve_methods(spec: str | Iterable[str]) -> list[str]:
    """Method names from ``"all"``, ``"a,b"`` or a list; ValueError for an unknown one."""
    names = _split(spec)
    if names == ["all"]:
        return [check_name("method", n) for n in registry.names()]
    for n in names:
        check_name("method", n)
        registry.get(n)
    return list(dict.fromkeys(names))


def _split(spec) -> list[str]:
    names = [s.strip() for s in spec.split(",")] if isinstance(spec, str) else list(spec)
    names = [n for n in names if n]
    if not names:
        raise ValueError("expected at least one name")
    return names


def cli_command(tasks, methods, seeds, out, quick, backend="local", ray_address=None) -> str:
    """The ``dax-bench run`` command line that runs this grid (what ``run.json`` records
    when :func:`run_grid` is called from Python)."""
    parts = ["dax-bench", "run", "--tasks", ",".join(tasks), "--methods", ",".join(methods),
             "--seeds", seeds_text(seeds), *(["--quick"] if quick else []), "--out", str(out),
             *(["--backend", backend] if backend != "local" else []),
             *(["--ray-address", ray_address] if ray_address else [])]
    return shlex.join(parts)


class GridRows(list):
    """The rows :func:`run_grid` returns (the row that counts for each run, :func:`dax_algos.
    bench.rows.latest`), with what it left undone: ``left`` runs (``left_by_task``:
    ``{task: runs}``) because ``max_minutes`` ran out."""

    left: int = 0
    left_by_task: dict

    def left_text(self) -> str:
        """One line saying what is left (``""`` if nothing)."""
        if not self.left:
            return ""
        per = ", ".join(f"{t} {n}" for t, n in self.left_by_task.items() if n)
        return f"{self.left} runs left ({per}); run the same command again to continue"


def check_seeds(seeds) -> range:
    """The seeds of a grid as a ``range``: an int ``K`` in ``1 .. MAX_SEEDS`` is seeds
    ``0 .. K-1``; a ``range`` of step 1 within ``0 .. MAX_SEEDS - 1`` (a piece of a grid:
    seeds 3-4 of five run in another process, gathered by ``dax-bench merge``) is itself
    (``PRNGKey`` takes 32-bit seeds); ``ValueError`` otherwise."""
    if isinstance(seeds, range):
        if seeds.step == 1 and 0 <= seeds.start < seeds.stop <= MAX_SEEDS:
            return seeds
    elif isinstance(seeds, int) and not isinstance(seeds, bool) and 0 < seeds <= MAX_SEEDS:
        return range(seeds)
    raise ValueError(f"seeds must be an int K in 1 .. {MAX_SEEDS} (seeds 0 .. K-1 are "
                     f"PRNGKey's 32-bit seeds) or a non-empty range of step 1 within them, "
                     f"got {seeds!r}")


def seeds_text(seeds) -> str:
    """How ``dax-bench run --seeds`` writes :func:`check_seeds`'s ``seeds``: ``"K"`` for
    seeds ``0 .. K-1``, ``"A-B"`` (both included) for any other range."""
    seeds = check_seeds(seeds)
    return str(seeds.stop) if seeds.start == 0 else f"{seeds.start}-{seeds.stop - 1}"


def parse_seeds(text: str) -> range:
    """``--seeds`` text (``"K"`` or ``"A-B"``, :func:`seeds_text`) as :func:`check_seeds`'s
    range; ``ValueError`` naming the text otherwise."""
    try:
        first, sep, last = text.strip().partition("-")
        seeds = range(int(first), int(last) + 1) if sep else int(first)
    except ValueError:
        raise ValueError(f"expected a number of seeds K or a range A-B, got {text!r}") from None
    return check_seeds(seeds)


def run_grid(tasks="all", methods="all", seeds: int | range = 1, out: str | os.PathLike = "results",
             quick: bool = False, task_overrides: Mapping | None = None,
             method_overrides: Mapping | None = None, cache_goal: bool = True,
             progress: bool = True, demo_dir: str | os.PathLike | None = None,
             command: str | None = None, backend: str = "local",
             ray_address: str | None = None, ray_cpus: float = 1, retry_failed: bool = True,
             max_minutes: float | None = None, include_stale: bool = False,
             lock_wait: float = 0.0, rerun_stale: bool = False) -> GridRows:
    """Run every combination not yet in ``out/results.csv``; returns the row that counts
    for each run in the file (:class:`GridRows`).

    task_overrides: ``{task: {TaskSpec field or lam/aux_weight: value}}`` passed to
    ``dax_tasks.make`` (e.g. a coarser scene for tests). method_overrides: ``{method:
    {config field: value}}`` on top of the budget. cache_goal: passed to
    ``dax_tasks.make``. demo_dir: where the imitation methods' demonstration sets are made
    or reused (default ``$DAX_CACHE_DIR/demos``, :func:`dax_data.standard.cache_dir`).
    command: the command line recorded in ``run.json`` (default: the equivalent
    ``dax-bench run`` command, :func:`cli_command`). seeds: ``K`` runs seeds ``0 .. K-1``
    (at most :data:`MAX_SEEDS`; the runs are enumerated as they are needed, never listed
    whole), a ``range`` those seeds (:func:`check_seeds`).

    retry_failed: a run whose row in ``out`` is ``failed`` is run again (its new row lists
    the earlier errors in ``previous_errors``; the failed row stays in the file and no
    longer counts); ``False`` leaves failed runs as they are. max_minutes: start no run
    after this many minutes (a run under way finishes; the reports are written; the
    rows returned say what is left); ``None``: no limit. include_stale: the reports count
    stale rows (:func:`dax_algos.bench.summary.write_reports`; written when the grid
    ends and, while it runs, every :data:`REFRESH_MINUTES` at the end of a run).
    rerun_stale: a run whose row is stale
    (:func:`dax_algos.bench.provenance.stale_reason`: measured on other dax-tasks /
    dax-physics code, task spec or method config than today's) is run again; its new row
    is the one that counts (the old one stays in the file). Default: a run with a row is
    done, stale or not.

    backend: ``"local"`` (this process) or ``"ray"``: every (task, method, seed) is one Ray
    task (:func:`dax_algos.bench.backends.run_ray`) on the cluster at ``ray_address`` (default:
    ``RAY_ADDRESS``, else a Ray instance started on this machine; an already initialised
    Ray is used as it is), each reserving ``ray_cpus`` CPUs; this process alone writes
    ``out``, recording each run as its task finishes. The rows are those of the local
    backend (their order is the order runs finish in).

    Before any work: ``out`` must be (or become) a writable directory whose
    ``results.csv`` is a results file with valid rows (:func:`dax_algos.bench.rundir.
    check_out`, :func:`dax_algos.bench.rows.read_rows`), no other run may be writing it
    (its lock, ``.results.csv.lock``, :func:`dax_tasks.io.exclusive`: ``FileLockedError``
    naming the holder, at once or after waiting ``lock_wait`` seconds), results already
    there must have been made with the same task and method overrides (recorded in
    ``run.json``) and in the precision JAX computes in now (float32, or float64 under
    ``JAX_ENABLE_X64``); each problem is one error naming the path."""
    task_names = resolve_tasks(tasks)
    method_names = resolve_methods(methods)
    _check_backend(backend, ray_address, ray_cpus)
    seeds = check_seeds(seeds)
    if max_minutes is not None and not max_minutes > 0:
        raise ValueError(f"max_minutes must be positive, got {max_minutes!r}")
    budget = "quick" if quick else "full"
    task_overrides = dict(task_overrides or {})
    method_overrides = dict(method_overrides or {})
    out = Path(out)
    csv_path = rundir.check_out(out)
    config = {"task_overrides": rundir.canonical(task_overrides),
              "method_overrides": rundir.canonical(method_overrides)}
    with exclusive(csv_path, wait=lock_wait):
        rows = read_rows(csv_path)
        _check_precision(csv_path, rows)
        rundir.record_run(out, rows, config, command or cli_command(
            task_names, method_names, seeds, out, quick, backend, ray_address))
        upgrade(csv_path, rows)
        today = provenance.Today(task_overrides, method_overrides)
        current = latest(rows)
        redo = ({key(r) for r in current if r["task"] in task_names
                 and r["method"] in method_names and provenance.stale_reason(r, today)}
                if rerun_stale else set())
        plan = Plan(task_names, method_names, seeds, budget, current, retry_failed,
                    None if max_minutes is None else time.monotonic() + 60 * max_minutes,
                    redo)
        envs: dict = {}  # the tasks built so far, as this run built them

        def make_env(task):
            if task not in envs:
                envs[task] = dax_tasks.make(task, cache_goal=cache_goal,
                                            **task_overrides.get(task, {}))
            return envs[task]

        def write_reports():
            rows = GridRows(latest(read_rows(csv_path)))
            summary.write_reports(rows, out, budget, make_env, include_stale, today)
            return rows

        _run_todo(plan, out, task_overrides, method_overrides, cache_goal, progress,
                  demo_dir, backend, dict(address=ray_address, num_cpus=ray_cpus), envs,
                  write_reports)
        result = write_reports()
        result.left, result.left_by_task = plan.left()
        return result


def rows_of(rows, tasks, methods, seeds: int | range, budget: str) -> list:
    """The rows of ``rows`` that belong to the grid ``tasks`` x ``methods`` x ``seeds``
    (:func:`check_seeds`) of ``budget`` (names as :func:`run_grid` takes them)."""
    tasks, methods = set(resolve_tasks(tasks)), set(resolve_methods(methods))
    seeds = check_seeds(seeds)
    return [r for r in rows if r["task"] in tasks and r["method"] in methods
            and int(r["seed"]) in seeds and r["budget"] == budget]


def _check_precision(path: Path, rows) -> None:
    """Refuse to add rows computed in another precision than the rows in ``path``."""
    now = provenance.precision()
    other = sorted({r["precision"] for r in rows if r["precision"]} - {now})
    if other:
        raise ValueError(f"{path}: holds {'/'.join(other)} results and this run computes in "
                         f"{now} (JAX_ENABLE_X64 is {'set' if now == 'float64' else 'unset'}); "
                         f"one grid, one precision: use another --out directory")


class Plan:
    """The runs of a grid still to do, enumerated lazily (``(task, method, seed)`` in task,
    method, seed order), with the failed runs' error history and the time limit."""

    def __init__(self, tasks, methods, seeds, budget, rows, retry_failed, deadline,
                 redo=frozenset()):
        seeds = check_seeds(seeds)
        self.tasks, self.methods, self.seeds, self.budget = tasks, methods, seeds, budget
        self.deadline = deadline
        self.history = {key(r): errors_of(r) for r in rows
                        if r["status"] == "failed" and retry_failed}
        # ``redo``: runs whose row is there but no longer counts (stale), run again
        self.done = {key(r) for r in rows} - set(self.history) - set(redo)
        self.finished: Counter = Counter()
        in_grid = Counter(t for t, m, s, b in self.done
                          if t in tasks and m in methods and s in seeds and b == budget)
        self.todo_by_task = {t: len(methods) * len(seeds) - in_grid[t] for t in tasks}
        self.total = sum(self.todo_by_task.values())

    def time_is_up(self) -> bool:
        """The time limit has passed (no new run may start)."""
        return self.deadline is not None and time.monotonic() > self.deadline

    def seeds_of(self, task, method):
        """The seeds of (task, method) still to run, lazily; none once the time is up."""
        for s in self.seeds:
            if self.time_is_up():
                return
            if (task, method, s, self.budget) not in self.done:
                yield s

    def groups(self) -> int:
        """The (task, method) pairs with runs still to do."""
        return sum(next(self.seeds_of(t, m), None) is not None
                   for t in self.tasks for m in self.methods)

    def __iter__(self):
        for t in self.tasks:
            for m in self.methods:
                for s in self.seeds_of(t, m):
                    yield t, m, s

    def record(self, result) -> None:
        """Count ``result`` as finished; give its row the run's earlier errors."""
        row = result.row
        errors = self.history.get((row["task"], row["method"], int(row["seed"]),
                                   row["budget"]))
        if errors:
            row["previous_errors"] = json.dumps(errors)
        self.finished[row["task"]] += 1

    def left(self) -> tuple[int, dict]:
        """``(runs left, {task: runs left})``."""
        by_task = {t: n - self.finished[t] for t, n in self.todo_by_task.items()}
        return sum(by_task.values()), by_task


def _check_backend(backend, ray_address, ray_cpus) -> None:
    if backend not in BACKENDS:
        raise ValueError(f"unknown backend {backend!r}; valid: {', '.join(BACKENDS)}")
    if backend == "ray":
        backends.require_ray()
        if not ray_cpus > 0:
            raise ValueError(f"ray_cpus (--ray-cpus) must be positive, got {ray_cpus!r}")
    elif ray_address:
        raise ValueError("--ray-address is for --backend ray (the backend is local)")


def _run_todo(plan: Plan, out, task_overrides, method_overrides, cache_goal, progress,
              demo_dir, backend, ray_options, envs: dict, write_reports) -> None:
    """Run the runs of ``plan`` with ``backend``, recording each result in ``out`` as it
    finishes (a status line ticks every second, :class:`dax_algos.bench.progress.Clock`)
    and calling ``write_reports()`` after a run once :data:`REFRESH_MINUTES` have passed
    since the last call (a failure there is reported on stderr; the grid goes on); the
    local backend keeps the tasks it builds in ``envs`` (``{task: env}``)."""
    clock = Clock(plan.total, plan.groups() if backend == "local" else 0, enabled=progress)
    last_reports = time.monotonic()

    def finished(result):  # the driver alone writes the output directory
        nonlocal last_reports
        plan.record(result)
        record(out, result)
        clock.finished(result.row)
        if time.monotonic() - last_reports >= 60 * REFRESH_MINUTES:
            try:
                write_reports()
            except Exception as err:  # noqa: BLE001 - the page waits; the runs go on
                print(f"dax-bench: warning: the reports were not rewritten: {err}",
                      file=sys.stderr)
            last_reports = time.monotonic()

    try:
        if backend == "ray":
            backends.run_ray(iter(plan), plan.budget, task_overrides, method_overrides,
                             cache_goal, demo_dir, finished, stop=plan.time_is_up,
                             **ray_options)
        else:
            _run_local(plan, task_overrides, method_overrides, cache_goal, demo_dir, envs,
                       finished, clock)
    finally:
        clock.close()


def _run_local(plan: Plan, task_overrides, method_overrides, cache_goal, demo_dir, envs,
               finished, clock) -> None:
    """The runs of ``plan`` in this process, task by task (each built once, kept in
    ``envs``) and method by method (each compiled once for all its seeds)."""
    budget = plan.budget
    for t in plan.tasks:
        if all(next(plan.seeds_of(t, m), None) is None for m in plan.methods):
            continue
        clock.building(t)
        try:
            env = envs[t] = dax_tasks.make(t, cache_goal=cache_goal,
                                           **task_overrides.get(t, {}))
        except Exception as err:  # noqa: BLE001 - recorded, the grid continues
            for m in plan.methods:
                for s in plan.seeds_of(t, m):
                    finished(execute.failed(t, m, s, budget, err,
                                            prefix="building the task: "))
            continue
        for m in plan.methods:
            seeds = plan.seeds_of(t, m)
            first = next(seeds, None)
            if first is None:
                continue
            clock.start(t, m)
            for result in execute.run_method(env, t, m, itertools.chain([first], seeds),
                                             budget, method_overrides.get(m, {}), demo_dir,
                                             task_overrides.get(t), phase=clock.phase):
                finished(result)
        jax.clear_caches()


def record(out: Path, result: SeedResult) -> None:
    """Write ``result`` into the output directory ``out``: its learning curve (before the
    row, so a resumed run never lacks one), episode recording and policy file, then its
    results row (one atomic append). If a file cannot be written, the row says so
    (``failed``)."""
    row = result.row
    t, m, s, budget = row["task"], row["method"], row["seed"], row["budget"]
    try:
        if result.curve:
            learning.append_curve(learning.learning_path(out, t), result.curve)
        if result.episode is not None:
            episodes.save_episode(episodes.episode_path(out, t, m, s), **result.episode)
        if result.policy is not None:
            policy_io.save_policy(out / "policies" / check_name("task", t)
                                  / check_name("method", m) / f"seed{s}.msgpack",
                                  *result.policy)
    except Exception as err:  # noqa: BLE001
        keep = {k: row.get(k, "") for k in ("compile_s", "previous_errors", *PROVENANCE)}
        row = execute.failed(t, m, s, budget, err, **keep).row
    append_row(out / "results.csv", row)
