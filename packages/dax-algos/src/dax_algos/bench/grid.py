"""The benchmark grid: every task x method x seed not yet in ``results.csv``, run by a
backend, each result recorded as it finishes, then the reports written.

For each task the local backend builds it once (``dax_tasks.make``), for each method it
builds and compiles the episode once (``jax.jit(...).lower(key, params).compile()``, timed
as ``compile_s``; the env's default params are an argument, not constants), then runs seeds
``0..K-1`` (:func:`dax_algos.bench.execute.run_method`): seed ``k`` uses ``PRNGKey(k)``
(the initial state comes from ``fold_in(key, 0)``, the same for every method). The
**episode score is the final-step ``r_gt``**. Every finished run is appended to
``results.csv`` at once (:func:`record`: one flushed, fsynced write per row); started again,
the grid skips the (task, method, seed, budget) rows already there. Beside each row it
records the episode (start key and actions, ``episodes/<task>/<method>/seed<k>.npz``,
:mod:`dax_algos.bench.episodes`). At the end it rewrites the reports
(:func:`dax_algos.bench.summary.write_reports`). ``backend="ray"`` runs every (task,
method, seed) as a Ray task instead (:mod:`dax_algos.bench.backends`); this process still
writes every file.
"""

from __future__ import annotations

import os
import shlex
import sys
from collections.abc import Iterable, Mapping
from pathlib import Path

import jax
from tqdm.auto import tqdm

import dax_tasks
from dax_tasks.io import exclusive

from .. import registry
from . import backends, episodes, execute, learning, policy_io, rundir, summary
from .execute import SeedResult
from .rows import append_row, read_rows

#: where the runs of a grid run (``--backend``)
BACKENDS = ("local", "ray")


def resolve_tasks(spec: str | Iterable[str]) -> list[str]:
    """Task names from ``"all"`` (the available ones), ``"a,b"`` or a list; ValueError
    listing the valid names for an unknown or not yet implemented one."""
    declared, available = dax_tasks.TASKS, dax_tasks.available()
    names = _split(spec)
    if names == ["all"]:
        return list(available)
    for n in names:
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
        return list(registry.names())
    for n in names:
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
             "--seeds", str(seeds), *(["--quick"] if quick else []), "--out", str(out),
             *(["--backend", backend] if backend != "local" else []),
             *(["--ray-address", ray_address] if ray_address else [])]
    return shlex.join(parts)


def run_grid(tasks="all", methods="all", seeds: int = 1, out: str | os.PathLike = "results",
             quick: bool = False, task_overrides: Mapping | None = None,
             method_overrides: Mapping | None = None, cache_goal: bool = True,
             progress: bool = True, demo_dir: str | os.PathLike | None = None,
             command: str | None = None, backend: str = "local",
             ray_address: str | None = None, ray_cpus: float = 1) -> list[dict]:
    """Run every combination not yet in ``out/results.csv``; returns all rows of the file.

    task_overrides: ``{task: {TaskSpec field or lam/aux_weight: value}}`` passed to
    ``dax_tasks.make`` (e.g. a coarser scene for tests). method_overrides: ``{method:
    {config field: value}}`` on top of the budget. cache_goal: passed to
    ``dax_tasks.make``. demo_dir: where the imitation methods' demonstration sets are made
    or reused (default ``$DAX_CACHE_DIR/demos``, :func:`dax_data.standard.cache_dir`).
    command: the command line recorded in ``run.json`` (default: the equivalent
    ``dax-bench run`` command, :func:`cli_command`).

    backend: ``"local"`` (this process) or ``"ray"``: every (task, method, seed) is one Ray
    task (:func:`dax_algos.bench.backends.run_ray`) on the cluster at ``ray_address`` (default:
    ``RAY_ADDRESS``, else a Ray instance started on this machine; an already initialised
    Ray is used as it is), each reserving ``ray_cpus`` CPUs; this process alone writes
    ``out``, recording each run as its task finishes. The rows are those of the local
    backend (their order is the order runs finish in).

    Before any work: ``out`` must be (or become) a writable directory whose
    ``results.csv`` is a results file (:func:`dax_algos.bench.rundir.check_out`,
    :func:`dax_algos.bench.rows.read_rows`), no other run may be writing it (its lock,
    ``.results.csv.lock``, :func:`dax_tasks.io.exclusive`: ``FileLockedError`` naming the
    holder), and results already there must have been made with the same task and method
    overrides (recorded in ``run.json``); each problem is one error naming the path."""
    task_names = resolve_tasks(tasks)
    method_names = resolve_methods(methods)
    _check_backend(backend, ray_address, ray_cpus)
    if not (isinstance(seeds, int) and not isinstance(seeds, bool) and seeds > 0):
        raise ValueError(f"seeds must be a positive int, got {seeds!r}")
    budget = "quick" if quick else "full"
    task_overrides = dict(task_overrides or {})
    method_overrides = dict(method_overrides or {})
    out = Path(out)
    csv_path = rundir.check_out(out)
    config = {"task_overrides": rundir.canonical(task_overrides),
              "method_overrides": rundir.canonical(method_overrides)}
    with exclusive(csv_path):
        rows = read_rows(csv_path)
        rundir.record_run(out, rows, config, command or cli_command(
            task_names, method_names, seeds, out, quick, backend, ray_address))
        done = {(r["task"], r["method"], int(r["seed"]), r["budget"]) for r in rows}
        todo = [(t, m, s) for t in task_names for m in method_names for s in range(seeds)
                if (t, m, s, budget) not in done]
        envs = _run_todo(todo, task_names, method_names, out, budget, task_overrides,
                         method_overrides, cache_goal, progress, demo_dir, backend,
                         dict(address=ray_address, num_cpus=ray_cpus))
        rows = read_rows(csv_path)

        def make_env(task):  # the task as this run built it
            if task not in envs:
                envs[task] = dax_tasks.make(task, cache_goal=cache_goal,
                                            **task_overrides.get(task, {}))
            return envs[task]

        summary.write_reports(rows, out, budget, make_env)
        return rows


