"""The results page: one static ``index.html`` in the output directory that opens from the
file system (no server, no network: inline CSS, no fonts or scripts from elsewhere, the
pictures by relative path).

It shows the score table (mean ± SE over seeds, the best mean per task marked), the compute
and gradient-norm tables, the score-against-compute charts, the learning curves, for each
(task, method) the median seed's episode as an animation and a filmstrip beside the goal
(:mod:`dax_algos.bench.episodes`), the failed and skipped runs with their causes, and what
produced it: the command lines, the machine and the package versions recorded in
``run.json``. Everything is in a fixed order and nothing on the page is the time it was
written (only the times ``run.json`` records), so writing it again from the same results
gives the same bytes. A small inline script marks ``<body>`` after loading
(``data-images-loaded``, ``data-images-broken``, ``data-errors``) for a headless browser
to check.
"""

from __future__ import annotations

import html
import json
import math
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path

import numpy as np

from dax_tasks.io import atomic_write

from . import report
from .rows import key

PAGE = "index.html"

_CSS = """
body { font-family: system-ui, -apple-system, "Segoe UI", Roboto, sans-serif;
       margin: 1.5em auto; max-width: 1400px; padding: 0 1em; color: #222; }
h1 { font-size: 1.6em; } h2 { margin-top: 1.8em; border-bottom: 1px solid #ccc; }
table { border-collapse: collapse; margin: 0.6em 0; font-size: 0.92em; }
th, td { border: 1px solid #ccc; padding: 0.25em 0.6em; text-align: right; }
th { background: #f2f2f2; } td.name, th.name { text-align: left; }
td.best { font-weight: bold; background: #e3f4e1; }
td.failed { color: #a00; }
.note { color: #555; font-size: 0.9em; }
.warn { color: #a00; font-weight: bold; }
img { max-width: 100%; height: auto; }
.charts img { display: block; margin: 0.5em 0; }
.episodes { display: flex; flex-wrap: wrap; gap: 1em; }
figure { margin: 0; padding: 0.5em; border: 1px solid #ddd; border-radius: 4px;
         max-width: 100%; }
figure .row { display: flex; gap: 0.5em; align-items: flex-start; flex-wrap: wrap; }
figcaption { font-size: 0.85em; color: #333; margin-top: 0.3em; max-width: 60em; }
pre { background: #f6f6f6; padding: 0.5em; overflow-x: auto; font-size: 0.85em; }
"""

# marks <body> once the page has loaded: every picture complete with a width, and every
# error event (a failed resource fires one in the capture phase, not bubbling)
_SCRIPT = """
var daxErrors = 0;
window.addEventListener("error", function () { daxErrors += 1; }, true);
window.addEventListener("load", function () {
  var ok = 0, broken = 0;
  for (var i = 0; i < document.images.length; i++) {
    var im = document.images[i];
    if (im.complete && im.naturalWidth > 0) { ok += 1; } else { broken += 1; }
  }
  document.body.setAttribute("data-images-loaded", String(ok));
  document.body.setAttribute("data-images-broken", String(broken));
  document.body.setAttribute("data-errors", String(daxErrors));
});
"""


def _e(text) -> str:
    return html.escape(str(text), quote=True)


def _num(v, fmt="{:.3g}") -> str:
    x = report.as_float(v)
    return "" if math.isnan(x) else fmt.format(x)


def _table(head: Sequence[str], body: Iterable[Sequence], name_cols: int = 1,
           table_id: str | None = None) -> list[str]:
    """An HTML table; cells are text, or ``(text, css_class)``; the first ``name_cols``
    columns are left-aligned names."""
    lines = [f'<table id="{table_id}">' if table_id else "<table>", "<tr>" + "".join(
        f'<th{" class=name" if i < name_cols else ""}>{_e(h)}</th>'
        for i, h in enumerate(head)) + "</tr>"]
    for row in body:
        cells = []
        for i, c in enumerate(row):
            text, cls = c if isinstance(c, tuple) else (c, "")
            cls = " ".join(x for x in (cls, "name" if i < name_cols else "") if x)
            cells.append(f'<td{f" class={chr(34)}{cls}{chr(34)}" if cls else ""}>'
                         f'{_e(text)}</td>')
        lines.append("<tr>" + "".join(cells) + "</tr>")
    lines.append("</table>")
    return lines


