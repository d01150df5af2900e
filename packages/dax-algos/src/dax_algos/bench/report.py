"""Benchmark outputs: the results table in Markdown (mean ± standard error, methods as rows
and tasks as columns, as in the literature's tables; the standard-error convention stated
under every table, :func:`se_note`) and one chart per task of score against compute (wall
time and simulated environment steps), each method in its own colour on every chart
(:func:`colour`). Files are written to a temporary name and renamed into place."""

from __future__ import annotations

import hashlib
import html
import math
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np

from dax_tasks.io import atomic_write

from .. import registry
from .rows import check_name, key


def as_float(v):
    """A results-row field as a float (``nan`` for an empty or non-numeric one)."""
    try:
        return float(v)
    except (TypeError, ValueError):
        return math.nan


def mean_se(values) -> tuple[float, float]:
    """Mean and standard error (sample std / sqrt(n); nan for n < 2)."""
    x = np.asarray(values, np.float64)
    if x.size == 0:
        return math.nan, math.nan
    se = float(np.std(x, ddof=1) / math.sqrt(x.size)) if x.size > 1 else math.nan
    return float(np.mean(x)), se


def group_rows(rows):
    """``{(task, method): [rows]}``."""
    groups = defaultdict(list)
    for r in rows:
        groups[(r["task"], r["method"])].append(r)
    return groups


def _order(values, preferred):
    seen = list(dict.fromkeys(values))
    first = [v for v in preferred if v in seen]
    return first + [v for v in seen if v not in first]


def md(text) -> str:
    """``text`` safe in a Markdown table cell: HTML escaped (nothing copied from a results
    file becomes markup), ``|`` escaped, on one line."""
    return html.escape(" ".join(str(text).split()), quote=False).replace("|", "\\|")


def se_note(methods) -> str:
    """The standard-error convention of a table of ``methods``, one sentence per kind of
    row it holds: a learner's SE is over training seeds (each seed's score the mean of its
    evaluation rollouts), a planner's, random's and expert's over episodes (one per
    seed)."""
    kinds = {_kind(m) for m in methods}
    parts = []
    if "learner" in kinds:
        parts.append("learners (RL and imitation): mean ± standard error over training "
                     "seeds, each seed's score the mean of its evaluation rollouts")
    if "episode" in kinds:
        parts.append("planners, random and expert: mean ± standard error over episodes, "
                     "one per seed")
    return "Cells: " + "; ".join(parts) + ". (n=1): one seed, no standard error."


def span(seeds) -> str:
    """Sorted ints as text: ``0-4`` for a run of consecutive seeds, else ``0, 2, 7``."""
    seeds = sorted(seeds)
    if seeds and seeds == list(range(seeds[0], seeds[-1] + 1)) and len(seeds) > 1:
        return f"{seeds[0]}-{seeds[-1]}"
    return ", ".join(map(str, seeds))


def cell_seeds(rows) -> dict:
    """``{(task, method): {seed, ...}}``: the seeds each cell of ``rows`` holds."""
    cells = defaultdict(set)
    for r in rows:
        cells[(r["task"], r["method"])].add(int(r["seed"]))
    return dict(cells)


def common_seeds(cells) -> frozenset:
    """The seed set most of ``cells`` (:func:`cell_seeds`) hold; ties: the smaller set,
    then the one met first; empty for no cells."""
    counts = Counter(frozenset(seeds) for seeds in cells.values())
    return max(counts, key=lambda s: (counts[s], -len(s)), default=frozenset())


