"""What ILD's per-part weighting of the state distance does (JSON lines and a chart).

The ILD paper names the open problem: a state of many particle coordinates and a few
gripper coordinates, matched as one vector, drowns the gripper's signal (pouring). This
trains ILD on one task with several weightings of the object and end-effector terms
(:func:`dax_algos.il.ild.state_distance`), the same seeds, budget and demonstration for
each, and reports each one's evaluation score (mean ± SE over seeds of the mean final-step
r_gt of ``n_eval`` rollouts), its tracking loss over training and its seconds per seed:

* ``flat``: the whole state as one vector (the end effector 1 / (N + 1) of the weight);
* ``per_part``: each part's mean, weighted 1 : 1 (the default);
* ``effector x10``: per part, the end effector weighted 10;
* ``object only`` / ``effector only``: one of the two terms alone.

    python -m benchmarks.ild_weighting --task pour_water --seeds 2 --out DIR

writes ``ild_weighting_<task>.jsonl`` and ``ild_weighting_<task>.png`` into DIR.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import dax_tasks
from dax_algos import learner, registry
from dax_algos.bench import report
from dax_algos.il import demos
from dax_algos.method import BUDGETS
from dax_tasks.io import atomic_write

WEIGHTINGS = {
    "flat": dict(weighting="flat"),
    "per_part": dict(weighting="per_part"),
    "effector x10": dict(weighting="per_part", effector_weight=10.0),
    "object only": dict(weighting="per_part", effector_weight=0.0),
    "effector only": dict(weighting="per_part", object_weight=0.0),
}


def run(task: str, seeds: int, budget: str = "full", names=tuple(WEIGHTINGS),
        demo_dir=None, overrides: dict | None = None) -> list[dict]:
    """One record per weighting (see the module docstring)."""
    env = dax_tasks.make(task)
    method = registry.get("ild")
    keys = jax.vmap(jax.random.PRNGKey)(jnp.arange(seeds))
    records = []
    for name in names:
        config = method.config(budget, task, **{**(overrides or {}), **WEIGHTINGS[name]})
        runnable = method.build(env, config)
        data = runnable.demos.load(env, demos.locate(env, runnable.demos, demo_dir))
        fn = jax.jit(jax.vmap(runnable.episode, in_axes=(0, None, None)))
        compiled = fn.lower(keys, env.default_params, data).compile()
        t0 = time.perf_counter()
        out = jax.device_get(jax.block_until_ready(compiled(keys, env.default_params, data)))
        wall = (time.perf_counter() - t0) / seeds
        scores = np.asarray(out.episode.score, np.float64)
        mean, se = report.mean_se(scores)
        rollouts = rollout_scores(env, config, out.policy, keys)
        records.append({
            "task": task, "weighting": name, "config": {k: v for k, v in
                                                        WEIGHTINGS[name].items()},
            "budget": budget, "seeds": seeds, "score_mean": mean, "score_se": se,
            "scores": scores.tolist(),
            "rollout_scores": rollouts.tolist(),
            "rollout_se": report.mean_se(rollouts.ravel())[1],
            "loss_per_update": np.asarray(out.metrics.loss).mean(0).tolist(),
            "train_score_per_update": np.nanmean(np.asarray(out.metrics.score), 0).tolist(),
            "nonfinite_grads": int(np.sum(out.metrics.nonfinite)),
            "seconds_per_seed": round(wall, 2), "env_steps": runnable.env_steps})
        print(json.dumps(records[-1]), flush=True)
    return records


def rollout_scores(env, config, policies, keys) -> np.ndarray:
    """``(seeds, n_eval)`` final-step r_gt of every evaluation rollout of the trained
    ``policies`` (batched over seeds), replayed as the runner evaluates (same starts, under
    ``vmap`` over the seeds): the SE over the evaluation starts, the only spread there is
    with one training seed."""
    act = registry.get("ild").learner.make_act(env, config)
    evaluate = learner.make_evaluate(env, act, config.n_eval, per_rollout=True)
    starts = jax.vmap(lambda k: jax.random.fold_in(k, 0))(keys)
    out = jax.jit(jax.vmap(evaluate, in_axes=(0, 0, None)))(policies, starts,
                                                            env.default_params)
    return np.asarray(jax.device_get(out.score), np.float64)


def chart(records: list[dict], path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(10, 4))
    names = [r["weighting"] for r in records]
    means = [r["score_mean"] for r in records]
    # one seed: the error bar is the SE over its evaluation rollouts
    ses = [r["score_se"] if np.isfinite(r["score_se"]) else r.get("rollout_se", 0.0)
           for r in records]
    ax.bar(names, means, yerr=ses, capsize=4, color=[f"C{i}" for i in range(len(names))])
    for i, r in enumerate(records):
        ax.plot([i] * len(r["scores"]), r["scores"], "k.", alpha=0.5)
    ax.set_ylabel("evaluation score (final-step r_gt)")
    ax.tick_params(axis="x", rotation=20)
    ax.grid(True, axis="y", alpha=0.3)
    for i, r in enumerate(records):
        loss = np.asarray(r["loss_per_update"])
        ax2.plot(np.arange(1, len(loss) + 1), loss / loss[0], color=f"C{i}",
                 label=r["weighting"])
    ax2.set_xlabel("update")
    ax2.set_ylabel("tracking loss / first update's")
    ax2.set_yscale("log")
    ax2.legend(fontsize=8)
    ax2.grid(True, alpha=0.3)
    r0 = records[0]
    spread = ("mean ± SE over seeds, dots: seeds" if r0["seeds"] > 1 else
              "one seed, mean ± SE over its evaluation rollouts")
    fig.suptitle(f"ILD on {r0['task']}: weighting of the object and end-effector terms "
                 f"({r0['budget']} budget; {spread})")
    fig.tight_layout()
    path = Path(path)
    atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=100))
    plt.close(fig)
    return path


def render_table(path) -> str:
    """The Markdown table of :func:`run`'s records (the JSON lines :func:`main` writes):
    per weighting its config, its score (mean ± SE: over training seeds, or over the
    evaluation rollouts where there was one seed, as the table states), its tracking loss
    after the last update over the first update's, its env steps and seconds per seed."""
    import math

    from benchmarks._report import file_date, read_result

    path, recs = read_result(path)
    out = ["| weighting (config) | score | tracking loss after the last update / first "
           "update's | training seconds per seed |", "|---|---|---|---|"]
    conventions = set()
    for r in recs:
        one = r["seeds"] == 1 or not math.isfinite(r.get("score_se", float("nan")))
        se = r["rollout_se"] if one else r["score_se"]
        n = len(r["rollout_scores"][0]) if one else r["seeds"]
        conventions.add(f"over the {n} evaluation rollouts of its one training seed" if one
                        else f"over its {n} training seeds")
        cfg = ", ".join(f"{k}={v}" for k, v in r["config"].items())
        loss = r["loss_per_update"]
        out.append(f"| `{r['weighting']}` ({cfg}) | {r['score_mean']:.3f} ± {se:.3f} | "
                   f"{loss[-1] / loss[0]:.2f} after {len(loss)} updates | "
                   f"{r['seconds_per_seed']:.0f} |")
    tasks = sorted({r["task"] for r in recs})
    budgets = sorted({f"{r['budget']} budget, {r['env_steps']} env steps" for r in recs})
    out += ["", f"{', '.join(tasks)}, {'; '.join(budgets)}; score: the mean final-step r_gt "
            f"of the trained policy's evaluation rollouts, ± the standard error "
            f"{' / '.join(sorted(conventions))}. Non-finite gradients: "
            f"{sum(r.get('nonfinite_grads', 0) for r in recs)}. The file records neither "
            f"the machine nor its load; `{path.as_posix()}` "
            f"({file_date(path) or 'date not recorded'})."]
    return "\n".join(out) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.ild_weighting",
                                description=__doc__.split("\n\n")[0])
    p.add_argument("--task", default="pour_water")
    p.add_argument("--seeds", type=int, default=2)
    p.add_argument("--budget", default="full", choices=BUDGETS)
    p.add_argument("--weightings", default=",".join(WEIGHTINGS),
                   help=f"comma-separated, of: {', '.join(WEIGHTINGS)}")
    p.add_argument("--demos", default=None, help="demonstration directory")
    p.add_argument("--out", required=True, help="output directory")
    args = p.parse_args(argv)
    names = [n.strip() for n in args.weightings.split(",")]
    unknown = [n for n in names if n not in WEIGHTINGS]
    if unknown:
        p.error(f"unknown weighting(s) {unknown}; valid: {', '.join(WEIGHTINGS)}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    records = run(args.task, args.seeds, args.budget, names, args.demos)
    atomic_write(out / f"ild_weighting_{args.task}.jsonl",
                 "".join(json.dumps(r) + "\n" for r in records))
    print(chart(records, out / f"ild_weighting_{args.task}.png"), file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
