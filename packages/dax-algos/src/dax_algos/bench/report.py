"""Benchmark outputs: the results table in Markdown (mean ± standard error, methods as rows
and tasks as columns, as in the literature's tables) and one chart per task of score
against compute (wall time and simulated environment steps). Files are written to a
temporary name and renamed into place."""

from __future__ import annotations

import math
from collections import defaultdict
from pathlib import Path

import numpy as np

from dax_tasks.io import atomic_write


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


def score_cell(rows) -> str:
    """The score of one (task, method)'s rows: mean ± SE of the finished seeds (``(n=1)``
    for one), with the failed and skipped runs counted; ``failed`` / ``n/a`` for none."""
    ok = [as_float(r["score"]) for r in rows if r["status"] == "ok"]
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
    return text


def markdown(rows, task_order=(), method_order=(), title="DaX benchmark") -> str:
    """The results as Markdown: scores (mean ± SE over seeds) and compute per run."""
    groups = group_rows(rows)
    tasks = _order([r["task"] for r in rows], task_order)
    methods = _order([r["method"] for r in rows], method_order)
    budgets = sorted({r.get("budget", "") for r in rows})
    seeds = sorted({int(r["seed"]) for r in rows}) if rows else []
    lines = [f"# {title}", "",
             "Episode score = the ground-truth reward r_gt = exp(-λ·D(s_T, g)) after the "
             "**final** step of the episode (evaluation uses r_gt only). Cells: mean ± "
             f"standard error over seeds {seeds} (failed runs excluded and counted). "
             f"Budget: {', '.join(budgets)}.", "",
             "## Score", "",
             "| method | " + " | ".join(tasks) + " |",
             "|---|" + "---|" * len(tasks)]
    for m in methods:
        cells = [score_cell(groups.get((t, m), [])) if (t, m) in groups else "" for t in tasks]
        lines.append(f"| {m} | " + " | ".join(cells) + " |")
    lines += ["", "## Compute per run", "",
              "Mean wall time of the compiled episode [s] (compilation excluded; see "
              "`compile_s` in results.csv) / simulated environment steps (planning rollouts "
              "included).", "",
              "| method | " + " | ".join(tasks) + " |",
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
        lines.append(f"| {m} | " + " | ".join(cells) + " |")
    grads = [r for r in rows if r.get("grad_norm") not in ("", None)
             and r["status"] != "skipped"]
    if grads:
        lines += ["", "## Gradient norms (raw, before clipping)", "",
                  "| task | method | max over runs | mean | non-finite grad steps |",
                  "|---|---|---|---|---|"]
        for (t, m), rs in sorted(group_rows(grads).items()):
            gmax = max(as_float(r["grad_norm"]) for r in rs)
            gmean = np.nanmean([as_float(r["grad_norm_mean"]) for r in rs])
            bad = sum(int(as_float(r["nonfinite_grads"]) or 0) for r in rs)
            lines.append(f"| {t} | {m} | {gmax:.3g} | {gmean:.3g} | {bad} |")
    failures = [r for r in rows if r["status"] == "failed"]
    if failures:
        lines += ["", "## Failed runs", "", "| task | method | seed | error |", "|---|---|---|---|"]
        for r in failures:
            err = str(r["error"]).replace("|", "\\|").replace("\n", " ")
            lines.append(f"| {r['task']} | {r['method']} | {r['seed']} | {err} |")
    return "\n".join(lines) + "\n"


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
        for i, m in enumerate(methods):
            rs = groups[(task, m)]
            colour = f"C{i % 10}"
            score = [as_float(r["score"]) for r in rs]
            for ax, col in zip(axes, ("wall_s", "env_steps"), strict=True):
                x = [max(as_float(r[col]), 1e-3) for r in rs]
                ax.scatter(x, score, color=colour, alpha=0.3, s=12)
                (mx, sx), (my, sy) = mean_se(x), mean_se(score)
                ax.errorbar([mx], [my], xerr=[0 if math.isnan(sx) else sx],
                            yerr=[0 if math.isnan(sy) else sy], fmt="o", color=colour,
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
        path = out_dir / f"chart_{task}.png"
        atomic_write(path, lambda f, fig=fig: fig.savefig(f, format="png", dpi=100))
        plt.close(fig)
        written.append(path)
    return written
