"""Re-evaluate the policies a ``dax-bench run`` saved, rollout by rollout: mean and
standard error of the final-step r_gt over the evaluation starts.

A learner's results row holds the mean of its ``n_eval`` evaluation rollouts (20 at the
full budget); with one training seed the spread across rows says nothing, so this tool
loads each ``policies/<task>/<method>/seed<k>.msgpack`` under ``--out``, replays the same
evaluation (the same starts, ``fold_in(PRNGKey(k), 0)``, the task's default params) and
prints, per file, the mean ± SE over the rollouts beside the row's score. The replay runs
unbatched, one seed, as the runner runs its seeds: a program of another batch shape
rounds differently, and that alone flipped a Transporter pick (its argmax) in one of 20
Fold-Cloth-3 rollouts (0.662 against the row's 0.643) when the runner still trained its
seeds together under ``vmap``.

    python -m benchmarks.eval_trained --out results --json > eval.jsonl
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

import jax

import dax_tasks
from dax_algos.bench import trained


def _rows(path: Path) -> dict:
    """The results rows by (task, method, seed), read without touching the file (a run may
    be appending to it)."""
    if not path.is_file():
        return {}
    with open(path, newline="") as f:
        rows = [r for r in csv.DictReader(f) if None not in r.values()]
    return {(r.get("task"), r.get("method"), r.get("seed")): r for r in rows}


def saved_policies(out, tasks=None, methods=None):
    """``(path, task, method, seed)`` of each policy a ``dax-bench run`` saved under
    ``out/policies/<task>/<method>/seed<k>.msgpack``, sorted; only ``tasks`` / ``methods``
    (sets of names) where given."""
    for path in sorted(Path(out, "policies").glob("*/*/seed*.msgpack")):
        task, method = path.parent.parent.name, path.parent.name
        if (tasks and task not in tasks) or (methods and method not in methods):
            continue
        yield path, task, method, int(path.stem.removeprefix("seed").split(".")[0])


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.eval_trained",
                                description=__doc__.split("\n\n")[0])
    p.add_argument("--out", required=True, help="the dax-bench output directory")
    p.add_argument("--tasks", default=None, help="comma-separated (default: every task)")
    p.add_argument("--methods", default=None, help="comma-separated (default: every one)")
    p.add_argument("--json", action="store_true", help="one JSON object per line")
    args = p.parse_args(argv)
    out = Path(args.out)
    root = out / "policies"
    if not root.is_dir():
        print(f"eval_trained: {root}: no such directory (run dax-bench with --out {out})",
              file=sys.stderr)
        return 2
    tasks = set(args.tasks.split(",")) if args.tasks else None
    methods = set(args.methods.split(",")) if args.methods else None
    rows = _rows(out / "results.csv")
    for path, task, method, seed in saved_policies(out, tasks, methods):
        rec = trained.evaluate_trained(path, dax_tasks.make(task), method, seed)
        row = rows.get((task, method, str(seed)))
        rec["row_score"] = float(row["score"]) if row and row.get("score") else None
        if args.json:
            print(json.dumps(rec), flush=True)
        else:
            print(f"{task:14s} {method:16s} seed {seed}: {rec['mean']:.3f} ± {rec['se']:.3f}"
                  f" over {rec['n_rollouts']} rollouts (row: {rec['row_score']})", flush=True)
        jax.clear_caches()
    return 0


if __name__ == "__main__":
    sys.exit(main())
