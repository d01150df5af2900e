"""What the planners optimise against what they are scored on (JSON lines).

A model-predictive planner picks each action by the planning objective over its own short
horizon (``CEMConfig.objective``: the env's reward after the plan's last step, or the sum
over its steps; the reward is r_gt + aux_weight · aux, and the planners run at the default
weight 0, so it is r_gt); the episode is scored by the final step's r_gt alone. diff-CEM-MPC refines
CEM's best plan by gradient ascent on that objective and keeps the better of the two, so
from the same state it never plans worse than CEM by the objective. Where it still scores
worse (the finding "diff-CEM-MPC >= CEM-MPC"), the question is whether it won what it
optimised and lost the score, or lost both. For each method and seed this runs the grid's
episode (the registry's config for the task and budget, ``PRNGKey(seed)``: the same
episode as the grid row on the same machine) and records per step the objective of the
chosen plan, the executed reward and r_gt.

    python -m benchmarks.planner_objective whip_rope --seeds 5 \\
        --out benchmarks/results/DATE-planner-objective-whip_rope.jsonl

Each (method, seed) is one JSON line, appended as it finishes (a rerun skips those there).
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import jax
import numpy as np

import dax_tasks
from dax_algos import registry
from dax_algos.bench import csvlog, report

METHODS = ("cem_mpc", "diff_cem_mpc")


def measure(env, task: str, method: str, seed: int, budget: str = "full",
            overrides: dict | None = None, compiled=None) -> tuple[dict, object]:
    """``(record, compiled episode)`` of one planner episode: ``score`` (final r_gt),
    per step ``objective`` (the chosen plan's planning value), ``reward`` (the env's reward
    of the executed step) and ``r_gt``; their means. ``compiled``: the episode compiled by
    an earlier call for the same method (reused)."""
    config = registry.get(method).config(budget, task, **(overrides or {}))
    params = env.default_params
    if compiled is None:
        run = registry.get(method).build(env, config)
        compiled = jax.jit(run.episode).lower(jax.random.PRNGKey(0), params).compile()
    t0 = time.perf_counter()
    out = jax.device_get(jax.block_until_ready(compiled(jax.random.PRNGKey(seed), params)))
    wall = time.perf_counter() - t0
    objective = np.asarray(out.stats.objective, np.float64)
    reward = np.asarray(out.reward, np.float64)
    r_gt = np.asarray(out.r_gt, np.float64)
    rec = dict(task=task, method=method, seed=seed, budget=budget, score=float(out.score),
               objective_mean=float(objective.mean()), reward_mean=float(reward.mean()),
               r_gt_mean=float(r_gt.mean()), objective=objective.tolist(),
               reward=reward.tolist(), r_gt=r_gt.tolist(), wall_s=round(wall, 2),
               load_1min=os.getloadavg()[0], date=time.strftime("%Y-%m-%d"),
               device=f"{jax.devices()[0].platform}:{jax.devices()[0].device_kind}")
    return rec, compiled


def _mean_se(xs) -> str:
    mean, se = report.mean_se(xs)
    return f"{mean:.3f} ± {se:.3f}" if len(xs) > 1 else f"{mean:.3f} (n=1)"


def render_table(path) -> str:
    """Per task and method: the final score, the mean executed reward (what the planning
    objective rewards, step by step), the mean chosen-plan objective and the mean r_gt over
    the episode's first and last fifth, mean ± SE over seeds; and each method against the
    first (paired by seed)."""
    from benchmarks._report import file_date, load_range, read_result

    path, recs = read_result(path)
    out = ["| task | method | seeds | final r_gt (score) | mean executed reward | mean planned "
           "objective | r_gt, first fifth of the steps | r_gt, last fifth |",
           "|---|---|---|---|---|---|---|---|"]
    groups: dict = {}
    for r in recs:
        groups.setdefault((r["task"], r["method"]), {})[r["seed"]] = r
    for (task, method), by_seed in groups.items():
        rs = list(by_seed.values())
        out.append(f"| {task} | {method} | {len(rs)} | {_mean_se([r['score'] for r in rs])} | "
                   f"{_mean_se([r['reward_mean'] for r in rs])} | "
                   f"{_mean_se([r['objective_mean'] for r in rs])} | "
                   f"{_mean_se([_fifth(r, 0) for r in rs])} | "
                   f"{_mean_se([_fifth(r, -1) for r in rs])} |")
    pairs = []
    tasks = dict.fromkeys(t for t, _ in groups)
    for task in tasks:
        methods = [m for t, m in groups if t == task]
        for m in methods[1:]:
            a, b = groups[(task, methods[0])], groups[(task, m)]
            seeds = sorted(set(a) & set(b))
            if len(seeds) < 2:
                continue
            d = {k: [b[s][k] - a[s][k] for s in seeds] for k in ("score", "reward_mean")}
            early = [_fifth(b[s], 0) - _fifth(a[s], 0) for s in seeds]
            late = [_fifth(b[s], -1) - _fifth(a[s], -1) for s in seeds]
            pairs.append(f"{task}: {m} − {methods[0]} ({len(seeds)} seeds): score "
                         f"{_signed(d['score'])}, mean executed reward "
                         f"{_signed(d['reward_mean'])}, r_gt over the first fifth "
                         f"{_signed(early)}, over the last fifth {_signed(late)}")
    loads = load_range(r.get("load_1min") for r in recs)
    devices = sorted({r.get("device", "cpu:cpu") for r in recs})
    out += ["", "Each row: the grid's episode of that method and seed (the registry's config, "
            "`PRNGKey(seed)`), re-run with its per-step record. Executed reward: the env's "
            "reward of each executed step (r_gt + aux_weight · aux, at the default weight 0: "
            "r_gt), the quantity the planning objective scores at the end of the plan's "
            "horizon; planned objective: the chosen plan's value at each step. "
            + ("Paired by seed: " + "; ".join(pairs) + ". " if pairs else "")
            + f"{', '.join(devices)}, 1-minute load {loads}; `{path.as_posix()}` "
            f"({file_date(path) or 'date not recorded'})."]
    return "\n".join(out) + "\n"


def _fifth(rec, which: int) -> float:
    """The mean r_gt over the first (``which`` 0) or last (-1) fifth of the episode's steps."""
    r = np.asarray(rec["r_gt"], np.float64)
    n = max(1, len(r) // 5)
    return float(r[:n].mean() if which == 0 else r[-n:].mean())


def _signed(xs) -> str:
    mean, se = report.mean_se(xs)
    return f"{mean:+.3f} ± {se:.3f}"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("task", choices=sorted(dax_tasks.TASKS))
    p.add_argument("--methods", default=",".join(METHODS))
    p.add_argument("--seeds", type=int, default=5)
    p.add_argument("--budget", choices=("quick", "full"), default="full")
    p.add_argument("--out", required=True, help="JSON lines file (appended; rerun resumes)")
    args = p.parse_args(argv)
    methods = [m for m in args.methods.split(",") if m]
    for m in methods:
        if registry.get(m).family != "planning":
            p.error(f"{m} is not a planner")
    out = Path(args.out)
    done = set()
    if out.exists():
        from benchmarks._report import read_records  # a torn last line dropped

        done = {(r["method"], r["seed"]) for r in read_records(out)
                if r.get("task") == args.task}
    env = dax_tasks.make(args.task)
    for m in methods:
        compiled = None
        for s in range(args.seeds):
            if (m, s) in done:
                continue
            rec, compiled = measure(env, args.task, m, s, args.budget, compiled=compiled)
            csvlog.append(out, json.dumps(rec) + "\n")  # one fsynced write, torn line cut
            print(f"{m} seed {s}: score {rec['score']:.4f}, mean reward "
                  f"{rec['reward_mean']:.4f}, mean objective {rec['objective_mean']:.4f} "
                  f"({rec['wall_s']} s)", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
