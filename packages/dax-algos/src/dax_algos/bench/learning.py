"""Learning curves of the learning methods: ``learning_<task>.csv`` and its chart.

One row per training update of a run: ``task, method, seed, budget, update, env_steps,
wall_s, score`` (``env_steps`` and ``wall_s`` cumulative over training; ``score`` the mean
final-step r_gt of the training episodes that ended in the update, empty/NaN when none
did). All rows of one run are appended in a single flushed, fsynced write, before the
run's row in results.csv. Reading drops an incomplete last line (a killed writer),
keeps the last copy of a repeated (task, method, seed, budget, update) (a run re-done
after an interruption) and, given ``keep``, only runs that results.csv has.
``learning_<task>.png``: score against environment steps and against wall time, each
method's mean ± SE band over seeds and every update's point (each method in its colour,
:func:`dax_algos.bench.report.colour`), and the reference rows' mean scores (random,
expert) as dashed lines, so that a curve's rise is seen against them.
"""

from __future__ import annotations

import csv
import io
import math
from pathlib import Path

import numpy as np

from dax_tasks.io import atomic_write

from . import csvlog
from .report import colour
from .rows import check_name

COLUMNS = ("task", "method", "seed", "budget", "update", "env_steps", "wall_s", "score")


def learning_path(out_dir, task) -> Path:
    """``out_dir/learning_<task>.csv`` (``ValueError`` for a task name that is not a file
    name, :func:`dax_algos.bench.rows.check_name`)."""
    return Path(out_dir) / f"learning_{check_name('task', task)}.csv"


def _fmt(v):
    if isinstance(v, float):
        return repr(v) if math.isfinite(v) else "nan"
    return v


def append_curve(path, rows: list[dict]) -> None:
    """Append one run's rows in a single write (header first if the file is new). An
    incomplete last line left by a killed writer is cut off first, so the new rows never
    join it."""
    buf = io.StringIO()
    writer = csv.DictWriter(buf, COLUMNS, lineterminator="\n")
    if csvlog.is_empty(path):
        writer.writeheader()
    for r in rows:
        writer.writerow({k: _fmt(r[k]) for k in COLUMNS})
    csvlog.append(path, buf.getvalue())


def read_curves(path, keep: set | None = None) -> list[dict]:
    """The rows (typed), each run's in update order; only runs in ``keep`` if given. A
    run's curve is written whole after the run, so a row whose update is not past the run's
    previous row starts the run's curve again (the run re-done: a resume, or
    ``--rerun-stale``): only the last curve of each run is kept, never a mix of two."""
    path = Path(path)
    reader = csv.DictReader(io.StringIO(csvlog.read_complete(path)))
    if reader.fieldnames is not None and tuple(reader.fieldnames) != COLUMNS:
        raise ValueError(f"{path} has columns {reader.fieldnames}, expected {list(COLUMNS)}")
    curves: dict = {}  # run -> its rows, in update order
    for r in reader:
        row = dict(task=r["task"], method=r["method"], seed=int(r["seed"]),
                   budget=r["budget"], update=int(r["update"]),
                   env_steps=float(r["env_steps"]), wall_s=float(r["wall_s"]),
                   score=float(r["score"]) if r["score"] not in ("", None) else math.nan)
        run = (row["task"], row["method"], row["seed"], row["budget"])
        if keep is not None and run not in keep:
            continue
        curve = curves.setdefault(run, [])
        if curve and row["update"] <= curve[-1]["update"]:
            curve.clear()
        curve.append(row)
    return [row for curve in curves.values() for row in curve]


