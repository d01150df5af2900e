"""Merge the output directories of one grid run in pieces on several machines
(``dax-bench merge --into DIR SRC ...``).

A grid can be split by task or method (``dax-bench run --tasks ... --methods ...``), each
piece run where it runs best (a GPU for the batched MPM planners, the CPUs for the rest)
into its own ``--out`` directory, and the pieces gathered into one. For each source
directory, :func:`merge_dirs` adds to ``into``:

* the rows of every run (task, method, seed, budget) that ``into`` has no row for, in the
  source's file order (a failed row and its retry both come), each with its ``device``,
  ``versions`` and ``commit`` as the source recorded them; a run ``into`` already has is
  left as it is (its row counts; the source's is reported as skipped), unless ``into``'s
  row that counts failed and the source's did not: then the source's rows come as the
  retry of ``into``'s (their ``previous_errors`` begin with ``into``'s error history), as
  if the run had been resumed there; or unless ``into``'s row that counts is stale
  (measured on other code, task spec or method config than today's,
  :func:`~.provenance.stale_reason`, under ``into``'s overrides) and the source's is not
  and did not fail: then the source's rows come after it and count, as if the run had
  been run again there with ``--rerun-stale``;
* for each added run, its episode files (``episodes/<task>/<method>/seed<k>*``), its
  policy (``policies/<task>/<method>/seed<k>*``) and its learning-curve rows, all written
  before its row, as the runner writes them, so an interrupted merge leaves no row without
  its files (the files of a run whose row did not land are copied again on the next merge);
* the source's ``run.json`` invocations that ``into`` lacks (command, start, machine and
  package versions: where each row was made).

The sources must have been made with the same task and method overrides and in the same
precision as ``into`` (the checks ``dax-bench run`` makes), and no run may be writing
``into`` (its lock). ``dax-bench merge`` then writes the reports and the page again
(:func:`dax_algos.bench.summary.report_dir`).
"""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

from dax_tasks.io import atomic_write, exclusive

from . import learning, provenance, rundir, summary
from .episodes import DIR as EPISODES
from .rows import append_row, errors_of, key, latest, previous_errors, read_rows, upgrade

#: where a run's policy files are kept (``policies/<task>/<method>/seed<k>.msgpack``)
POLICIES = "policies"


@dataclasses.dataclass
class Merged:
    """What :func:`merge_dirs` did: the runs added and skipped (``(task, method, seed,
    budget)`` each), and the files copied."""

    added: list = dataclasses.field(default_factory=list)
    skipped: list = dataclasses.field(default_factory=list)
    files: int = 0

    def line(self, into: Path) -> str:
        return (f"{len(self.added)} runs merged into {into / 'results.csv'} ({self.files} "
                f"files copied); {len(self.skipped)} already there, left as they were")


def _copy(src: Path, dst: Path) -> None:
    """Copy one file so that ``dst`` is never half-written (:func:`atomic_write`)."""
    dst.parent.mkdir(parents=True, exist_ok=True)
    with open(src, "rb") as f:
        atomic_write(dst, lambda out: shutil.copyfileobj(f, out))


def _run_files(source: Path, task: str, method: str, seed: int) -> list[Path]:
    """The episode and policy files of one run in ``source`` (relative paths)."""
    found = []
    for top in (EPISODES, POLICIES):
        folder = source / top / task / method
        if folder.is_dir():
            found += [p.relative_to(source) for p in sorted(folder.iterdir())
                      if p.is_file() and (p.name.split(".")[0] == f"seed{seed}"
                                          or p.name.startswith(f"seed{seed}-"))]
    return found


