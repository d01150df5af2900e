"""Are the learners' budgets enough? Each (learner, task)'s learning curve, read off a grid.

    python -m benchmarks.tables budgets benchmarks/results/GRID

For every learner and task of a grid directory (its rows that count, of one budget, stale
rows left out: :func:`benchmarks.findings._grid_rows`) the table gives what the budget is
(environment steps and updates per training seed, the training wall time on the grid's
machine) and whether the curve has flattened by its end:

* the curve is ``learning_<task>.csv`` (:mod:`dax_algos.bench.learning`): per update, the
  mean final-step r_gt of the training episodes that ended in it (the behaviour policy,
  with PPO's exploration noise; the only per-update score a run records);
* per seed, ``Δ`` = the curve's mean over the last fifth of the updates minus its mean over
  the fifth before (updates with no finished episode left out); the table's ``Δ`` is the
  mean over seeds;
* the verdict compares ``Δ`` with the SE (over training seeds) of the evaluation score in
  ``results.csv``: *flat* when ``|Δ|`` is below it (the last fifth of the budget moves
  the score by less than its SE); else *rising* or *falling* when ``|Δ|`` is also more
  than 2 SE of ``Δ`` over seeds (a move the curves' noise does not explain), and *noisy*
  when it is not (the curve cannot tell). A run with fewer than 10 scored updates cannot
  be split in fifths: *too short*; one in which no training episode reached its end
  (fewer env steps per env than the horizon) has no score at all: *no episode ended*.
  For these two the table gives what reading the curve would take (:func:`steps_to_read`):
  the env steps per seed at which every env ends :data:`MIN_UPDATES` episodes, and the
  training wall time that would cost at the row's own rate.

A learner without environment steps (Transporter, trained on demonstrations only) has no
curve in the file; its row gives its Adam steps and wall time and the verdict ``no
curve``.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from benchmarks.findings import _grid_rows, _stats, run_curves

#: Fewer scored updates than this and a curve is not split in fifths.
MIN_UPDATES = 10


def _fifths_delta(scores) -> float:
    """Mean of the last fifth of ``scores`` (finite entries, in update order) minus the
    mean of the fifth before; NaN when there are fewer than :data:`MIN_UPDATES`."""
    ys = np.asarray([s for s in scores if math.isfinite(s)], float)
    if len(ys) < MIN_UPDATES:
        return math.nan
    k = len(ys) // 5
    return float(ys[-k:].mean() - ys[-2 * k:-k].mean())


def steps_to_read(task: str, method: str, budget: str, steps_per_update: float,
                  **overrides) -> int | None:
    """Env steps per training seed at which a curve of ``method``'s ``budget`` config on
    ``task`` (with config ``overrides``), at ``steps_per_update`` env steps per update
    (all envs), has :data:`MIN_UPDATES` scored updates. An update of
    ``u = steps_per_update / num_envs`` steps per env ends an episode in every env when
    ``u`` reaches the horizon ``h``, else in a fraction ``u / h`` of the updates:
    ``ceil(MIN_UPDATES * max(1, h / u))`` updates.
    ``None`` for a method that trains without envs (its config has no ``num_envs``)."""
    import dax_tasks
    from dax_algos import registry

    num_envs = getattr(registry.get(method).config(budget, task, **overrides), "num_envs",
                       None)
    if num_envs is None or not steps_per_update > 0:
        return None
    per_env = steps_per_update / num_envs
    updates = math.ceil(MIN_UPDATES * max(1.0, dax_tasks.get_spec(task).horizon / per_env)
                        - 1e-9)
    return round(updates * steps_per_update)


def curve_verdict(deltas, eval_se: float) -> tuple[float, float, str]:
    """``(Δ mean, Δ SE, verdict)`` of per-seed fifths ``deltas`` (:func:`_fifths_delta`,
    NaN where a seed's curve is too short) against the evaluation score's SE over seeds
    (the module docstring's rule): *too short* when no seed's curve splits."""
    from dax_algos.bench import report

    finite = [d for d in deltas if math.isfinite(d)]
    if not finite:
        return math.nan, math.nan, "too short"
    d_mean, d_se = report.mean_se(finite)
    if abs(d_mean) < eval_se:
        return d_mean, d_se, "flat"
    if abs(d_mean) > 2 * (0.0 if math.isnan(d_se) else d_se):
        return d_mean, d_se, "rising" if d_mean > 0 else "falling"
    return d_mean, d_se, "noisy"


def curve_budgets(path, budget=None, include_stale=False) -> tuple[list[dict], str, str]:
    """``(rows, budget, stale note)`` (:func:`benchmarks.findings.stale_note`): one dict
    per (task, learner) with curves or learner rows in the grid at ``path``: env steps and
    updates per seed, the mean training wall time, the per-seed fifths ``Δ`` (mean, SE),
    the evaluation score's SE, the number of seeds and the verdict (see the module
    docstring)."""
    from dax_algos import registry
    from dax_algos.bench import learning
    from dax_algos.method import LearnerMethod

    rows, budget, note = _grid_rows(path, budget, include_stale)
    stats = _stats(rows)
    ok = [r for r in rows if r["status"] == "ok"]
    learners = {m for m in {r["method"] for r in ok}
                if m in registry.names() and isinstance(registry.get(m), LearnerMethod)}
    curves = run_curves(path, [r for r in ok if r["method"] in learners])
    out = []
    for task in sorted({r["task"] for r in ok}):
        curve_file = learning.learning_path(".", task).name
        for method in sorted({r["method"] for r in ok
                              if r["task"] == task and r["method"] in learners}):
            mine = [r for r in ok if r["task"] == task and r["method"] == method]
            by_seed = curves.get((task, method), {})
            deltas, steps, updates, walls = [], [], [], []
            for rs in by_seed.values():
                deltas.append(_fifths_delta([c["score"] for c in rs]))
                steps.append(rs[-1]["env_steps"])
                updates.append(len(rs))
                walls.append(rs[-1]["wall_s"])
            if not walls:
                walls = [float(r["wall_s"]) for r in mine if r.get("wall_s")]
            _, eval_se, n = stats.get((task, method), (math.nan, math.nan, len(mine)))
            scored = any(math.isfinite(c["score"]) for rs in by_seed.values() for c in rs)
            d_mean, d_se, verdict = curve_verdict(deltas, eval_se)
            if not by_seed:
                verdict = "no curve"
            elif not scored:
                verdict = "no episode ended"
            env_steps = max(steps, default=0)
            wall = float(np.mean(walls)) if walls else math.nan
            n_updates = max(updates, default=0)
            to_read = (steps_to_read(task, method, budget, env_steps / n_updates)
                       if verdict in ("too short", "no episode ended") and n_updates
                       else None)
            out.append(dict(task=task, method=method, env_steps=env_steps,
                            updates=n_updates, wall_s=wall,
                            delta=d_mean, delta_se=d_se, eval_se=eval_se, n=n,
                            verdict=verdict, curve=curve_file if by_seed else None,
                            to_read=to_read,
                            to_read_wall_s=(wall * to_read / env_steps
                                            if to_read and env_steps else None)))
    return out, budget, note


def render_table(path, budget=None, include_stale=False) -> str:
    """The budget table of the grid at ``path`` (Markdown)."""
    rows, budget, note = curve_budgets(path, budget, include_stale)
    if not rows:
        raise ValueError(f"{path}: no learner rows in it")
    lines = ["| task | method | seeds | env steps / seed | updates | training wall (s) | "
             "Δ last fifth (± SE) | eval SE | verdict | to read: env steps / seed "
             "(training wall, s) | curve |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        delta = ("—" if not math.isfinite(r["delta"]) else
                 f"{r['delta']:+.3f} ± {0.0 if math.isnan(r['delta_se']) else r['delta_se']:.3f}")
        to_read = ("—" if r["to_read"] is None else f"{r['to_read']:,} ("
                   + ("?" if r["to_read_wall_s"] is None or math.isnan(r["to_read_wall_s"])
                      else f"{r['to_read_wall_s']:,.0f}") + ")")
        lines.append(
            f"| {r['task']} | {r['method']} | {r['n']} | {r['env_steps']:.0f} | {r['updates']} | "
            f"{r['wall_s']:.0f} | {delta} | {r['eval_se']:.3f} | {r['verdict']} | "
            f"{to_read} | {'`' + r['curve'] + '`' if r['curve'] else '—'} |")
    lines += ["", f"From `{Path(path).as_posix()}`, {budget} budget"
              + note
              + ". Seeds: the row's training seeds (its curves and evaluation scores). "
              "Curve: per update, "
              "the mean final-step r_gt of the training episodes that ended in it. Δ: per "
              "seed, the mean over the last fifth of the updates minus the fifth before, mean "
              "± SE over seeds; flat when |Δ| is below the SE of the evaluation score (over "
              "seeds), rising or falling when |Δ| is also above 2 SE of Δ, else noisy; wall "
              "time: training only, mean over seeds, on "
              "the grid's machine (run.json). To read: for a curve too short to split "
              f"(fewer than {MIN_UPDATES} updates that end an episode), the env steps per "
              f"seed at which each env ends {MIN_UPDATES} episodes, and its training wall "
              "time at the row's own rate (an estimate, not a run)."]
    return "\n".join(lines) + "\n"


def env_rate(task_record: dict, batch: int, grad: bool) -> float:
    """The environment's own steps per second at ``batch`` from a throughput document's
    task record (:func:`benchmarks.tasks.throughput_main`), forward or with the action
    gradient: interpolated linearly in log(rate) against log(batch) between the measured
    batches, the nearest measured one outside them; NaN when none was measured."""
    key = "grad_steps_per_s" if grad else "steps_per_s"
    pts = sorted((r["batch"], r[key]) for r in task_record["rows"]
                 if r.get("measured") and r.get(key))
    if not pts:
        return math.nan
    bs, rs = np.log([p[0] for p in pts]), np.log([p[1] for p in pts])
    return float(np.exp(np.interp(math.log(batch), bs, rs)))


def training_throughput(grid, throughput, budget=None, include_stale=False) -> list[dict]:
    """Per (task, learner) of the grid with a learning curve: environment steps per second
    of training (the curve's last cumulative env steps over its last cumulative wall time,
    mean over seeds), the batch it trains at (the budget's ``num_envs``), the environment's
    own rate at that batch from the throughput document (with the action gradient for a
    method that differentiates the simulator) and their ratio: the share of training time
    the environment's steps would take alone."""
    import json

    from dax_algos import registry

    rows, budget, _ = curve_budgets(grid, budget, include_stale)
    tp = Path(throughput)
    if not tp.is_file():
        from benchmarks._report import ROOT
        tp = ROOT / throughput
    doc = json.loads(tp.read_text())
    if doc.get("bench") != "throughput":
        raise ValueError(f"{throughput}: not a throughput document")
    records = {t["task"]: t for t in doc["tasks"]}
    out = []
    for r in rows:
        if not r["env_steps"] or r["task"] not in records:
            continue
        method = registry.get(r["method"])
        config = method.config(budget, r["task"])
        batch = int(getattr(config, "num_envs", 1))
        rate = r["env_steps"] / r["wall_s"]
        env = env_rate(records[r["task"]], batch, method.uses_gradients)
        out.append(dict(task=r["task"], method=r["method"], batch=batch, train_rate=rate,
                        env_rate=env, grad=method.uses_gradients, share=rate / env))
    return out


def render_throughput(grid, throughput, budget=None, include_stale=False) -> str:
    """The training throughput table (Markdown) of the grid at ``grid`` beside the
    environment's own rates in the throughput document ``throughput``."""
    rows = training_throughput(grid, throughput, budget, include_stale)
    if not rows:
        raise ValueError(f"{grid}: no learner with a learning curve on a task of {throughput}")
    lines = ["| task | method | envs | training: env steps/s | env alone at that batch: "
             "steps/s | env's share of training time |", "|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['task']} | {r['method']} | {r['batch']} | {r['train_rate']:.1f} | "
                     f"{r['env_rate']:.1f}{' (grad)' if r['grad'] else ''} | "
                     f"{100 * r['share']:.0f} % |")
    lines += ["", f"Training rate: from `{Path(grid).as_posix()}` (its learning curves: "
              "cumulative env steps over cumulative training wall time, mean over seeds; "
              "evaluation excluded). Env alone: `" + Path(throughput).as_posix() + "` (the "
              "forward step, or with the action gradient for a method that differentiates "
              "the simulator), interpolated in log-log between its measured batches. Share: "
              "training rate over the env's rate, the part of training the env's steps "
              "would take alone; near or above 100 % the env step is the bottleneck (the "
              "two files were measured in different sittings, each on 2 shared cores)."]
    return "\n".join(lines) + "\n"


def render_reads(*paths) -> str:
    """The budget reads (Markdown): per ablation file (:mod:`benchmarks.ablate`) and each
    of its variants that changes only ``total_env_steps`` (a longer run of the budget's
    config, e.g. ``to_read``), its curve judged by the budget table's rule
    (:func:`curve_verdict`, against the SE of the read's own evaluation over seeds), its
    evaluation against the budget's (the file's baseline, paired by seed) and what that
    says of the budget: *stays* unless the read (a longer run, or a shorter one such as
    ``half``) scores above the budget by more than 2 SE of the paired difference, then
    *longer* or *shorter is better* (by the curves' lengths)."""
    from benchmarks._report import read_result
    from benchmarks.ablate import summarise

    lines = ["| task | method | variant | updates: budget → read | env steps / seed | seeds "
             "| Δ last fifth (± SE) | eval SE | verdict | score: budget → read | read − "
             "budget (paired) | budget |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for path in paths:
        _, records = read_result(path)
        seeds = [r for r in records if not r.get("summary") and r["status"] == "ok"]
        base = [r for r in seeds if r["variant"] == "baseline"]
        summaries = {s["variant"]: s for s in summarise(seeds)}
        for variant, s in summaries.items():
            if variant == "baseline" or set(s["changes"]) != {"total_env_steps"}:
                continue
            runs = [r for r in seeds if r["variant"] == variant]
            deltas = [_fifths_delta([math.nan if c is None else c for c in r["curve"]])
                      for r in runs]
            d_mean, d_se, verdict = curve_verdict(deltas, s["score_se"])
            b = summaries["baseline"]
            diff, dse = s["minus_baseline"], s["minus_baseline_se"]
            n_base, n_read = (max(len(r["curve"]) for r in rs) for rs in (base, runs))
            verdict_budget = (("**shorter is better**" if n_read < n_base
                               else "**longer is better**") if s["better"] else "stays")
            lines.append(
                f"| {s['task']} | {s['method']} | `{variant}` | {n_base} → {n_read} | "
                f"{s['changes']['total_env_steps']:,} | {len(runs)} | "
                + ("—" if math.isnan(d_mean) else f"{d_mean:+.3f} ± {d_se:.3f}")
                + f" | {s['score_se']:.3f} | {verdict} | {b['score_mean']:.3f} → "
                f"{s['score_mean']:.3f} | {diff:+.3f} ± {dse:.3f} | "
                + verdict_budget + " |")
    names = ", ".join(f"`{Path(p).as_posix()}`" for p in paths)
    lines += ["", f"From {names}. A read: the budget's config run for more (or fewer) "
              "env steps per seed (the variant's), on the seeds of the budget's rows. Updates: the "
              "curve's length. Δ: per seed, the curve's last fifth minus the fifth before, "
              "mean ± SE over seeds; flat when |Δ| is below the SE of the read's evaluation "
              "score, rising or falling when |Δ| is also above 2 SE of Δ, else noisy (the "
              "budget table's rule). Scores: mean final-step r_gt of the evaluation "
              "rollouts, mean over seeds; the difference paired by seed. The budget stays "
              "unless the read scores above it by more than 2 SE."]
    return "\n".join(lines) + "\n"
