"""Diff-MPC on Fold-Cloth-1 with the table's Coulomb friction and with the smooth friction
law (``ClothScene.friction_model="smooth"``, see dax_physics.cloth.ClothConfig), the same
runner, budget and seeds as ``dax-bench run --tasks fold_cloth1 --methods diff_mpc``.

    python -m benchmarks.friction_smoothing --seeds 2 --quick --out bench_out/friction

The smoothed task is a different physics model: its goal (the scripted fold) is computed
with it, and the planner is scored on it, not on the Coulomb task. Prints one JSON line:
per model, the mean score, each seed's score and the wall time.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
from pathlib import Path

import dax_tasks
from dax_algos.bench.grid import run_grid


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--task", default="fold_cloth1")
    ap.add_argument("--method", default="diff_mpc")
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--out", default="bench_out/friction")
    args = ap.parse_args(argv)
    scene = dax_tasks.get_spec(args.task).scene
    record = dict(bench="friction-smoothing", task=args.task, method=args.method,
                  seeds=args.seeds, budget="quick" if args.quick else "full")
    for model in ("coulomb", "smooth"):
        overrides = {args.task: dict(scene=dataclasses.replace(scene, friction_model=model))}
        rows = run_grid(args.task, args.method, args.seeds, Path(args.out) / model,
                        quick=args.quick, task_overrides=overrides, progress=False)
        ok = [r for r in rows if r["status"] == "ok"]
        scores = [float(r["score"]) for r in ok]
        record[model] = dict(
            scores=scores, mean=statistics.fmean(scores) if scores else None,
            wall_s=[float(r["wall_s"]) for r in ok],
            failed=[r["error"] for r in rows if r["status"] != "ok"])
    print(json.dumps(record), flush=True)


if __name__ == "__main__":
    main()