def best_methods(rows, task: str) -> set:
    """The methods with the highest mean score on ``task`` (finished runs; ties: all)."""
    means = {}
    for (t, m), rs in report.group_rows(rows).items():
        ok = [report.as_float(r["score"]) for r in rs if r["status"] == "ok"]
        ok = [x for x in ok if math.isfinite(x)]
        if t == task and ok:
            means[m] = float(np.mean(ok))
    if not means:
        return set()
    top = max(means.values())
    return {m for m, v in means.items() if v == top}


def score_table(rows, tasks, methods, stale=None) -> list[str]:
    """One row per task, one column per method; the best mean of each task marked; a cell
    holding stale rows (``stale``: ``{row key: reason}``) marked †."""
    stale = stale or {}
    groups = report.group_rows(rows)
    body = []
    for t in tasks:
        best = best_methods(rows, t)
        cells = [t]
        for m in methods:
            rs = groups.get((t, m))
            if not rs:
                cells.append("")
                continue
            text = report.score_cell(rs, bool(stale) and any(stale.get(key(r)) for r in rs))
            if m in best:
                cells.append(("★ " + text, "best"))
            elif text == "failed":
                cells.append((text, "failed"))
            else:
                cells.append(text)
        body.append(cells)
    return _table(["task", *methods], body, table_id="scores")


def compute_table(rows, tasks, methods) -> list[str]:
    """HTML lines: per (task, method) the finished runs and the means of their wall time,
    compile time, simulated and differentiated environment steps."""
    groups = report.group_rows(rows)
    body = []
    for t in tasks:
        for m in methods:
            rs = groups.get((t, m), [])
            ok = [r for r in rs if r["status"] == "ok"]
            if not rs:
                continue

            def mean(col, fmt, ok=ok):
                xs = [report.as_float(r[col]) for r in ok]
                xs = [x for x in xs if math.isfinite(x)]
                return fmt.format(float(np.mean(xs))) if xs else ""

            body.append([t, m, f"{len(ok)} / {len(rs)}", mean("wall_s", "{:.2f}"),
                         mean("compile_s", "{:.1f}"), mean("env_steps", "{:.0f}"),
                         mean("backprop_steps", "{:.0f}")])
    return _table(["task", "method", "finished / runs", "wall time [s]", "compile [s]",
                   "env steps", "backprop steps"], body, name_cols=2, table_id="compute")


def gradient_table(rows, tasks, methods) -> list[str]:
    """HTML lines: per (task, method) that reports gradients, the largest and the mean raw
    gradient norm over its runs and the non-finite gradient steps."""
    grads = [r for r in rows if r.get("grad_norm") not in ("", None)
             and r["status"] != "skipped"]
    if not grads:
        return ['<p class="note">No method here differentiates through the simulator.</p>']
    groups = report.group_rows(grads)
    body = []
    for t in tasks:
        for m in methods:
            rs = groups.get((t, m))
            if not rs:
                continue
            gmax = max(report.as_float(r["grad_norm"]) for r in rs)
            means = [report.as_float(r["grad_norm_mean"]) for r in rs]
            means = [x for x in means if math.isfinite(x)]
            bad = sum(int(report.as_float(r["nonfinite_grads"]) or 0) for r in rs)
            body.append([t, m, _num(gmax), _num(np.mean(means)) if means else "", str(bad)])
    return _table(["task", "method", "max over runs", "mean", "non-finite gradient steps"],
                  body, name_cols=2, table_id="gradients")


