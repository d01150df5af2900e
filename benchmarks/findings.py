"""The benchmark's findings and the learners' bar, checked against a grid's result file.

Two tables, each rendered from a grid directory's ``results.csv`` (the rows that count,
:func:`dax_algos.bench.rows.latest`, of one budget, stale rows left out,
:mod:`dax_algos.bench.provenance`):

* :func:`render_findings`: for each finding of the original benchmark (:data:`FINDINGS`),
  on each of its tasks where both methods have rows, whether each of its comparisons
  holds: ``a > b`` holds when ``mean_a - mean_b > 2 SE``, ``a >= b`` when ``mean_a -
  mean_b > -2 SE`` (``SE = sqrt(SE_a² + SE_b²)``, each the row kind's SE: learners over
  training seeds, planners over episodes). A finding is *reproduced* when every comparison
  holds on every task measured, *not reproduced* when one fails (the failing ones listed
  with their numbers and, per task where one fails, the measured reason the finding
  names for it, :attr:`Finding.why`), *not measured* when no task has both methods' rows.
* :func:`render_untrained`: for each learner and task, the trained score beside the
  untrained policy's (``untrained_score``, the same seeds and evaluation starts) and their
  paired difference over seeds: *above* (more than 2 SE), *below* (more than 2 SE below,
  which the learners issue forbids) or *within*.

    python -m benchmarks.tables findings benchmarks/results/GRID
    python -m benchmarks.tables untrained benchmarks/results/GRID
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np

CLOTH = ("fold_cloth1", "fold_cloth3", "fold_tshirt", "unfold_cloth1", "unfold_cloth3")
MACRO = ("push_rope", *CLOTH)
ALL = ("pour_water", "pour_soup", "push_rope", "whip_rope", *CLOTH)


@dataclasses.dataclass(frozen=True)
class Finding:
    """A claim of the original benchmark: ``claims`` are ``(a, op, b)`` with ``op`` one of
    ``>`` (a above b by more than 2 SE) and ``>=`` (a not below b by more than 2 SE),
    checked on each of ``tasks``. ``why`` is ``((task, reason), ...)``: for a task where a
    claim has failed, what measurement says why (in words, naming the script or table that
    measured it; its numbers stay in the result files and the dax-algos README). A failing
    task without one is shown as having no measured reason."""

    name: str
    text: str
    tasks: tuple
    claims: tuple
    why: tuple = ()

    def reason(self, task: str) -> str:
        """The measured reason the claim fails on ``task``, or ``"no measured reason"``."""
        return dict(self.why).get(task, "no measured reason")


_ILD_NOISE = ("ILD's tracking-loss gradient at its budget's batch is mostly noise "
              "across starts (`benchmarks.gradient_noise --method ild`)")

FINDINGS = (
    Finding("F1", "PPO ≥ APG and SHAC on the macro cloth tasks", CLOTH,
            (("ppo", ">=", "apg"), ("ppo", ">=", "shac"))),
    Finding("F2", "APG far above PPO on Whip-Rope, SHAC between", ("whip_rope",),
            (("apg", ">", "ppo"), ("apg", ">", "shac"), ("shac", ">", "ppo")),
            (("whip_rope", "SHAC stays at its untrained score; not for want of a gradient "
              "(its first is as directed as APG's: `benchmarks.gradient_noise --method "
              "shac`): more updates grow its gradient norm and lower its curve, a smaller "
              "step holds it flat (`benchmarks.ablate shac whip_rope`)"),)),
    Finding("F3", "Transporter on RGB above Transporter on height maps", MACRO,
            (("transporter_rgb", ">", "transporter"),),
            (("push_rope", "the RGB network picks as near the expert's pick but places the "
              "push's end further off (`benchmarks.transporter_picks`)"),
             ("fold_cloth1", "the RGB network picks nearer the expert's first pick and makes "
              "the better first fold (`benchmarks.transporter_picks`); both networks' later "
              "actions, off the demonstrations' path, undo part of it, leaving a gap in the "
              "finding's direction under 2 SE"),
             ("fold_cloth3", "the RGB network follows the expert's first two folds more "
              "closely (`benchmarks.transporter_picks`) and scores higher on every seed: "
              "over 2 SE paired by seed, under it by this table's unpaired rule"))),
    Finding("F4", "ILD at or above Transporter on the macro tasks", MACRO,
            (("ild", ">=", "transporter"),),
            (("push_rope", "ILD's tracking-loss gradient points one way whatever the start "
              "(`benchmarks.gradient_noise --method ild`)"),
             *((t, _ILD_NOISE) for t in CLOTH))),
    Finding("F5", "diff-CEM-MPC ≥ CEM-MPC ≫ diff-MPC", ALL,
            (("diff_cem_mpc", ">=", "cem_mpc"), ("cem_mpc", ">", "diff_mpc")),
            (("whip_rope", "diff-CEM-MPC under CEM-MPC: both maximise the reward two steps "
              "ahead, and the better optimiser of that myopic objective ends worse "
              "(`benchmarks.planner_objective`); CEM-MPC over diff-MPC by less than 2 SE "
              "of five chaotic episodes, not measured further"),
             *((t, "a ceiling: CEM-MPC reaches the expert's score on every seed and "
                "diff-MPC on most (the grid's rows)")
               for t in ("unfold_cloth1", "unfold_cloth3")))),
)


def stale_note(reasons: list[str], n_rows: int, included: bool) -> str:
    """The footer phrase for the stale rows of a table (``""`` when none is): how many,
    left out or included, and, when included, why each is stale (counted by kind,
    :func:`dax_algos.bench.report.stale_kinds`)."""
    if not reasons:
        return ""
    if not included:
        return f", {len(reasons)} stale rows left out"
    from dax_algos.bench import report

    counts = report.stale_kinds(reasons)
    return (f", **{len(reasons)} of {n_rows} rows are stale** and included (why: "
            + "; ".join(f"{text}: {n}" for text, n in counts.items()) + ")")


def _grid_path(path) -> Path:
    """``path`` as given when it exists or is absolute, else relative to the repository
    root (how the README blocks name their grids)."""
    from benchmarks._report import ROOT

    path = Path(path)
    return path if path.is_absolute() or path.exists() else ROOT / path


def _grid_rows(path, budget=None, include_stale=False):
    """``(rows that count, budget, stale note)`` of a grid directory or results CSV: the
    latest row per run, of ``budget`` (default: the last row's), stale rows left out
    unless ``include_stale``; the note (:func:`stale_note`) says which."""
    from dax_algos.bench import provenance, rundir, summary
    from dax_algos.bench.rows import latest, read_rows

    path = Path(path)
    full = _grid_path(path)
    csv_path = full if full.suffix == ".csv" else full / "results.csv"
    if not csv_path.is_file():
        raise ValueError(f"{path}: not a grid directory or results file (no {csv_path.name})")
    rows = latest(read_rows(csv_path))
    budget = summary.budgets(rows, budget)
    today = summary.today_of(rundir.read_run_file(csv_path.parent))
    rows = [r for r in rows if r["budget"] == budget]
    reasons = [provenance.stale_reason(r, today) for r in rows]
    fresh = [r for r, why in zip(rows, reasons, strict=True) if include_stale or not why]
    return fresh, budget, stale_note([w for w in reasons if w], len(rows), include_stale)


def _stats(rows, col="score"):
    """``{(task, method): (mean, se, n)}`` over the ok rows' ``col``."""
    from dax_algos.bench import report

    out = {}
    for (task, method), rs in report.group_rows(rows).items():
        xs = [float(r[col]) for r in rs if r["status"] == "ok" and r.get(col, "") != ""]
        if xs:
            mean, se = report.mean_se(xs)
            out[task, method] = (mean, 0.0 if math.isnan(se) else se, len(xs))
    return out


def check_claim(stats, task, a, op, b):
    """``(holds, difference, se)`` of one comparison on one task, or ``None`` when one of
    the two methods has no rows there."""
    if (task, a) not in stats or (task, b) not in stats:
        return None
    ma, sa, _ = stats[task, a]
    mb, sb, _ = stats[task, b]
    diff, se = ma - mb, math.hypot(sa, sb)
    holds = diff > 2 * se if op == ">" else diff > -2 * se
    return holds, diff, se


def findings(rows) -> list[dict]:
    """Per finding: its verdict, the tasks measured and the comparisons that failed."""
    stats = _stats(rows)
    out = []
    for f in FINDINGS:
        measured, failed = [], []
        for task in f.tasks:
            checks = [(c, check_claim(stats, task, *c)) for c in f.claims]
            if any(r is None for _, r in checks):
                continue
            measured.append(task)
            failed += [(task, c, r) for c, r in checks if not r[0]]
        verdict = ("not measured" if not measured else
                   "not reproduced" if failed else "reproduced")
        out.append({"finding": f, "measured": measured, "failed": failed,
                    "verdict": verdict})
    return out


def render_findings(path, budget=None, include_stale=False) -> str:
    """The findings table of the grid at ``path`` (see the module docstring)."""
    rows, budget, note = _grid_rows(path, budget, include_stale)
    lines = ["| finding | claim | tasks measured | verdict | where it fails (a − b ± SE) "
             "| why it fails there (measured) |",
             "|---|---|---|---|---|---|"]
    for f in findings(rows):
        fails = "; ".join(f"{t}: {a} {op} {b}: {d:+.3f} ± {se:.3f}"
                          for t, (a, op, b), (_, d, se) in f["failed"])
        by_reason: dict = {}  # the failing tasks that share a reason, named together
        for t in dict.fromkeys(t for t, _, _ in f["failed"]):
            by_reason.setdefault(f["finding"].reason(t), []).append(t)
        why = "; ".join(f"{', '.join(ts)}: {r}" for r, ts in by_reason.items())
        lines.append(f"| {f['finding'].name} | {f['finding'].text} | "
                     f"{', '.join(f['measured']) or '—'} | {f['verdict']} | {fails or '—'} "
                     f"| {why or '—'} |")
    lines += ["", f"From `{Path(path).as_posix()}`, {budget} budget"
              + note + ". `a > b`: a above "
              "b by more than 2 SE; `a ≥ b`: a not below b by more than 2 SE (SE of the "
              "difference from each row kind's SE: learners over training seeds, planners "
              "over episodes)." + equal_time_text(path, rows)]
    return "\n".join(lines) + "\n"


#: The comparison the learners issue asks for at equal wall-clock training time: a
#: gradient method against PPO on Whip-Rope.
EQUAL_TIME = ("whip_rope", ("apg", "shac"), "ppo")


def run_curves(path, rows) -> dict:
    """``{(task, method): {seed: [curve rows in update order]}}``: the learning curves in
    the grid at ``path`` (``learning_<task>.csv``, :mod:`dax_algos.bench.learning`) of the
    ok runs in ``rows``; each task's file read once."""
    from dax_algos.bench import learning

    full = _grid_path(path)
    out: dict = {}
    for task in sorted({r["task"] for r in rows}):
        runs = {(r["task"], r["method"], int(r["seed"]), r["budget"]) for r in rows
                if r["task"] == task and r["status"] == "ok"}
        lp = learning.learning_path(full, task)
        if not lp.exists():
            continue
        for c in learning.read_curves(lp, keep=runs):  # each run's in update order
            out.setdefault((task, c["method"]), {}).setdefault(c["seed"], []).append(c)
    return out


def training_seconds(path, rows) -> dict:
    """``{(task, method): mean training wall time per seed [s]}`` of the learners with a
    learning curve in the grid at ``path`` (the curve's last cumulative ``wall_s``: training
    only, evaluation excluded), for the runs in ``rows``."""
    return {k: float(np.mean([curve[-1]["wall_s"] for curve in seeds.values()]))
            for k, seeds in run_curves(path, rows).items()}


def equal_time_text(path, rows) -> str:
    """A sentence on :data:`EQUAL_TIME`: each gradient method's score and training time
    against PPO's, and whether it is above PPO by more than 2 SE with no more training time
    than PPO had (then it is above at equal time too, PPO having had as long or longer);
    ``""`` when the grid has no such pair."""
    task, grads, base = EQUAL_TIME
    stats, secs = _stats(rows), training_seconds(path, rows)
    parts = []
    for g in grads:
        check = check_claim(stats, task, g, ">", base)
        if check is None or (task, g) not in secs or (task, base) not in secs:
            continue
        holds, diff, se = check
        tg, tb = secs[task, g], secs[task, base]
        if holds and tg <= tb:
            verdict = "above at equal time (it trained no longer)"
        elif holds:
            verdict = (f"above, but it trained {tg / tb:.1f}x as long: not yet an "
                       "equal-time comparison")
        else:
            verdict = "not above"
        parts.append(f"{g} {diff:+.3f} ± {se:.3f} against {base}, training {tg:.0f} s "
                     f"against {tb:.0f} s per seed: {verdict}")
    if not parts:
        return ""
    return (f" At equal wall-clock training time on {task} (training only, mean over seeds, "
            "from the learning curves): " + "; ".join(parts) + ".")


def versus_untrained(rows) -> list[dict]:
    """Per (task, learner) with untrained scores: trained and untrained mean ± SE over
    seeds, the paired difference and its SE, and the verdict (above / within / below)."""
    from dax_algos.bench import report

    runs: dict = {}
    for r in rows:
        if r["status"] == "ok" and r.get("untrained_score", "") != "":
            runs.setdefault((r["task"], r["method"]), []).append(
                (float(r["score"]), float(r["untrained_score"])))
    out = []
    for (task, method), pairs in runs.items():
        x = np.asarray(pairs, np.float64)
        (m, s), (mu, su), (d, sd) = (report.mean_se(x[:, 0]), report.mean_se(x[:, 1]),
                                     report.mean_se(x[:, 0] - x[:, 1]))
        sd = 0.0 if math.isnan(sd) else sd
        verdict = ("above" if d > 2 * sd and len(x) > 1 else
                   "below" if d < -2 * sd and len(x) > 1 else "within")
        out.append({"task": task, "method": method, "n": len(x), "trained": (m, s),
                    "untrained": (mu, su), "difference": (d, sd), "verdict": verdict})
    return out


def _in_table_order(found: list[dict]) -> list[dict]:
    """``found`` (dicts with ``task`` and ``method``) sorted as the tables list them: by
    the registry's method order, then the task order of :data:`dax_tasks.TASKS`; names
    unknown to either last."""
    import dax_tasks
    from dax_algos import registry

    order = {t: i for i, t in enumerate(dax_tasks.TASKS)}
    methods = {m: i for i, m in enumerate(registry.names())}
    return sorted(found, key=lambda f: (methods.get(f["method"], 99),
                                        order.get(f["task"], 99)))


def added_seeds(rows) -> list[dict]:
    """The learner cells that hold seeds beyond the grid's common ones (the seed set most
    (task, learner) cells with untrained scores hold; ties: the smaller set): per such
    cell, :func:`versus_untrained` on the common seeds, on the added seeds alone and on
    all of them (``common``, ``added``, ``all``), and the added seeds. What a reader needs
    to judge a grid extended on some cells: how the verdict moved and what the new seeds
    alone say."""
    from dax_algos.bench import report

    learner = [r for r in rows if r["status"] == "ok" and r.get("untrained_score", "") != ""]
    cells = report.cell_seeds(learner)
    common = report.common_seeds(cells)
    out = []
    for (task, method), seeds in cells.items():
        extra = seeds - common
        if not extra:
            continue
        mine = [r for r in learner if (r["task"], r["method"]) == (task, method)]

        def verdict_on(keep, mine=mine):
            found = versus_untrained([r for r in mine if int(r["seed"]) in keep])
            return found[0] if found else None

        out.append({"task": task, "method": method, "common_seeds": sorted(common),
                    "added_seeds": sorted(extra), "common": verdict_on(common),
                    "added": verdict_on(extra), "all": verdict_on(seeds)})
    return out


def render_added_seeds(path, budget=None, include_stale=False) -> str:
    """The table of :func:`added_seeds` of the grid at ``path`` (Markdown)."""
    from dax_algos.bench import report

    rows, budget, note = _grid_rows(path, budget, include_stale)
    found = _in_table_order(added_seeds(rows))
    if not found:
        raise ValueError(f"{path}: no learner cell holds more seeds than the others")

    def diff(f):
        if f is None:
            return "—"
        d, sd = f["difference"]
        return f"{d:+.3f} ± {sd:.3f}" if f["n"] > 1 else f"{d:+.3f} (n=1)"

    def t_of(f):
        d, sd = f["difference"]
        return f" ({d / sd:.1f} SE)" if sd > 0 and f["n"] > 1 else ""

    common = report.span(found[0]["common_seeds"])
    lines = [f"| method | task | seeds {common} | verdict | added seeds | added alone | "
             "all seeds | verdict |", "|---|---|---|---|---|---|---|---|"]
    for f in found:
        c, a = f["common"], f["all"]
        lines.append(f"| {f['method']} | {f['task']} | {diff(c)} | "
                     f"{c['verdict'] if c else '—'} | {report.span(f['added_seeds'])} | "
                     f"{diff(f['added'])} | {diff(a)} | {a['verdict']}{t_of(a)} |")
    lines += ["", f"From `{Path(path).as_posix()}`, {budget} budget" + note
              + f": the learner cells holding seeds beyond {common}, the seeds most cells "
              "hold. Trained − untrained: the paired difference over those seeds, mean ± "
              "SE; above / below: by more than 2 SE; (x SE): the difference over all seeds "
              "in its SE."]
    return "\n".join(lines) + "\n"


def render_untrained(path, budget=None, include_stale=False) -> str:
    """The learners-against-their-untrained-policy table of the grid at ``path``."""
    rows, budget, note = _grid_rows(path, budget, include_stale)
    found = _in_table_order(versus_untrained(rows))

    def cell(ms):
        m, s = ms
        return f"{m:.3f} ± {s:.3f}" if not math.isnan(s) else f"{m:.3f} (n=1)"

    lines = ["| method | task | seeds | trained | untrained | trained − untrained | verdict |",
             "|---|---|---|---|---|---|---|"]
    for f in found:
        lines.append(f"| {f['method']} | {f['task']} | {f['n']} | {cell(f['trained'])} | "
                     f"{cell(f['untrained'])} | {cell(f['difference'])} | {f['verdict']} |")
    counts = {v: sum(f["verdict"] == v for f in found) for v in ("above", "within", "below")}
    lines += ["", f"From `{Path(path).as_posix()}`, {budget} budget"
              + note
              + f": {counts['above']} above, {counts['within']} within, {counts['below']} "
              "below. Mean ± SE over training seeds; the difference is paired by seed (the "
              "same evaluation starts); above / below: by more than 2 SE."]
    return "\n".join(lines) + "\n"
