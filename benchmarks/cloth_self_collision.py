"""What self-collision costs a cloth task per env step (issue 16).

For each task, one env step (the expert's first action from ``PRNGKey(0)``) compiled ahead
of time three times, with the task's self-collision (its pair search, every pair on the
task meshes), with the same contact through the 16-slot spatial hash (``self_search=
"hash"``, the tasks' search until 2026-11-25) and with ``thickness=0`` (off), then timed
interleaved (on, hash, off, on, ...) in this one process, so that a load shared with other
processes falls on all alike; prints one JSON line per task with the medians and the
ratios to the step without self-collision. Usage:
    python -m benchmarks.cloth_self_collision [--tasks fold_cloth1,fold_tshirt] [--reps 9]

Fold-Cloth-3 and the unfold tasks have Fold-Cloth-1's cloth, contact and substeps.
"""

import argparse
import dataclasses
import json
import os
import time

import jax
import numpy as np

import dax_tasks


def _compiled(name, thickness, **scene):
    spec = dax_tasks.get_spec(name)
    env = dax_tasks.make(name, cache_goal=False,
                         scene=dataclasses.replace(spec.scene, thickness=thickness, **scene))
    params = env.default_params
    _, state = jax.jit(env.reset)(jax.random.PRNGKey(0), params)
    action = env.expert_action(state, params)
    step = jax.jit(env.step).lower(state, action, params).compile()
    jax.block_until_ready(step(state, action, params))
    return step, (state, action, params)


def measure(name, reps):
    thickness = dax_tasks.get_spec(name).scene.thickness
    if not thickness > 0:
        raise ValueError(f"{name} has no self-collision to measure")
    runs = {"on": _compiled(name, thickness),
            "hash": _compiled(name, thickness, self_search="hash"),
            "off": _compiled(name, 0.0)}
    times = {label: [] for label in runs}
    for _ in range(reps):
        for label, (step, args) in runs.items():
            t0 = time.perf_counter()
            jax.block_until_ready(step(*args))
            times[label].append(time.perf_counter() - t0)
    on, hashed, off = (float(np.median(times[k])) for k in ("on", "hash", "off"))
    spec = dax_tasks.get_spec(name)
    return dict(task=name, thickness_m=thickness, substeps=spec.substeps,
                self_search=spec.scene.self_search, step_on_s=round(on, 4),
                step_hash_s=round(hashed, 4), step_off_s=round(off, 4),
                ratio=round(on / off, 2), ratio_hash=round(hashed / off, 2),
                reps=reps, load_1min=round(os.getloadavg()[0], 2))


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", default="fold_cloth1,fold_tshirt")
    parser.add_argument("--reps", type=int, default=9)
    args = parser.parse_args(argv)
    for name in args.tasks.split(","):
        print(json.dumps(measure(name, args.reps)), flush=True)


if __name__ == "__main__":
    main()