def problem_table(rows, tasks, methods) -> list[str]:
    """HTML lines: the failed and skipped runs with their causes, in task and method
    order."""
    bad = [r for r in rows if r["status"] in ("failed", "skipped")]
    if not bad:
        return ['<p class="note">None: every run finished.</p>']
    t_rank = {t: i for i, t in enumerate(tasks)}
    m_rank = {m: i for i, m in enumerate(methods)}
    bad.sort(key=lambda r: (t_rank.get(r["task"], 1e9), r["task"],
                            m_rank.get(r["method"], 1e9), r["method"], int(r["seed"])))
    body = [[r["task"], r["method"], r["seed"],
             (r["status"], "failed" if r["status"] == "failed" else ""), r["error"]]
            for r in bad]
    return _table(["task", "method", "seed", "status", "cause"], body, name_cols=5,
                  table_id="problems")


def stale_section(rows, stale, include_stale: bool) -> list[str]:
    """HTML lines: how many rows are stale, why, and whether the tables include them."""
    bad = [r for r in rows if stale.get(key(r))]
    if not bad:
        return ['<p class="note">None: every row was measured on today\'s task specs, code '
                "and method configs.</p>"]
    what = ("They are included in the tables above, their cells marked †." if include_stale
            else "They are left out of the tables, charts and episodes above (dax-bench "
                 "report --include-stale includes them).")
    lines = [f'<p class="warn">{len(bad)} of {len(rows)} rows are stale: they no longer '
             f"describe today's code. {_e(what)}</p>"]
    body = [[reason, str(len(rs)), ", ".join(dict.fromkeys(r["task"] for r in rs)),
             ", ".join(dict.fromkeys(r["method"] for r in rs))]
            for reason, rs in report.stale_groups(bad, stale).items()]
    return lines + _table(["why", "rows", "tasks", "methods"], body, name_cols=4,
                          table_id="stale")


def provenance_table(rows) -> list[str]:
    """HTML lines: the distinct provenances of the rows (versions, commit, precision,
    device, machine class) with how many rows have each."""
    cols = ("versions", "commit", "precision", "device", "machine")
    counts: dict = {}
    for r in rows:
        k = tuple(r.get(c, "") for c in cols)
        counts[k] = counts.get(k, 0) + 1
    body = [[*(v or "unknown" for v in k), str(n)] for k, n in counts.items()]
    return _table([*cols, "rows"], body, name_cols=len(cols), table_id="provenance")


def compute_seconds(rows) -> float:
    """The run's compute [s] as its rows record it: every row's ``wall_s`` plus each
    (task, method)'s compilation once per distinct ``compile_s`` (a run's seeds share one)."""
    wall = sum(x for x in (report.as_float(r["wall_s"]) for r in rows) if math.isfinite(x))
    compiles = {(r["task"], r["method"], r["compile_s"]) for r in rows}
    comp = sum(x for x in (report.as_float(c) for _, _, c in compiles) if math.isfinite(x))
    return wall + comp


def _caption(p) -> str:
    parts = [f"seed {p.seed} (the median of {p.n_seeds} finished "
             f"seed{'s' if p.n_seeds != 1 else ''})"]
    if p.n_rollouts > 1:
        parts.append(f"row score {p.row_score:.3f} (the mean of {p.n_rollouts} evaluation "
                     f"rollouts); shown: rollout {p.rollout + 1}, recorded "
                     f"{p.recorded:.3f}, replayed {p.replayed:.3f}")
    else:
        parts.append(f"row score {p.row_score:.3f}, replayed {p.replayed:.3f}")
    text = _e("; ".join(parts))
    if p.replay_mode and p.replay_mode != "unbatched":
        text += _e(f" (replayed under {p.replay_mode})")
    if p.mismatch:
        text += (f' <span class="warn">replay differs from the recording by '
                 f'{abs(p.replayed - p.recorded):.3f}</span>')
    if not p.same_task:
        text += ' <span class="warn">the task\'s code or spec changed since the run</span>'
    return text + _e(f". {p.frames} frames; final-step r_gt; the goal drawn faintly.")


