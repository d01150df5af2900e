"""The benchmark runner: every task x method x seed, evaluated with r_gt only.

The ``dax-bench`` command::

    dax-bench run [--preset demo|cloth|paper] [--tasks T1,T2|all] [--methods M1,M2|all]
                  [--seeds K|A-B] [--quick | --budget quick|full] [--out DIR]
                  [--max-minutes N] [--no-retry-failed] [--include-stale]
                  [--rerun-stale]
    dax-bench report --out DIR [--budget quick|full] [--include-stale] [--markdown]
    dax-bench merge --into DIR SRC [SRC ...] [--lock-timeout SECONDS]
    dax-bench list

``run`` runs the grid (:func:`dax_algos.bench.grid.run_grid`: resumable, failed runs
retried, one results row per run, :mod:`dax_algos.bench.rows`; a preset names a grid,
:mod:`dax_algos.bench.presets`), ``report`` rewrites a directory's reports and results
page (:func:`dax_algos.bench.summary.report_dir`) or prints its score table as Markdown,
``merge`` gathers the output directories of a grid run in pieces (on several machines)
into one (:func:`dax_algos.bench.merge.merge_dirs`) and rewrites its reports, ``list``
lists the tasks, methods and presets. A bad argument, output directory or results file
is one line ``dax-bench: error: ...`` and exit status 2; a failed run of the
grid, one line naming it and exit status 1; runs left when ``--max-minutes`` ran out, one
line and exit status 3.
"""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path

import dax_tasks

from .. import method, registry
from . import grid, merge, page, presets, summary
from .execute import use_default_compilation_cache


def _seeds(text: str) -> range:
    try:
        return grid.parse_seeds(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None


def _minutes(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not value > 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"expected a positive number of minutes, got {text!r}")
    return value


def _seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not value >= 0:
        raise argparse.ArgumentTypeError(f"expected seconds >= 0, got {text!r}")
    return value


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="dax-bench", description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="run tasks x methods x seeds")
    run.add_argument("--preset", choices=list(presets.PRESETS), default=None,
                     help="a named grid (" + "; ".join(f"{k}: {v.what}" for k, v in
                                                     presets.PRESETS.items())
                     + "); the options given replace its values")
    run.add_argument("--tasks", default=None, help="comma-separated task names, or all "
                                                   "(default: all)")
    run.add_argument("--methods", default=None, help="comma-separated method names, or all "
                                                     "(default: all)")
    run.add_argument("--seeds", type=_seeds, default=None,
                     help=f"number of seeds K (seeds 0..K-1, K <= {grid.MAX_SEEDS}; default 1), "
                          f"or seeds A-B (A..B, both included: a piece of a grid run "
                          f"elsewhere too, gathered with merge)")
    run.add_argument("--quick", action="store_const", const="quick", dest="budget",
                     help="the quick budgets (a smoke run; the same as --budget quick)")
    run.add_argument("--budget", choices=method.BUDGETS, default=None,
                     help="quick or full (default: full, or the preset's)")
    run.add_argument("--out", default=None, help="output directory (default: results, or "
                                                 "the preset's)")
    run.add_argument("--max-minutes", type=_minutes, default=None, metavar="N",
                     help="start no run after N minutes: the runs under way finish, the "
                          "reports are written and one line says what is left (exit status "
                          "3); the same command again continues")
    run.add_argument("--no-retry-failed", action="store_true",
                     help="leave runs recorded as failed as they are (default: run them "
                          "again; the new row keeps the old errors in previous_errors)")
    run.add_argument("--include-stale", action="store_true",
                     help="count stale rows in the reports' tables and means (marked)")
    run.add_argument("--rerun-stale", action="store_true",
                     help="run again the runs whose rows are stale (measured on other code, "
                          "task spec or method config than today's); the new rows count")
    run.add_argument("--demos", default=None, metavar="DIR",
                     help="where the imitation methods' demonstration sets are recorded or "
                          "reused (default: $DAX_CACHE_DIR/demos, ~/.cache/dax/demos)")
    run.add_argument("--backend", default="local", choices=grid.BACKENDS,
                     help="where the runs run: local (this process, the default) or ray "
                          "(one Ray task per task x method x seed; pip install "
                          "'dax-algos[ray]')")
    run.add_argument("--ray-address", default=None, metavar="ADDRESS",
                     help="the Ray cluster to use with --backend ray, e.g. "
                          "ray://head:10001 or auto (default: $RAY_ADDRESS, else a Ray "
                          "instance started on this machine)")
    run.add_argument("--ray-cpus", type=float, default=1, metavar="N",
                     help="CPUs each Ray task reserves (default 1)")
    run.add_argument("--no-progress", action="store_true", help="no progress line")
    run.add_argument("--lock-timeout", type=_seconds, default=0.0, metavar="SECONDS",
                     help="wait up to this long for another run writing the same --out "
                          "(saying who it is) instead of refusing at once (default 0)")
    rep = sub.add_parser("report", help="write the results page (index.html) and tables of "
                                        "an output directory again")
    rep.add_argument("--out", default="results", help="output directory of a run")
    rep.add_argument("--budget", default=None, choices=method.BUDGETS,
                     help="the budget's rows (default: the budget of the last row)")
    rep.add_argument("--include-stale", action="store_true",
                     help="count stale rows in the tables and means (marked †)")
    rep.add_argument("--markdown", action="store_true",
                     help="print the score table as Markdown (what a README holds) "
                          "instead of writing the reports")
    mer = sub.add_parser("merge", help="add to one output directory the runs it lacks from "
                                       "others (pieces of one grid run elsewhere)")
    mer.add_argument("--into", required=True, help="the output directory merged into")
    mer.add_argument("sources", nargs="+", metavar="SRC", help="output directories of "
                                                               "pieces of the same grid")
    mer.add_argument("--lock-timeout", type=_seconds, default=0.0, metavar="SECONDS",
                     help="wait up to this long for a run writing --into (default 0)")
    sub.add_parser("list", help="list the tasks, methods and presets")
    return p


