"""Several processes (hosts) running one sharded batch of rollouts, forward and backward.

Start the same command on every host, each with its own ``--process-id``, from the
repository root::

    python -m benchmarks.distributed --coordinator HOST:PORT --num-processes N \\
        --process-id I [--task fold_cloth1] [--batch 8] [--steps 3] [--seed 0] \\
        [--set substeps=12 --set scene.n=4 ...] [--out result.json]

Each process joins the job first (:func:`dax_tasks.core.distributed.initialize`), then runs
:func:`dax_tasks.core.distributed.rollout_gradient`: a batch of rollouts of one task with
random actions, forward and backward (the gradient of the summed reward wrt every action),
split over every device of every process and gathered so every process holds the whole
result. The processes check that they agree
(:func:`jax.experimental.multihost_utils.assert_equal`) and each prints the result as one
JSON line (and writes it to ``--out``). Without ``--coordinator`` it runs in this process
alone, on its local devices: the reference the multi-process run is compared with
(``tests/multidevice/test_distributed.py``). Bad input is one ``error:`` line on stderr and
exit status 2.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys

import jax
from jax.experimental import multihost_utils

import dax_tasks
from dax_tasks.core.distributed import digest, initialize, rollout_gradient
from dax_tasks.core.spec import checked_fields
from dax_tasks.io import atomic_write


def parse_sets(task: str, sets: list[str]) -> dict:
    """``KEY=VALUE`` (a TaskSpec field, or ``scene.FIELD``) -> ``make`` overrides; VALUE is
    JSON (``12``, ``0.5``, ``[1, 2]``, ``true``) or else a string."""
    top, scene = {}, {}
    for item in sets:
        key, sep, raw = item.partition("=")
        if not sep or not key:
            raise ValueError(f"--set takes KEY=VALUE, got {item!r}")
        try:
            value = json.loads(raw)
        except json.JSONDecodeError:
            value = raw
        if key.startswith("scene."):
            scene[key[len("scene."):]] = value
        else:
            top[key] = value
    if scene:
        default = dax_tasks.get_spec(task).scene
        top["scene"] = dataclasses.replace(default,
                                           **checked_fields(default, scene, "scene."))
    return top


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m benchmarks.distributed",
                                description=__doc__.split("\n\n")[0])
    p.add_argument("--coordinator", help="HOST:PORT of process 0 (omit: one process)")
    p.add_argument("--num-processes", type=int, default=1)
    p.add_argument("--process-id", type=int, default=0)
    p.add_argument("--timeout", type=int, default=120,
                   help="seconds to wait for the other processes")
    p.add_argument("--task", default="fold_cloth1")
    p.add_argument("--batch", type=int, default=8)
    p.add_argument("--steps", type=int, default=3)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="a make() override: a TaskSpec field or scene.FIELD (repeatable)")
    p.add_argument("--no-goal-cache", action="store_true",
                   help="compute the goal instead of reading or writing the goal cache")
    p.add_argument("--out", help="also write the JSON result here")
    return p


def record(args, result: dict) -> dict:
    """The JSON record a process prints: who it is, what it ran, the result's digest and
    its arrays as lists."""
    return {"process_id": jax.process_index(), "process_count": jax.process_count(),
            "device_count": jax.device_count(),
            "local_device_count": jax.local_device_count(), "task": args.task,
            "batch": args.batch, "steps": args.steps, "seed": args.seed,
            "digest": digest(result), **{k: v.tolist() for k, v in result.items()}}


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    try:
        if args.coordinator is not None:
            initialize(args.coordinator, args.num_processes, args.process_id, args.timeout)
        elif args.num_processes != 1 or args.process_id != 0:
            raise ValueError("--num-processes / --process-id need --coordinator")
        env = dax_tasks.make(args.task, cache_goal=not args.no_goal_cache,
                             **parse_sets(args.task, args.set))
        result = rollout_gradient(env, args.batch, args.steps, args.seed)
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if jax.process_count() > 1:
        multihost_utils.assert_equal(result, "the processes' gathered results differ")
    line = json.dumps(record(args, result))
    print(line, flush=True)
    if args.out:
        atomic_write(args.out, line + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