def episode_section(pictures, tasks) -> list[str]:
    """HTML lines: per task, each method's median-seed episode (animation, filmstrip and
    caption, :class:`dax_algos.bench.episodes.Picture`)."""
    lines = []
    for t in tasks:
        pics = [p for p in pictures if p.task == t]
        if not pics:
            continue
        lines.append(f"<h3>{_e(t)}</h3>")
        lines.append('<div class="episodes">')
        for p in pics:
            lines.append("<figure>")
            lines.append(f"<strong>{_e(p.method)}</strong>")
            if p.gif is None:
                lines.append(f'<p class="note">{_e(p.note)}</p></figure>')
                continue
            alt = f"{t}, {p.method}, seed {p.seed}"
            lines.append('<div class="row">'
                         f'<img src="{_e(p.gif)}" alt="{_e(alt)}: animation">'
                         f'<img src="{_e(p.strip)}" alt="{_e(alt)}: key frames and goal">'
                         "</div>")
            lines.append(f"<figcaption>{_caption(p)}</figcaption></figure>")
        lines.append("</div>")
    return lines


def run_section(run: Mapping) -> list[str]:
    """HTML lines: what ``run.json`` records (each command line with its start, machine
    and package versions; the task and method overrides)."""
    invocations = [i for i in run.get("invocations", []) if isinstance(i, Mapping)]
    if not invocations:
        return ['<p class="note">Not recorded (results from before run.json recorded '
                "commands).</p>"]
    lines = []
    for inv in invocations:
        lines.append(f"<pre>{_e(inv.get('command', '?'))}</pre>")
        lines.append(f'<p class="note">started {_e(inv.get("started", "?"))}</p>')
        machine = inv.get("machine", {})
        lines += _table(["machine", ""], [[k, json.dumps(v) if not isinstance(v, str) else v]
                                          for k, v in sorted(machine.items())], name_cols=2)
        versions = inv.get("versions", {})
        lines += _table(["package", "version"], sorted(versions.items()), name_cols=2)
    for name in ("task_overrides", "method_overrides"):
        if run.get(name):
            lines.append(f"<p>{_e(name.replace('_', ' '))}:</p>"
                         f"<pre>{_e(json.dumps(run[name], indent=1, sort_keys=True))}</pre>")
    return lines


def _size(out: Path, rels) -> int:
    return sum((out / r).stat().st_size for r in rels if (out / r).is_file())