def seed_text(rows, tasks=()) -> str:
    """Which seeds a table's cells hold: ``0-4`` when every (task, method) has the same
    seeds; else the seeds most cells hold (:func:`common_seeds`) and, after them, each
    other set with its cells, methods that share the same tasks named together, e.g.
    ``0-4 (0-9: ppo, apg on fold_cloth1, unfold_cloth3)``. A table whose cells hold
    different numbers of seeds must say so: their standard errors are over different n.
    Tasks are named in the order of ``tasks``, then of the rows."""
    cells = cell_seeds(rows)
    if not cells:
        return ""
    common = common_seeds(cells)
    order = list(dict.fromkeys([*tasks, *(r["task"] for r in rows)]))
    sets = defaultdict(list)  # each other seed set -> [(task, method)], in the rows' order
    for cell, seeds in cells.items():
        if seeds != common:
            sets[tuple(sorted(seeds))].append(cell)
    others = []
    for seeds in sorted(sets, key=lambda s: (len(s), s)):
        tasks_of = defaultdict(list)
        for task, method in sets[seeds]:
            tasks_of[method].append(task)
        by_tasks = defaultdict(list)  # the same tasks -> the methods that have them
        for method, its_tasks in tasks_of.items():
            by_tasks[tuple(sorted(its_tasks, key=order.index))].append(method)
        cells_text = "; ".join(f"{', '.join(ms)} on {', '.join(ts)}"
                               for ts, ms in by_tasks.items())
        others.append(f"{span(seeds)}: {cells_text}")
    return span(common) + (f" ({'; '.join(others)})" if others else "")


UNTRAINED_NOTE = (" *untrained*: the learner's policy before training (its network at "
                  "initialisation), on the same evaluation starts, over the same seeds.")


def _kind(method: str) -> str:
    try:
        return "learner" if registry.get(method).family in ("rl", "il") else "episode"
    except ValueError:
        return "episode"


def score_cell(rows, stale_marked: bool = False, col: str = "score") -> str:
    """The score of one (task, method)'s rows: mean ± SE of the finished seeds (``(n=1)``
    for one), with the failed and skipped runs counted; ``failed`` / ``n/a`` for none;
    `` †`` appended when ``stale_marked`` (stale rows included). ``col``: which score
    (``untrained_score``: the learner's untrained policy, from the rows that have one)."""
    ok = [as_float(r[col]) for r in rows if r["status"] == "ok" and r.get(col, "") != ""]
    failed = sum(r["status"] == "failed" for r in rows)
    skipped = sum(r["status"] == "skipped" for r in rows)
    if ok:
        m, se = mean_se(ok)
        text = f"{m:.3f} ± {se:.3f}" if not math.isnan(se) else f"{m:.3f} (n=1)"
    else:
        text = "n/a" if skipped and not failed else "failed"
    notes = []
    if failed:
        notes.append(f"{failed} failed")
    if skipped:
        notes.append(f"{skipped} skipped")
    if notes and ok:
        text += " (" + ", ".join(notes) + ")"
    return text + (" †" if stale_marked else "")


def counted(rows, stale=None, include_stale: bool = False) -> list:
    """The rows the means use: those that are not stale (``stale``: ``{row key: reason}``),
    or all of them with ``include_stale``."""
    if include_stale or not stale:
        return list(rows)
    return [r for r in rows if not stale.get(key(r))]


def score_lines(rows, tasks, methods, stale=None, include_stale=False) -> list[str]:
    """A Markdown score table, methods as rows and tasks as columns, of the rows that count
    (:func:`counted`; a cell with stale rows included is marked †), followed by the
    standard-error convention."""
    stale = stale or {}
    groups = group_rows(counted(rows, stale, include_stale))
    lines = ["| method | " + " | ".join(md(t) for t in tasks) + " |",
             "|---|" + "---|" * len(tasks)]
    note = se_note(methods)
    for m in methods:
        cells = []
        for t in tasks:
            rs = groups.get((t, m))
            marked = bool(rs and stale) and any(stale.get(key(r)) for r in rs)
            cells.append(score_cell(rs, marked) if rs else "")
        lines.append(f"| {md(m)} | " + " | ".join(cells) + " |")
        untrained = [[r for r in groups.get((t, m), ()) if r.get("untrained_score", "") != ""]
                     for t in tasks]
        if any(untrained):
            lines.append(f"| {md(m)}, untrained | " + " | ".join(
                score_cell(rs, col="untrained_score") if rs else "" for rs in untrained) + " |")
            note = se_note(methods) + UNTRAINED_NOTE
    if include_stale and stale and any(stale.get(key(r)) for r in rows):
        note += " †: includes stale rows (see below)."
    return [*lines, "", note]


