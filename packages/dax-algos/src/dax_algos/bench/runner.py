"""The benchmark runner: every task x method x seed, evaluated with r_gt only.

The ``dax-bench`` command::

    dax-bench run --tasks T1,T2|all --methods M1,M2|all --seeds K [--quick] --out DIR
    dax-bench report --out DIR [--budget quick|full]
    dax-bench list

``run`` runs the grid (:func:`dax_algos.bench.grid.run_grid`: resumable, one results row
per run, :mod:`dax_algos.bench.rows`), ``report`` rewrites a directory's reports and
results page (:func:`dax_algos.bench.summary.report_dir`), ``list`` lists the tasks and
methods. A bad argument, output directory or results file is one line
``dax-bench: error: ...`` and exit status 2.
"""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path

import dax_tasks

from .. import method, registry
from . import grid, page, summary
from .execute import use_default_compilation_cache


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
    run.add_argument("--no-progress", action="store_true", help="no progress bar")
    rep = sub.add_parser("report", help="write the results page (index.html) and tables of "
                                        "an output directory again")
    rep.add_argument("--out", default="results", help="output directory of a run")
    rep.add_argument("--budget", default=None, choices=method.BUDGETS,
                     help="the budget's rows (default: the budget of the last row)")
    sub.add_parser("list", help="list the tasks and methods")
    return p


def main(argv=None) -> int:
    """The ``dax-bench`` console script; returns the exit status."""
    args = _parser().parse_args(argv)
    if args.command == "list":
        print("tasks:", ", ".join(dax_tasks.available()),
              f"(declared: {', '.join(dax_tasks.TASKS)})")
        print("methods:", ", ".join(registry.names()))
        return 0
    use_default_compilation_cache()
    try:
        if args.command == "report":
            index = summary.report_dir(args.out, args.budget)
            print(index.resolve())
            return 0
        command = shlex.join(["dax-bench", *(sys.argv[1:] if argv is None else argv)])
        rows = grid.run_grid(args.tasks, args.methods, args.seeds, args.out, quick=args.quick,
                             progress=not args.no_progress, demo_dir=args.demos,
                             command=command, backend=args.backend,
                             ray_address=args.ray_address, ray_cpus=args.ray_cpus)
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