def _check_backend(backend, ray_address, ray_cpus) -> None:
    if backend not in BACKENDS:
        raise ValueError(f"unknown backend {backend!r}; valid: {', '.join(BACKENDS)}")
    if backend == "ray":
        backends.require_ray()
        if not ray_cpus > 0:
            raise ValueError(f"ray_cpus (--ray-cpus) must be positive, got {ray_cpus!r}")
    elif ray_address:
        raise ValueError("--ray-address is for --backend ray (the backend is local)")


def _run_todo(todo, task_names, method_names, out, budget, task_overrides,
              method_overrides, cache_goal, progress, demo_dir, backend,
              ray_options) -> dict:
    """Run ``todo`` (``(task, method, seed)`` triples) with ``backend``, recording each
    result in ``out`` as it finishes (a progress bar counts them); returns the tasks the
    local backend built (``{task: env}``)."""
    bar = tqdm(total=len(todo), desc="dax-bench", unit="run", disable=not progress,
               file=sys.stderr)

    def finished(result):  # the driver alone writes the output directory
        record(out, result)
        bar.update()

    envs: dict = {}
    try:
        if backend == "ray":
            backends.run_ray(todo, budget, task_overrides, method_overrides, cache_goal,
                             demo_dir, finished, **ray_options)
        else:
            _run_local(todo, task_names, method_names, budget, task_overrides,
                       method_overrides, cache_goal, demo_dir, envs, finished, bar)
    finally:
        bar.close()
    return envs


def _run_local(todo, task_names, method_names, budget, task_overrides, method_overrides,
               cache_goal, demo_dir, envs, finished, bar) -> None:
    """The runs of ``todo`` in this process, task by task (each built once, kept in
    ``envs``) and method by method (each compiled once for all its seeds)."""
    for t in task_names:
        t_todo = [(m, s) for tt, m, s in todo if tt == t]
        if not t_todo:
            continue
        try:
            env = envs[t] = dax_tasks.make(t, cache_goal=cache_goal,
                                           **task_overrides.get(t, {}))
        except Exception as err:  # noqa: BLE001 - recorded, the grid continues
            for m, s in t_todo:
                finished(execute.failed(t, m, s, budget, err, prefix="building the task: "))
            continue
        for m in method_names:
            m_seeds = [s for mm, s in t_todo if mm == m]
            if not m_seeds:
                continue
            bar.set_postfix_str(f"{t} / {m}")
            for result in execute.run_method(env, t, m, m_seeds, budget,
                                             method_overrides.get(m, {}), demo_dir,
                                             task_overrides.get(t)):
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
            policy_io.save_policy(out / "policies" / t / m / f"seed{s}.msgpack",
                                  *result.policy)
    except Exception as err:  # noqa: BLE001
        row = execute.failed(t, m, s, budget, err, compile_s=row.get("compile_s", "")).row
    append_row(out / "results.csv", row)
