"""What an output directory shows of its results: ``results.md`` (mean ± SE, methods x
tasks), ``chart_<task>.png`` (score against wall time and simulated environment steps),
the learning curves' charts and the results page ``index.html`` (:mod:`.page`, with each
(task, method)'s median episode replayed and drawn, :mod:`.episodes`), all rewritten from
``results.csv`` (:func:`write_reports`, at the end of every grid; :func:`report_dir`, for
``dax-bench report``). Stale rows (:mod:`.provenance`) are named and left out of the
means unless asked for."""

from __future__ import annotations

from pathlib import Path

import dax_tasks
from dax_tasks.io import atomic_write, exclusive

from .. import registry
from . import episodes, learning, page, provenance, report, rundir
from .rows import key, latest, read_rows


def write_reports(rows, out: Path, budget: str, make_env=None, include_stale: bool = False,
                  today: provenance.Today | None = None) -> Path:
    """Rewrite ``results.md``, the charts and the results page (``index.html``, with the
    median seed's episode of each (task, method) drawn unless it already is) from the rows
    of ``budget`` that count (:func:`dax_algos.bench.rows.latest`); returns the page's path.

    Rows that no longer describe today's code (:func:`dax_algos.bench.provenance.
    stale_reason`: checked against ``today``, default the overrides ``run.json`` records)
    are listed with their reasons and left out of the tables, charts and pictures unless
    ``include_stale``. ``make_env(task)`` builds a task as the run did (default: with the
    task overrides recorded in ``run.json``)."""
    rows = [r for r in latest(rows) if r["budget"] == budget]
    run = rundir.read_run_file(out)
    overrides = task_overrides_of(run)
    if today is None:
        today = today_of(run)
    stale = {key(r): provenance.stale_reason(r, today) for r in rows}
    shown = [r for r in rows if include_stale or not stale[key(r)]]
    title = f"DaX benchmark ({budget} budget)"
    atomic_write(out / "results.md", report.markdown(
        rows, dax_tasks.TASKS, registry.names(), title=title, stale=stale,
        include_stale=include_stale))
    drawn = report.charts(shown, out, registry.names())
    for task in dict.fromkeys(r["task"] for r in rows):  # no chart of an earlier report
        if out / f"chart_{task}.png" not in drawn:
            (out / f"chart_{task}.png").unlink(missing_ok=True)
    done = {key(r) for r in shown}
    references = _references(shown)
    for task in dict.fromkeys(r["task"] for r in rows):
        path = learning.learning_path(out, task)
        curves = learning.read_curves(path, keep=done) if path.exists() else []
        if curves:
            learning.charts(curves, out, registry.names(), references)
        else:  # no curve counts (none, or only stale runs'): no chart of an earlier report
            (out / f"learning_{task}.png").unlink(missing_ok=True)
    if make_env is None:
        def make_env(task):
            return dax_tasks.make(task, **overrides.get(task, {}))

    tasks = _order(dax_tasks.TASKS, rows, "task")
    methods = _order(registry.names(), rows, "method")
    pictures = episodes.episode_pictures(out, shown, make_env, tasks, methods)
    return page.write_page(out, rows, run, pictures, tasks, methods, title=title,
                           stale=stale, include_stale=include_stale)


def task_overrides_of(run: dict) -> dict:
    """``{task: overrides}`` a run file (``run.json``) records, for the tasks this
    installation has."""
    return {t: rundir.overrides_from_json(t, o)
            for t, o in run.get("task_overrides", {}).items() if t in dax_tasks.available()}


def today_of(run: dict) -> provenance.Today:
    """What a row of the run recorded in ``run`` (``run.json``) is checked against to be
    current (:func:`dax_algos.bench.provenance.stale_reason`): today's code with the run's
    task and method overrides."""
    return provenance.Today(task_overrides_of(run), run.get("method_overrides", {}))


def _references(rows) -> dict:
    """``{task: {method: mean score}}`` of the reference rows (random, expert) that ran."""
    refs: dict = {}
    ok = [r for r in rows if r["status"] == "ok" and r["method"] in ("random", "expert")]
    for (task, method), rs in report.group_rows(ok).items():
        refs.setdefault(task, {})[method] = report.mean_se(
            [report.as_float(r["score"]) for r in rs])[0]
    return refs


def markdown_tables(out, budget: str | None = None, include_stale: bool = False,
                    tasks=None, methods=None, label: str | None = None) -> str:
    """The score table of the output directory (or results file) ``out`` as Markdown, what
    a README holds: methods as rows, tasks as columns (``tasks`` / ``methods``: only these,
    in this order), the rows of ``budget`` (default: the last row's) that count, stale rows
    (checked against today's code, :mod:`.provenance`) left out unless ``include_stale``
    and counted under the table either way, and a line saying where the rows come from
    (``label``: how to name the file there; default its path)."""
    out = Path(out)
    csv_path = out if out.suffix == ".csv" else out / "results.csv"
    if not csv_path.is_file():
        raise ValueError(f"{csv_path}: no such results file")
    rows = latest(read_rows(csv_path))
    budget = budgets(rows, budget)
    rows = [r for r in rows if r["budget"] == budget and (tasks is None or r["task"] in tasks)
            and (methods is None or r["method"] in methods)]
    run = rundir.read_run_file(csv_path.parent) if out.suffix != ".csv" else {}
    today = today_of(run)
    stale = {key(r): provenance.stale_reason(r, today) for r in rows}
    tasks = list(tasks) if tasks else _order(dax_tasks.TASKS, rows, "task")
    methods = list(methods) if methods else _order(registry.names(), rows, "method")
    lines = report.score_lines(rows, tasks, methods, stale, include_stale)
    n_stale = sum(bool(v) for v in stale.values())
    lines += ["", f"Rows: `{label or csv_path.as_posix()}`, {budget} budget, "
              f"seeds {report.seed_text(rows, tasks)}; "
              f"final-step r_gt. " + _provenance_text(rows, stale, n_stale, include_stale)]
    return "\n".join(lines) + "\n"


def _provenance_text(rows, stale, n_stale, include_stale) -> str:
    if not n_stale:
        commits = sorted({r["commit"][:12] for r in rows if r.get("commit")})
        return ("Measured on today's task specs, code and method configs"
                + (f" (commit {', '.join(commits)})." if commits else "."))
    kinds = report.stale_kinds(stale[key(r)] for r in rows if stale[key(r)])
    what = "included, marked †" if include_stale else "left out"
    return (f"**{n_stale} of {len(rows)} rows are stale** ({what}) — why (rows): "
            + "; ".join(f"{text} ({n})" for text, n in kinds.items())
            + " (each row's fingerprint and config: the grid's page, Stale rows).")


def budgets(rows, budget: str | None) -> str:
    """``budget``, or the last row's; ``ValueError`` if no row has it."""
    if not rows:
        raise ValueError("no runs")
    budget = rows[-1]["budget"] if budget is None else budget
    if not any(r["budget"] == budget for r in rows):
        raise ValueError(f"no runs of the {budget} budget")
    return budget


def report_dir(out, budget: str | None = None, include_stale: bool = False) -> Path:
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
        return write_reports(rows, out, budget, include_stale=include_stale)


def _order(preferred, rows, col) -> list:
    """The values of ``col`` in ``rows``: those in ``preferred`` in its order, then the
    others sorted."""
    seen = list(dict.fromkeys(r[col] for r in rows))
    return [x for x in preferred if x in seen] + sorted(x for x in seen if x not in preferred)
