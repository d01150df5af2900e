"""What an output directory shows of its results: ``results.md`` (mean ± SE, methods x
tasks), ``chart_<task>.png`` (score against wall time and simulated environment steps),
the learning curves' charts and the results page ``index.html`` (:mod:`.page`, with each
(task, method)'s median episode replayed and drawn, :mod:`.episodes`), all rewritten from
``results.csv`` (:func:`write_reports`, at the end of every grid; :func:`report_dir`, for
``dax-bench report``)."""

from __future__ import annotations

from pathlib import Path

import dax_tasks
from dax_tasks.io import atomic_write, exclusive

from .. import registry
from . import episodes, learning, page, report, rundir
from .rows import read_rows


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
    run = rundir.read_run_file(out)
    if make_env is None:
        overrides = run.get("task_overrides", {})

        def make_env(task):
            return dax_tasks.make(task, **rundir.overrides_from_json(
                task, overrides.get(task, {})))

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
    """The values of ``col`` in ``rows``: those in ``preferred`` in its order, then the
    others sorted."""
    seen = list(dict.fromkeys(r[col] for r in rows))
    return [x for x in preferred if x in seen] + sorted(x for x in seen if x not in preferred)
