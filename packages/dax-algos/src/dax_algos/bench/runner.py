"""The benchmark runner: every task x method x seed, evaluated with r_gt only.

``dax-bench run --tasks T1,T2|all --methods M1,M2|all --seeds K [--quick] --out DIR``

For each task the runner builds it once (``dax_tasks.make``), for each method it builds and
compiles the episode once (``jax.jit(...).lower(key, params).compile()``, timed as
``compile_s``; the env's default params are an argument, not constants), then runs seeds
``0..K-1``: seed ``k`` uses ``PRNGKey(k)`` (the initial state comes from
``fold_in(key, 0)``, the same for every method). The **episode score is the final-step
``r_gt``**. Every finished run is appended to ``results.csv`` at once (one flushed, fsynced
write per row); started again, the runner skips the (task, method, seed, budget) rows already
there. Beside each row it records the episode (start key and actions,
``episodes/<task>/<method>/seed<k>.npz``, :mod:`dax_algos.bench.episodes`). At the end it
rewrites ``results.md`` (mean ± standard error, methods x tasks), ``chart_<task>.png``
(score against wall time and simulated environment steps) and the results page
``index.html`` (:mod:`dax_algos.bench.page`, with each (task, method)'s median episode replayed
and drawn); ``dax-bench report --out DIR`` rewrites them. ``--backend ray`` runs every
(task, method, seed) as a Ray task instead (:mod:`dax_algos.bench.backends`); this process still
writes every file.

A run fails (``status=failed``, cause in ``error``) when it raises, when a state, action or
reward turns non-finite (the task's ``finite`` flag), or when a gradient is non-finite
(unless the method zeroes NaNs); the grid continues. ``status=skipped``: the method does not
apply to the task (e.g. no scripted expert).
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import datetime
import importlib.metadata
import io
import json
import math
import os
import platform
import shlex
import sys
import tempfile
import time
from collections.abc import Iterable, Mapping
from pathlib import Path

import jax
import numpy as np
from tqdm.auto import tqdm

import dax_tasks
from dax_tasks.io import atomic_write, exclusive

from .. import common, registry
from ..il import demos
from . import csvlog, episodes, learning, page, policy_io, report, trained

#: where the runs of a grid run (``--backend``)
BACKENDS = ("local", "ray")

COLUMNS = ("task", "method", "seed", "budget", "status", "score", "final_distance", "wall_s",
           "compile_s", "env_steps", "backprop_steps", "grad_norm", "grad_norm_mean",
           "nonfinite_grads", "error")


def _task_names():
    return dax_tasks.TASKS, dax_tasks.available()


def resolve_tasks(spec: str | Iterable[str]) -> list[str]:
    """Task names from ``"all"`` (the available ones), ``"a,b"`` or a list; ValueError
    listing the valid names for an unknown or not yet implemented one."""
    declared, available = _task_names()
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


# ----------------------------------------------------------------------------- results.csv

def read_rows(path: Path) -> list[dict]:
    """The rows of ``results.csv`` (an incomplete last line, from an interrupted write, is
    dropped from the file). A file that is not a results file (not text, other columns, a
    seed that is not an integer) is a ``ValueError`` naming it."""
    def garbled(problem):
        return ValueError(f"{path}: not a dax-bench results file ({problem}); use another "
                          f"--out directory")

    try:  # checked before read_complete cuts an incomplete last line off the file
        text = path.read_bytes().decode() if path.is_file() else ""
        header = next(csv.reader([text.split("\n", 1)[0]])) if text else list(COLUMNS)
    except UnicodeDecodeError:
        raise garbled("not UTF-8 text") from None
    except csv.Error as err:
        raise garbled(f"bad CSV: {err}") from None
    if set(header) != set(COLUMNS):
        raise garbled(f"columns {header}, expected {list(COLUMNS)}")
    try:  # the complete lines (an interrupted write leaves an incomplete last one)
        rows = list(csv.DictReader(io.StringIO(text[:text.rfind("\n") + 1])))
    except csv.Error as err:
        raise garbled(f"bad CSV: {err}") from None
    rows = [r for r in rows if None not in r.values()]
    for i, r in enumerate(rows):
        try:
            int(r["seed"])
        except ValueError:
            raise garbled(f"row {i + 2}: seed {r['seed']!r} is not an integer") from None
    csvlog.read_complete(path)  # a results file: cut the incomplete line off it now
    return rows


def append_row(path: Path, row: Mapping) -> None:
    """Append one row with a single write, flushed and fsynced (header first if new)."""
    buf = io.StringIO()
    writer = csv.DictWriter(buf, COLUMNS, lineterminator="\n")
    if csvlog.is_empty(path):
        writer.writeheader()
    writer.writerow({k: _fmt(row.get(k, "")) for k in COLUMNS})
    csvlog.append(path, buf.getvalue())


def _fmt(v):
    if isinstance(v, float):
        return repr(v) if math.isfinite(v) else str(v)
    return v


# ----------------------------------------------------------------------------- running

def _error_text(err: BaseException) -> str:
    text = f"{type(err).__name__}: {err}".strip().splitlines()[0]
    return text[:300]


def _row(task, method, seed, budget, **values) -> dict:
    row = dict.fromkeys(COLUMNS, "")
    row.update(task=task, method=method, seed=seed, budget=budget, **values)
    return row


def evaluate(out, runnable) -> dict:
    """Row values from an :class:`EpisodeOutput` (NumPy), with the failure checks."""
    score = float(out.score)
    finite = np.asarray(out.finite)
    stats = out.stats
    values = dict(score=score, final_distance=float(np.asarray(out.distance)[-1]),
                  env_steps=runnable.env_steps, backprop_steps=runnable.backprop_steps)
    status, error = "ok", ""
    bad_grads = int(np.sum(stats.nonfinite_grads))
    if runnable.uses_gradients:
        steps = int(np.sum(stats.grad_steps))
        gmax = np.asarray(stats.grad_norm_max, np.float64)
        values.update(grad_norm=float(np.max(gmax)) if gmax.size else math.nan,
                      grad_norm_mean=float(np.sum(stats.grad_norm_sum))
                      / max(steps - bad_grads, 1),
                      nonfinite_grads=bad_grads)
        if bad_grads and not runnable.nan_grads_zeroed:
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


RUN_FILE = "run.json"


def _canonical(value):
    """JSON-able form of run overrides (a scene dataclass by class and fields)."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {"__class__": type(value).__name__,
                **{f.name: _canonical(getattr(value, f.name))
                   for f in dataclasses.fields(value)}}
    if isinstance(value, Mapping):
        return {str(k): _canonical(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_canonical(v) for v in value]
    if isinstance(value, np.generic | np.ndarray):
        return value.tolist()
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    return repr(value)


def check_out(out: Path) -> Path:
    """``out/results.csv`` once ``out`` is known to be a directory we can write (created if
    missing) whose results file, report and run file are files if they exist; one
    ``ValueError`` naming the path otherwise, before any work."""
    if out.exists() and not out.is_dir():
        raise ValueError(f"{out}: exists and is not a directory (--out takes a directory)")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise ValueError(f"{out}: cannot create the output directory "
                         f"({err.strerror or err})") from None
    try:  # a probe: an unwritable directory is found now, not after the first episode
        with tempfile.TemporaryFile(dir=out):
            pass
    except OSError as err:
        raise ValueError(f"{out}: cannot write in the output directory "
                         f"({err.strerror or err})") from None
    for name in ("results.csv", "results.md", RUN_FILE):
        path = out / name
        if path.exists() and not path.is_file():
            raise ValueError(f"{path}: exists and is not a file; use another --out directory")
        if path.exists() and not os.access(path, os.R_OK | os.W_OK):
            raise ValueError(f"{path}: cannot be read and written")
    return out / "results.csv"


def read_run_file(out: Path) -> dict:
    """``out/run.json`` (``{}`` if there is none); ``ValueError`` naming it if unreadable."""
    path = Path(out) / RUN_FILE
    if not path.exists():
        return {}
    try:
        old = json.loads(path.read_text())
        if not isinstance(old, dict):
            raise ValueError("not a JSON object")
    except ValueError as err:  # UnicodeDecodeError and JSONDecodeError too
        raise ValueError(f"{path}: unreadable run file ({err}); use another --out "
                         f"directory") from None
    return old


#: the packages whose versions a run records (run.json) and the results page shows
VERSIONED = ("dax-physics", "dax-tasks", "dax-data", "dax-algos", "jax", "jaxlib", "numpy",
             "flax", "optax", "matplotlib", "pillow")


def machine_info() -> dict:
    """The machine a run ran on: platform, Python, CPU count, JAX backend and devices."""
    return {"platform": platform.platform(), "python": platform.python_version(),
            "cpu_count": os.cpu_count(), "jax_backend": jax.default_backend(),
            "jax_devices": [str(d) for d in jax.devices()]}


def package_versions() -> dict:
    """``{package: version}`` of :data:`VERSIONED` (``"not installed"`` for a missing one)."""
    out = {}
    for name in VERSIONED:
        try:
            out[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            out[name] = "not installed"
    return out


def _check_run(out: Path, rows: list, config: dict, command: str) -> None:
    """Refuse to add to ``out`` results made with other task or method overrides (they
    would be mixed with, or silently stand in for, this run's); record them on first
    use in ``out/run.json``, and with them each new command line (``invocations``: the
    command, when it started, the machine and the package versions; a resumed run with
    the same command adds nothing)."""
    path = out / RUN_FILE
    old = read_run_file(out)
    if not old and rows:  # results from before run files: runs without overrides
        old = {"task_overrides": {}, "method_overrides": {}}
    for key in ("task_overrides", "method_overrides"):
        if old and old.get(key, {}) != config[key]:
            raise ValueError(
                f"{out}: holds results made with other {key.replace('_', ' ')} "
                f"({json.dumps(old.get(key, {}), sort_keys=True)[:200]}, now "
                f"{json.dumps(config[key], sort_keys=True)[:200]}); use another --out "
                f"directory")
    new = {**config, **old}
    invocations = list(new.get("invocations", []))
    if not any(isinstance(i, dict) and i.get("command") == command for i in invocations):
        started = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
        invocations.append({"command": command, "started": started,
                            "machine": machine_info(), "versions": package_versions()})
    new["invocations"] = invocations
    if new != old:
        atomic_write(path, json.dumps(new, indent=1, sort_keys=True) + "\n")


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
    ``results.csv`` is a results file (:func:`check_out`, :func:`read_rows`), no other run
    may be writing it (its lock, ``.results.csv.lock``, :func:`dax_tasks.io.exclusive`:
    ``FileLockedError`` naming the holder), and results already there must have been made
    with the same task and method overrides (recorded in ``run.json``); each problem is one
    error naming the path."""
    task_names = resolve_tasks(tasks)
    method_names = resolve_methods(methods)
    if backend not in BACKENDS:
        raise ValueError(f"unknown backend {backend!r}; valid: {', '.join(BACKENDS)}")
    if backend == "ray":
        from . import backends

        backends.require_ray()
        if not ray_cpus > 0:
            raise ValueError(f"ray_cpus (--ray-cpus) must be positive, got {ray_cpus!r}")
    elif ray_address:
        raise ValueError("--ray-address is for --backend ray (the backend is local)")
    if not (isinstance(seeds, int) and not isinstance(seeds, bool) and seeds > 0):
        raise ValueError(f"seeds must be a positive int, got {seeds!r}")
    budget = "quick" if quick else "full"
    task_overrides = dict(task_overrides or {})
    method_overrides = dict(method_overrides or {})
    out = Path(out)
    csv_path = check_out(out)
    config = {"task_overrides": _canonical(task_overrides),
              "method_overrides": _canonical(method_overrides)}
    with exclusive(csv_path):
        rows = read_rows(csv_path)
        _check_run(out, rows, config, command or cli_command(
            task_names, method_names, seeds, out, quick, backend, ray_address))
        return _run_grid_locked(task_names, method_names, seeds, out, csv_path, budget, rows,
                                task_overrides, method_overrides, cache_goal, progress,
                                demo_dir, backend, dict(address=ray_address,
                                                        num_cpus=ray_cpus))


def _run_grid_locked(task_names, method_names, seeds, out, csv_path, budget, rows,
                     task_overrides, method_overrides, cache_goal, progress,
                     demo_dir, backend="local", ray_options=None) -> list[dict]:
    """:func:`run_grid` while holding the results' lock."""
    done = {(r["task"], r["method"], int(r["seed"]), r["budget"]) for r in rows}
    todo = [(t, m, s) for t in task_names for m in method_names for s in range(seeds)
            if (t, m, s, budget) not in done]

    bar = tqdm(total=len(todo), desc="dax-bench", unit="run", disable=not progress,
               file=sys.stderr)

    def finished(result):  # the driver alone writes the output directory
        record(out, result)
        bar.update()

    envs = {}
    try:
        if backend == "ray":
            from . import backends

            backends.run_ray(todo, budget, task_overrides, method_overrides, cache_goal,
                             demo_dir, finished, **(ray_options or {}))
        else:
            _run_local(todo, task_names, method_names, budget, task_overrides,
                       method_overrides, cache_goal, demo_dir, envs, finished, bar)
    finally:
        bar.close()
    rows = read_rows(csv_path)

    def make_env(task):  # the task as this run built it
        if task not in envs:
            envs[task] = dax_tasks.make(task, cache_goal=cache_goal,
                                        **task_overrides.get(task, {}))
        return envs[task]

    write_reports(rows, out, budget, make_env)
    return rows


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
                finished(_task_failed(t, m, s, budget, err))
            continue
        for m in method_names:
            m_seeds = [s for mm, s in t_todo if mm == m]
            if not m_seeds:
                continue
            bar.set_postfix_str(f"{t} / {m}")
            for result in _run_method(env, t, m, m_seeds, budget, method_overrides.get(m, {}),
                                      demo_dir, task_overrides.get(t)):
                finished(result)
        jax.clear_caches()


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
        row = _row(t, m, s, budget, status="failed", compile_s=row.get("compile_s", ""),
                   error=_error_text(err))
    append_row(out / "results.csv", row)


def _task_failed(t, m, s, budget, err) -> SeedResult:
    return SeedResult(_row(t, m, s, budget, status="failed",
                           error="building the task: " + _error_text(err)))


def run_one(task: str, method: str, seed: int, budget: str, task_overrides: Mapping,
            method_overrides: Mapping, cache_goal: bool = True,
            demo_dir: str | None = None) -> SeedResult:
    """One (task, method, seed) from plain data, in a process of its own (a Ray worker):
    builds the task and the method, compiles and runs the seed; writes nothing (the driver
    records the result, :func:`record`)."""
    _default_compilation_cache()
    try:
        env = dax_tasks.make(task, cache_goal=cache_goal, **task_overrides)
    except Exception as err:  # noqa: BLE001
        return _task_failed(task, method, seed, budget, err)
    (result,) = _run_method(env, task, method, [seed], budget, method_overrides, demo_dir,
                            task_overrides or None)
    return result


def _run_method(env, t, m, seeds, budget, overrides, demo_dir=None, task_overrides=None):
    """The :class:`SeedResult` of each of ``seeds`` (a generator): the method's episode is
    built and compiled once, then called per seed with ``PRNGKey(seed)``. Every seed is
    computed the same way whichever seeds run with it (and under either backend), so its
    values do not depend on the grid: a learner's seeds are not batched under ``vmap``."""
    params = env.default_params
    try:  # (a method registered in the driver only is unknown to a Ray worker: a failed row)
        method = registry.get(m)
        config = method.config(budget, t, **overrides)
        runnable = method.build(env, config)
        data = ()
        if runnable.demos is not None:  # an imitation method: its demonstrations first
            path = demos.locate(env, runnable.demos, demo_dir, task_overrides)
            data = (runnable.demos.load(env, path),)
        t0 = time.perf_counter()
        compiled = jax.jit(runnable.episode).lower(jax.random.PRNGKey(0), params,
                                                   *data).compile()
        compile_s = time.perf_counter() - t0
    except Exception as err:  # noqa: BLE001
        status = "skipped" if isinstance(err, common.NotApplicable) else "failed"
        for s in seeds:
            yield SeedResult(_row(t, m, s, budget, status=status, error=_error_text(err)))
        return
    for s in seeds:
        try:
            t0 = time.perf_counter()
            out = jax.device_get(jax.block_until_ready(
                compiled(jax.random.PRNGKey(s), params, *data)))
            wall = time.perf_counter() - t0
            make = _learner_result if runnable.learns else _planner_result
            result = make(env, t, m, s, budget, config, runnable, out, wall, compile_s)
        except Exception as err:  # noqa: BLE001
            result = SeedResult(_row(t, m, s, budget, status="failed", compile_s=compile_s,
                                     error=_error_text(err)))
        yield result


def _planner_result(env, t, m, s, budget, config, runnable, out, wall, compile_s):
    row = _row(t, m, s, budget, wall_s=wall, compile_s=compile_s, **evaluate(out, runnable))
    episode = dict(reset_key=episodes.planner_reset_key(s), actions=np.asarray(out.actions),
                   score=float(out.score), fingerprint=env.spec.fingerprint(), budget=budget)
    return SeedResult(row, episode)


def _learner_result(env, t, m, s, budget, config, runnable, out, wall, compile_s):
    """A learner's seed: its row, its learning curve (``wall_s`` prorated over the updates,
    which all have the same shape), its first evaluation rollout and its trained policy
    (``policies/<task>/<method>/seed<k>.msgpack``, unless it is not finite)."""
    metrics = out.metrics
    n = len(metrics.env_steps)
    curve = None
    if runnable.train_env_steps:  # no curve for training on demonstrations only
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
    row = _row(t, m, s, budget, wall_s=wall, compile_s=compile_s, **evaluate(ep, runnable))
    return SeedResult(row, episode, curve, policy)


def write_reports(rows, out: Path, budget: str, make_env=None) -> Path:
    """Rewrite ``results.md``, the charts and the results page (``index.html``, with the
    median seed's episode of each (task, method) drawn unless it already is) from the rows
    of ``budget``; returns the page's path. ``make_env(task)`` builds a task as the run did
    (default: with the task overrides recorded in ``run.json``)."""
    rows = [r for r in rows if r["budget"] == budget]
    text = report.markdown(rows, dax_tasks.TASKS, registry.names(),
                           title=f"DaX benchmark ({budget} budget)")
    atomic_write(out / "results.md", text)
    report.charts(rows, out, registry.names())
    done = {(r["task"], r["method"], int(r["seed"]), r["budget"]) for r in rows}
    for task in dict.fromkeys(r["task"] for r in rows):
        path = learning.learning_path(out, task)
        if path.exists():
            learning.charts(learning.read_curves(path, keep=done), out, registry.names())
    run = read_run_file(out)
    if make_env is None:
        overrides = run.get("task_overrides", {})

        def make_env(task):
            return dax_tasks.make(task, **overrides_from_json(task, overrides.get(task, {})))

    tasks = _order(dax_tasks.TASKS, rows, "task")
    methods = _order(registry.names(), rows, "method")
    pictures = episodes.episode_pictures(out, rows, make_env, tasks, methods)
    return page.write_page(out, rows, run, pictures, tasks, methods,
                           title=f"DaX benchmark ({budget} budget)")


def report_dir(out, budget: str | None = None) -> Path:
    """Write the reports of the output directory ``out`` again (:func:`write_reports`,
    holding its results' lock); returns the page's path. ``budget``: whose rows (default:
    the last row's). ``ValueError`` naming the problem for a directory without results."""
    out = Path(out)
    csv_path = out / "results.csv"
    if not csv_path.is_file():
        raise ValueError(f"{csv_path}: no such results file (run dax-bench run --out {out} "
                         f"first)")
    with exclusive(csv_path):
        rows = read_rows(csv_path)
        if not rows:
            raise ValueError(f"{csv_path}: holds no runs")
        budget = rows[-1]["budget"] if budget is None else budget
        if not any(r["budget"] == budget for r in rows):
            raise ValueError(f"{csv_path}: holds no runs of the {budget} budget")
        return write_reports(rows, out, budget)


def _order(preferred, rows, col) -> list:
    seen = list(dict.fromkeys(r[col] for r in rows))
    return [x for x in preferred if x in seen] + sorted(x for x in seen if x not in preferred)


def overrides_from_json(task: str, data: Mapping) -> dict:
    """A task's ``make`` overrides from their ``run.json`` form (:func:`_canonical`): a
    scene recorded by class and fields is rebuilt from the task's default scene, lists
    become tuples where the default is one."""
    spec = dax_tasks.get_spec(task)

    def decode(default, value):
        if isinstance(value, Mapping) and "__class__" in value:
            if not dataclasses.is_dataclass(default) \
                    or type(default).__name__ != value["__class__"]:
                raise ValueError(f"run.json: task {task}: cannot rebuild a "
                                 f"{value['__class__']} (the task's is "
                                 f"{type(default).__name__})")
            fields = {k: decode(getattr(default, k, None), v) for k, v in value.items()
                      if k != "__class__"}
            return dataclasses.replace(default, **fields)
        if isinstance(value, list) and isinstance(default, tuple):
            like = [default[min(i, len(default) - 1)] if default else None
                    for i in range(len(value))]
            return tuple(decode(d, v) for d, v in zip(like, value, strict=True))
        return value

    return {k: decode(getattr(spec, k, None), v) for k, v in data.items()}


# ----------------------------------------------------------------------------- CLI

def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="dax-bench", description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="run tasks x methods x seeds")
    run.add_argument("--tasks", default="all", help="comma-separated task names, or all")
    run.add_argument("--methods", default="all", help="comma-separated method names, or all")
    run.add_argument("--seeds", type=int, default=1, help="number of seeds K (seeds 0..K-1)")
    run.add_argument("--quick", action="store_true", help="small planner budgets (smoke run)")
    run.add_argument("--out", default="results", help="output directory")
    run.add_argument("--demos", default=None, metavar="DIR",
                     help="where the imitation methods' demonstration sets are recorded or "
                          "reused (default: $DAX_CACHE_DIR/demos, ~/.cache/dax/demos)")
    run.add_argument("--backend", default="local", choices=BACKENDS,
                     help="where the runs run: local (this process, the default) or ray "
                          "(one Ray task per task x method x seed; pip install "
                          "'dax-algos[ray]')")
    run.add_argument("--ray-address", default=None, metavar="ADDRESS",
                     help="the Ray cluster to use with --backend ray, e.g. "
                          "ray://head:10001 or auto (default: $RAY_ADDRESS, else a Ray "
                          "instance started on this machine)")
    run.add_argument("--ray-cpus", type=float, default=1, metavar="N",
                     help="CPUs each Ray task reserves (default 1)")
    run.add_argument("--no-progress", action="store_true", help="no progress bar")
    rep = sub.add_parser("report", help="write the results page (index.html) and tables of "
                                        "an output directory again")
    rep.add_argument("--out", default="results", help="output directory of a run")
    rep.add_argument("--budget", default=None, choices=registry.BUDGETS,
                     help="the budget's rows (default: the budget of the last row)")
    sub.add_parser("list", help="list the tasks and methods")
    return p


def _default_compilation_cache() -> None:
    """Use the persistent XLA cache ``~/.cache/dax/jax`` (as the test sessions do) unless
    one is configured, so a second run does not recompile."""
    if os.environ.get("JAX_COMPILATION_CACHE_DIR") or jax.config.jax_compilation_cache_dir:
        return
    cache = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "dax" / "jax"
    jax.config.update("jax_compilation_cache_dir", str(cache))


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    if args.command == "list":
        declared, available = _task_names()
        print("tasks:", ", ".join(available), f"(declared: {', '.join(declared)})")
        print("methods:", ", ".join(registry.names()))
        return 0
    _default_compilation_cache()
    try:
        if args.command == "report":
            index = report_dir(args.out, args.budget)
            print(index.resolve())
            return 0
        command = shlex.join(["dax-bench", *(sys.argv[1:] if argv is None else argv)])
        rows = run_grid(args.tasks, args.methods, args.seeds, args.out, quick=args.quick,
                        progress=not args.no_progress, demo_dir=args.demos, command=command,
                        backend=args.backend, ray_address=args.ray_address,
                        ray_cpus=args.ray_cpus)
    except (ValueError, OSError) as err:  # FileLockedError is an OSError
        msg = " ".join(str(err).split()) or type(err).__name__
        print(f"dax-bench: error: {msg}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"dax-bench: interrupted; finished runs are in {Path(args.out) / 'results.csv'}"
              f" (run the same command again to resume)", file=sys.stderr)
        return 130
    failed = sum(r["status"] == "failed" for r in rows)
    print(f"{len(rows)} rows in {Path(args.out) / 'results.csv'} ({failed} failed); "
          f"table: {Path(args.out) / 'results.md'}; results page:")
    print((Path(args.out) / page.PAGE).resolve())  # the last line: the page to open
    return 0


if __name__ == "__main__":
    sys.exit(main())