def curve_bands(rows, x: str, points: int = 50) -> dict:
    """{method: (grid, mean, SE, n_seeds)} of the score interpolated on a common x grid."""
    out = {}
    by_method: dict = {}
    for r in rows:
        by_method.setdefault(r["method"], {}).setdefault(r["seed"], []).append(r)
    for method, seeds in by_method.items():
        curves = []
        for rs in seeds.values():
            rs = sorted(rs, key=lambda r: r["update"])
            xs = np.asarray([r[x] for r in rs], float)
            ys = np.asarray([r["score"] for r in rs], float)
            ok = np.isfinite(ys)
            if ok.sum():
                curves.append((xs[ok], ys[ok]))
        if not curves:
            continue
        lo = max(c[0][0] for c in curves)
        hi = min(c[0][-1] for c in curves)
        if hi < lo:
            lo, hi = min(c[0][0] for c in curves), max(c[0][-1] for c in curves)
        grid = np.linspace(lo, hi, points)
        ys = np.full((len(curves), points), np.nan)
        for i, (cx, cy) in enumerate(curves):
            inside = (grid >= cx[0]) & (grid <= cx[-1])
            ys[i, inside] = np.interp(grid[inside], cx, cy)
        out[method] = (grid, *_mean_se(ys), len(curves))
    return out


def _mean_se(ys):
    """Mean and standard error over axis 0 of the finite entries (NaN where none; SE 0
    where one), without NumPy's warnings about empty slices."""
    ok = np.isfinite(ys)
    n = ok.sum(0)
    total = np.where(ok, ys, 0.0).sum(0)
    mean = np.divide(total, n, out=np.full(n.shape, np.nan), where=n > 0)
    dev = np.where(ok, ys - mean, 0.0)
    var = np.divide((dev ** 2).sum(0), n - 1, out=np.zeros(n.shape), where=n > 1)
    se = np.divide(np.sqrt(var), np.sqrt(n), out=np.zeros(n.shape), where=n > 1)
    return mean, se


def charts(rows, out_dir, method_order=(), references=None) -> list[Path]:
    """Write ``learning_<task>.png`` for each task in ``rows`` (see the module docstring;
    methods in ``method_order`` first; ``references``: ``{task: {method: mean score}}``
    drawn as dashed lines); returns the paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    written = []
    for task in dict.fromkeys(r["task"] for r in rows):
        trows = [r for r in rows if r["task"] == task]
        seen = list(dict.fromkeys(r["method"] for r in trows))
        methods = [m for m in method_order if m in seen] + [m for m in seen
                                                            if m not in method_order]
        fig, axes = plt.subplots(1, 2, figsize=(10, 4), sharey=True)
        n_seeds = 0
        for ax, x, label in zip(axes, ("env_steps", "wall_s"),
                                ("training environment steps", "training wall time [s]"),
                                strict=True):
            bands = curve_bands(trows, x)
            for m in methods:
                if m not in bands:
                    continue
                grid, mean, se, n = bands[m]
                n_seeds = max(n_seeds, n)
                c = colour(m)
                pts = [r for r in trows if r["method"] == m and math.isfinite(r["score"])]
                ax.scatter([r[x] for r in pts], [r["score"] for r in pts], color=c, s=8,
                           alpha=0.35)  # every update's point, so one point still shows
                ax.plot(grid, mean, color=c, label=m)
                ax.fill_between(grid, mean - se, mean + se, color=c, alpha=0.25)
            for name, score in (references or {}).get(task, {}).items():
                ax.axhline(score, color=colour(name), ls="--", lw=1,
                           label=f"{name} (mean score)" if ax is axes[0] else None)
            ax.set_xlabel(label)
            ax.grid(True, alpha=0.3)
        axes[0].set_ylabel("final-step r_gt (training episodes)")
        if any(ax.get_legend_handles_labels()[0] for ax in axes):
            axes[0].legend(fontsize=8)
        else:
            axes[0].text(0.5, 0.5, "no training episode ended in any update", ha="center",
                         transform=axes[0].transAxes)
        fig.suptitle(f"{task}: learning curves (mean ± SE over {n_seeds} seeds; the first "
                     f"point is the untrained policy's)")
        fig.tight_layout()
        path = Path(out_dir) / f"learning_{check_name('task', task)}.png"
        atomic_write(path, lambda f, fig=fig: fig.savefig(f, format="png", dpi=100))
        plt.close(fig)
        written.append(path)
    return written