def stale_lines(rows, stale, include_stale: bool) -> list[str]:
    """Markdown lines saying how many rows are stale and why (none if none is)."""
    bad = [r for r in rows if stale.get(key(r))]
    if not bad:
        return []
    what = ("included in the tables, marked †" if include_stale else
            "left out of the tables and means (`dax-bench report --include-stale` includes "
            "them)")
    lines = ["", "## Stale rows", "",
             f"{len(bad)} of {len(rows)} rows no longer describe today's code: {what}.", "",
             "| reason | rows | tasks | methods |", "|---|---|---|---|"]
    for reason, rs in stale_groups(bad, stale).items():
        lines.append(f"| {md(reason)} | {len(rs)} | "
                     f"{md(', '.join(dict.fromkeys(r['task'] for r in rs)))} | "
                     f"{md(', '.join(dict.fromkeys(r['method'] for r in rs)))} |")
    return lines


#: The kinds of a stale row's reason (:func:`dax_algos.bench.provenance.stale_reason`):
#: (words the reason holds, the kind in words); a reason with none of them is the last.
STALE_KINDS = (("spec changed", "the task's spec changed"),
               ("code changed", "the dax-tasks or dax-physics code changed"),
               ("config changed", "the method's config changed"),
               ("", "provenance unknown or not checkable"))


def stale_kinds(reasons) -> dict:
    """``{kind in words: rows}`` of stale rows' ``reasons``, in :data:`STALE_KINDS` order;
    a row stale for two reasons counts under both."""
    counts = dict.fromkeys((text for _, text in STALE_KINDS), 0)
    for why in reasons:
        kinds = [text for words, text in STALE_KINDS[:-1] if words in why]
        for text in kinds or [STALE_KINDS[-1][1]]:
            counts[text] += 1
    return {text: n for text, n in counts.items() if n}


def stale_groups(rows, stale) -> dict:
    """``{reason: [rows]}`` of the stale ``rows``, reasons in order of first appearance."""
    out: dict = {}
    for r in rows:
        out.setdefault(stale[key(r)], []).append(r)
    return out


def markdown(rows, task_order=(), method_order=(), title="DaX benchmark", stale=None,
             include_stale: bool = False) -> str:
    """The results as Markdown: scores (mean ± SE, :func:`se_note`), compute per run,
    gradient norms, the failed runs and the stale rows. Everything copied from the rows is
    escaped (:func:`md`)."""
    stale = stale or {}
    tasks = _order([r["task"] for r in rows], task_order)
    methods = _order([r["method"] for r in rows], method_order)
    budgets = sorted({r.get("budget", "") for r in rows})
    seeds = seed_text(rows, tasks) or "none"
    used = counted(rows, stale, include_stale)
    groups = group_rows(used)
    lines = [f"# {md(title)}", "",
             "Episode score = the ground-truth reward r_gt = exp(-λ·D(s_T, g)) after the "
             "**final** step of the episode (evaluation uses r_gt only); failed runs are "
             f"excluded and counted. Seeds {md(seeds)}. Budget: {md(', '.join(budgets))}.", "",
             "## Score", "", *score_lines(rows, tasks, methods, stale, include_stale),
             "", "## Compute per run", "",
             "Mean wall time of the compiled episode [s] (compilation excluded; see "
             "`compile_s` in results.csv) / simulated environment steps (planning rollouts "
             "included).", "",
             "| method | " + " | ".join(md(t) for t in tasks) + " |",
             "|---|" + "---|" * len(tasks)]
    for m in methods:
        cells = []
        for t in tasks:
            rs = [r for r in groups.get((t, m), []) if r["status"] == "ok"]
            if not rs:
                cells.append("")
                continue
            w = np.mean([as_float(r["wall_s"]) for r in rs])
            e = np.mean([as_float(r["env_steps"]) for r in rs])
            cells.append(f"{w:.1f} s / {e:.0f}")
        lines.append(f"| {md(m)} | " + " | ".join(cells) + " |")
    lines += _gradient_lines(used) + _failure_lines(rows) + stale_lines(rows, stale,
                                                                         include_stale)
    return "\n".join(lines) + "\n"