def _check_source(into: Path, source: Path, into_run: dict, into_rows: list) -> tuple:
    """The source's rows and run file, after the checks ``dax-bench run`` makes."""
    if source.resolve() == into.resolve():
        raise ValueError(f"{source}: is the directory merged into")
    csv_path = source / "results.csv"
    if not csv_path.is_file():
        raise ValueError(f"{source}: has no results.csv (not a dax-bench output directory)")
    rows = read_rows(csv_path)
    run = rundir.read_run_file(source)
    field = rundir.other_overrides(into_run, bool(into_rows), run)
    if field:
        raise ValueError(
            f"{source}: made with other {field.replace('_', ' ')} than {into} "
            f"({json.dumps(run.get(field, {}), sort_keys=True)[:200]}, there "
            f"{json.dumps(into_run.get(field, {}), sort_keys=True)[:200]}); merge only "
            f"pieces of one grid")
    precisions = {r["precision"] for r in into_rows + rows if r["precision"]}
    if len(precisions) > 1:
        raise ValueError(f"{source}: its rows and those of {into} were computed in "
                         f"{' and '.join(sorted(precisions))}; one grid, one precision")
    return rows, run


def merge_dirs(into, sources, lock_wait: float = 0.0) -> Merged:
    """Add to the output directory ``into`` the runs of each directory of ``sources`` that
    it lacks (see the module docstring); returns what was added and skipped. A problem
    (a source that is not an output directory, other overrides or precision, a locked
    ``into``) is a ``ValueError`` or ``OSError`` naming the directory, raised before
    anything is written for that source."""
    into = Path(into)
    csv_path = rundir.check_out(into)
    done = Merged()
    with exclusive(csv_path, wait=lock_wait):
        for source in map(Path, sources):
            into_rows = read_rows(csv_path)
            into_run = rundir.read_run_file(into)
            rows, run = _check_source(into, source, into_run, into_rows)
            upgrade(csv_path, into_rows)
            history = _retried(into_rows, rows)
            have = {key(r) for r in into_rows} - set(history) - _refreshed(
                into_rows, rows, into_run)
            new = [r for r in rows if key(r) not in have]
            done.skipped += sorted({key(r) for r in rows if key(r) in have})
            curves = {}
            for r in new:
                k = key(r)
                if k in history:  # the retry of into's failed run
                    r = {**r, "previous_errors": json.dumps(history[k] + previous_errors(r))}
                if k in done.added:  # a failed run and its retry: files and curve once
                    append_row(csv_path, r)
                    continue
                task, method, seed, budget = k
                for rel in _run_files(source, task, method, seed):
                    _copy(source / rel, into / rel)
                    done.files += 1
                if task not in curves:
                    path = learning.learning_path(source, task)
                    curves[task] = learning.read_curves(path) if path.exists() else []
                curve = [c for c in curves[task] if (c["task"], c["method"], c["seed"],
                                                     c["budget"]) == k]
                if curve:
                    learning.append_curve(learning.learning_path(into, task), curve)
                append_row(csv_path, r)
                done.added.append(k)
            _add_invocations(into, into_run, run)
    return done


def _retried(into_rows: list, rows: list) -> dict:
    """``{run: into's error history}`` for each run whose row that counts failed in
    ``into`` (:func:`~.rows.latest`) and did not in the source: the source's rows retry
    it."""
    theirs = {key(r): r["status"] for r in latest(rows)}
    return {key(r): errors_of(r) for r in latest(into_rows)
            if r["status"] == "failed" and theirs.get(key(r), "failed") != "failed"}


def _refreshed(into_rows: list, rows: list, into_run: dict) -> set:
    """The runs whose row that counts in ``into`` is stale today (under ``into``'s task
    and method overrides) and whose row that counts in the source is not and did not fail:
    the source's rows come after ``into``'s and count."""
    today = summary.today_of(into_run)
    theirs = {key(r): r for r in latest(rows)}
    return {key(r) for r in latest(into_rows)
            if key(r) in theirs and theirs[key(r)]["status"] != "failed"
            and provenance.stale_reason(r, today)
            and not provenance.stale_reason(theirs[key(r)], today)}


def _add_invocations(into: Path, into_run: dict, run: dict) -> None:
    """Append the source's ``run.json`` invocations that ``into``'s lacks (atomically)."""
    mine = list(into_run.get("invocations", []))
    extra = [i for i in run.get("invocations", []) if i not in mine]
    if not extra and into_run:
        return
    merged = {**{k: run.get(k, {}) for k in rundir.OVERRIDES}, **into_run,
              "invocations": mine + extra}
    atomic_write(into / rundir.RUN_FILE, json.dumps(merged, indent=1, sort_keys=True) + "\n")