def write_page(out, rows: list[Mapping], run: Mapping, pictures: list, tasks: Sequence[str],
               methods: Sequence[str], title: str = "DaX benchmark", stale=None,
               include_stale: bool = False) -> Path:
    """Write ``out/index.html`` (atomically) from the results ``rows`` (one budget, the rows
    that count), the run file's contents ``run``, the episode ``pictures``
    (:func:`dax_algos.bench.episodes.episode_pictures`), with ``tasks`` and ``methods`` in
    that order. ``stale``: ``{row key: why}`` of the rows that no longer describe today's
    code; they are named, and left out of the tables unless ``include_stale``."""
    out = Path(out)
    stale = stale or {}
    all_rows, rows = rows, report.counted(rows, stale, include_stale)
    tasks = [t for t in tasks if any(r["task"] == t for r in all_rows)]
    methods = [m for m in methods if any(r["method"] == m for r in all_rows)]
    seeds = report.seed_text(all_rows, tasks)
    budgets = sorted({r.get("budget", "") for r in rows})
    counts = {s: sum(r["status"] == s for r in all_rows)
              for s in ("ok", "failed", "skipped")}
    counted_tasks = [t for t in tasks if any(r["task"] == t for r in rows)]  # not all stale
    charts = [f"chart_{t}.png" for t in counted_tasks if (out / f"chart_{t}.png").is_file()]
    curves = [f"learning_{t}.png" for t in counted_tasks
              if (out / f"learning_{t}.png").is_file()]
    shown = [p for p in pictures if p.gif]
    pics = [x for p in shown for x in (p.gif, p.strip)]
    render_s = sum(p.render_s for p in shown)
    run_s = compute_seconds(rows)
    n_stale = sum(bool(stale.get(key(r))) for r in all_rows)
    stale_note = (f" <span class=\"warn\">{n_stale} rows are stale (see Stale rows)"
                  f"{', included and marked †' if include_stale else ', left out'}.</span>"
                  if n_stale else "")
    body = [f"<h1>{_e(title)}</h1>",
            f"<p>{len(tasks)} task(s) × {len(methods)} method(s) × seeds {_e(seeds)}, "
            f"budget {_e(', '.join(budgets))}: {counts['ok']} runs finished, "
            f"{counts['failed']} failed, {counts['skipped']} skipped (the method does not "
            f"apply). Files beside this page: results.csv (every run), results.md."
            f"{stale_note}</p>",
            "<h2>Score</h2>",
            '<p class="note">Episode score = the ground-truth reward r_gt = exp(-λ·D(s_T, g))'
            " after the <b>final</b> step (evaluation uses r_gt only); failed runs excluded "
            f"and counted. {_e(report.se_note(methods))} ★ and bold: the best mean on the "
            "task.</p>",
            *score_table(rows, tasks, methods, stale),
            "<h2>Compute per run</h2>",
            '<p class="note">Means over the finished runs: wall time of the compiled '
            "episode (training and evaluation for a learner; compilation excluded), "
            "compilation, simulated environment steps (planning rollouts included) and "
            "environment steps differentiated through.</p>",
            *compute_table(rows, tasks, methods),
            "<h2>Gradient norms</h2>",
            '<p class="note">Raw global norms before clipping.</p>',
            *gradient_table(rows, tasks, methods),
            "<h2>Score against compute</h2>", '<div class="charts">',
            *[f'<img src="{_e(c)}" alt="{_e(c)}">' for c in charts],
            "</div>"]
    if curves:
        body += ["<h2>Learning curves</h2>", '<div class="charts">',
                 *[f'<img src="{_e(c)}" alt="{_e(c)}">' for c in curves], "</div>"]
    body += ["<h2>Episodes</h2>",
             '<p class="note">For each task and method, the episode of the median-score '
             "seed, replayed from the actions recorded during the run: an animation "
             "(looping) and key frames beside the goal. A learner's score is the mean over "
             "its evaluation rollouts; its first rollout is shown. Replaying and drawing "
             f"these {len(shown)} episodes took {render_s:.1f} s, "
             f"{100 * render_s / run_s if run_s > 0 else math.nan:.1f} % of the run's "
             f"{run_s:.0f} s of compute (the rows' wall and compile times); the pictures "
             f"take {_size(out, pics) / 1e6:.2f} MB.</p>",
             *episode_section(pictures, tasks),
             "<h2>Failed and skipped runs</h2>",
             *problem_table(all_rows, tasks, methods),
             "<h2>Stale rows</h2>",
             *stale_section(all_rows, stale, include_stale),
             "<h2>Run</h2>",
             '<p class="note">What the rows record they were measured on:</p>',
             *provenance_table(all_rows),
             *run_section(run)]
    text = "\n".join(["<!DOCTYPE html>", '<html lang="en">', "<head>",
                      '<meta charset="utf-8">',
                      '<meta name="viewport" content="width=device-width, initial-scale=1">',
                      f"<title>{_e(title)}</title>", f"<style>{_CSS}</style>",
                      f"<script>{_SCRIPT}</script>", "</head>", "<body>", *body,
                      "</body>", "</html>"]) + "\n"
    return atomic_write(out / PAGE, text)