def _gradient_lines(rows) -> list[str]:
    grads = [r for r in rows if r.get("grad_norm") not in ("", None)
             and r["status"] != "skipped"]
    if not grads:
        return []
    lines = ["", "## Gradient norms (raw, before clipping)", "",
             "| task | method | max over runs | mean | non-finite grad steps |",
             "|---|---|---|---|---|"]
    for (t, m), rs in sorted(group_rows(grads).items()):
        gmax = max(as_float(r["grad_norm"]) for r in rs)
        means = [x for x in (as_float(r["grad_norm_mean"]) for r in rs) if math.isfinite(x)]
        gmean = float(np.mean(means)) if means else math.nan
        bad = sum(int(as_float(r["nonfinite_grads"]) or 0) for r in rs)
        lines.append(f"| {md(t)} | {md(m)} | {gmax:.3g} | {gmean:.3g} | {bad} |")
    return lines


def _failure_lines(rows) -> list[str]:
    failures = [r for r in rows if r["status"] == "failed"]
    if not failures:
        return []
    lines = ["", "## Failed runs", "", "| task | method | seed | error |", "|---|---|---|---|"]
    for r in failures:
        lines.append(f"| {md(r['task'])} | {md(r['method'])} | {md(r['seed'])} | "
                     f"{md(r['error'])} |")
    return lines


#: a fixed colour per registered method, the same on every chart
COLOURS = {"random": "#7f7f7f", "expert": "#000000", "cem_mpc": "#1f77b4",
           "diff_mpc": "#ff7f0e", "diff_cem_mpc": "#2ca02c", "ppo": "#d62728",
           "apg": "#9467bd", "shac": "#8c564b", "transporter": "#e377c2",
           "transporter_rgb": "#bcbd22", "ild": "#17becf"}
#: colours of methods not in :data:`COLOURS`, picked by a hash of the name
_MORE = ("#393b79", "#637939", "#8c6d31", "#843c39", "#7b4173", "#3182bd", "#e6550d",
         "#31a354", "#756bb1", "#636363")


def colour(method: str) -> str:
    """The colour of ``method`` on every chart: :data:`COLOURS`, else one of a second
    palette chosen by a hash of the name (stable across runs and processes)."""
    if method in COLOURS:
        return COLOURS[method]
    return _MORE[int(hashlib.sha256(method.encode()).hexdigest(), 16) % len(_MORE)]


def charts(rows, out_dir: Path, method_order=()) -> list[Path]:
    """One PNG per task, ``chart_<task>.png``: score against wall time and against simulated
    environment steps (log x), each run a faint dot and each method's mean ± SE a marker."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    written = []
    groups = group_rows([r for r in rows if r["status"] == "ok"])
    tasks = list(dict.fromkeys(t for t, _ in groups))
    for task in tasks:
        methods = _order([m for t, m in groups if t == task], method_order)
        fig, axes = plt.subplots(1, 2, figsize=(10, 4), sharey=True)
        for m in methods:
            rs = groups[(task, m)]
            colour_ = colour(m)
            score = [as_float(r["score"]) for r in rs]
            for ax, col in zip(axes, ("wall_s", "env_steps"), strict=True):
                x = [max(as_float(r[col]), 1e-3) for r in rs]
                ax.scatter(x, score, color=colour_, alpha=0.3, s=12)
                (mx, sx), (my, sy) = mean_se(x), mean_se(score)
                ax.errorbar([mx], [my], xerr=[0 if math.isnan(sx) else sx],
                            yerr=[0 if math.isnan(sy) else sy], fmt="o", color=colour_,
                            capsize=3, label=m if col == "wall_s" else None)
        axes[0].set_xlabel("wall time per episode [s] (compiled)")
        axes[1].set_xlabel("simulated environment steps per episode")
        axes[0].set_ylabel("final-step r_gt")
        for ax in axes:
            ax.set_xscale("log")
            ax.grid(True, alpha=0.3)
        axes[0].legend(fontsize=8)
        fig.suptitle(f"{task}: score against compute")
        fig.tight_layout()
        path = out_dir / f"chart_{check_name('task', task)}.png"
        atomic_write(path, lambda f, fig=fig: fig.savefig(f, format="png", dpi=100))
        plt.close(fig)
        written.append(path)
    return written