def _grid_args(args) -> dict:
    """The grid of a ``run`` command: the preset's values (its method overrides
    included), replaced by those given."""
    pre = presets.get(args.preset) if args.preset else None

    def pick(name, default):
        given = getattr(args, name)
        return given if given is not None else (getattr(pre, name) if pre else default)

    budget = args.budget or ("quick" if pre and pre.quick else "full")
    return dict(tasks=pick("tasks", "all"), methods=pick("methods", "all"),
                seeds=pick("seeds", 1), out=pick("out", "results"), quick=budget == "quick",
                method_overrides=dict(pre.method_overrides) if pre else {})


def main(argv=None) -> int:
    """The ``dax-bench`` console script; returns the exit status: 0, 1 (a run of the grid
    failed: one line says which and why), 2 (a bad argument, output directory or results
    file: one line), 3 (``--max-minutes`` ran out with runs left: one line says which),
    130 (interrupted)."""
    args = _parser().parse_args(argv)
    if args.command == "list":
        print("tasks:", ", ".join(dax_tasks.available()),
              f"(declared: {', '.join(dax_tasks.TASKS)})")
        print("methods:", ", ".join(registry.names()))
        print("presets:", "; ".join(f"{k} ({v.what})" for k, v in presets.PRESETS.items()))
        return 0
    use_default_compilation_cache()
    out = args.into if args.command == "merge" else args.out
    try:
        if args.command == "report":
            if args.markdown:
                print(summary.markdown_tables(args.out, args.budget, args.include_stale),
                      end="")
                return 0
            index = summary.report_dir(args.out, args.budget, args.include_stale)
            print(index.resolve())
            return 0
        if args.command == "merge":
            done = merge.merge_dirs(args.into, args.sources, args.lock_timeout)
            print(done.line(Path(args.into)))
            print(summary.report_dir(args.into).resolve())
            return 0
        command = shlex.join(["dax-bench", *(sys.argv[1:] if argv is None else argv)])
        g = _grid_args(args)
        out = g["out"]
        rows = grid.run_grid(**g, progress=not args.no_progress, demo_dir=args.demos,
                             command=command, backend=args.backend,
                             ray_address=args.ray_address, ray_cpus=args.ray_cpus,
                             retry_failed=not args.no_retry_failed,
                             max_minutes=args.max_minutes, include_stale=args.include_stale,
                             lock_wait=args.lock_timeout, rerun_stale=args.rerun_stale)
    except (ValueError, OSError) as err:  # FileLockedError is an OSError
        msg = " ".join(str(err).split()) or type(err).__name__
        print(f"dax-bench: error: {msg}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"dax-bench: interrupted; finished runs are in {Path(out) / 'results.csv'}"
              f" (run the same command again to resume)", file=sys.stderr)
        return 130
    return _finish(rows, Path(g["out"]), g)


def _finish(rows, out: Path, g: dict) -> int:
    """Print what the run wrote (the page's path last) and the exit status's reason."""
    mine = grid.rows_of(rows, g["tasks"], g["methods"], g["seeds"],
                        "quick" if g["quick"] else "full")
    failed = [r for r in mine if r["status"] == "failed"]
    print(f"{len(mine)} runs of this grid in {out / 'results.csv'} ({len(failed)} failed"
          f"{f', {rows.left} left' if rows.left else ''}); table: {out / 'results.md'}; "
          f"results page:")
    print((out / page.PAGE).resolve())  # the page to open
    status = 0
    if failed:
        print(f"dax-bench: {failure_line(failed, len(mine))}", file=sys.stderr)
        status = 1
    if rows.left:
        print(f"dax-bench: stopped at the time limit: {rows.left_text()}", file=sys.stderr)
        status = status or 3
    return status


def failure_line(failed, total: int) -> str:
    """One line: how many of ``total`` runs failed, and for each (task, method) which
    seeds and the first error."""
    groups: dict = {}
    for r in failed:
        groups.setdefault((r["task"], r["method"]), []).append(r)
    parts = [f"{t} / {m} seed{'s' if len(rs) > 1 else ''} "
             f"{','.join(str(r['seed']) for r in rs)}: {rs[0]['error'][:160]}"
             for (t, m), rs in groups.items()]
    text = f"{len(failed)} of {total} runs failed: " + "; ".join(parts)
    return (text[:600] + " ...") if len(text) > 600 else text


if __name__ == "__main__":
    sys.exit(main())
