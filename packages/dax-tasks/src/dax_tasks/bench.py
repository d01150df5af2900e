"""Benchmark of the tasks: per task and batch size, reset time, forward step time,
step-plus-gradient time (gradient of the summed reward with respect to the actions) and
the compile time of each, with the resolution the task runs at. One JSON line per task on
stdout (``--json``); progress on stderr. Speed is measured here, never asserted in tests.

    python -m dax_tasks.bench --json                         # all tasks, batch 1 and 8
    python -m dax_tasks.bench --json --tasks fold_cloth1 --batch 1 --reps 5

Times are medians over ``--reps`` calls after the compiled function's first call; compile
times come from lowering and compiling ahead of time (set ``JAX_COMPILATION_CACHE_DIR``
unset to see cold compiles). ``per_env_step_s`` = step time / batch size. The actions
timed are the task's scripted expert's (so the gripper touches the object), else the
middle of the action box. ``grad_finite`` says whether that gradient was finite
(``grad_norm`` is null when it was not, so the output stays strict JSON).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from dax_physics.bench import _emit, _median_time, _peak_rss_mb

from .registry import TASKS, available, make

#: Scene fields reported as the task's resolution when the scene has them.
RESOLUTION_FIELDS = ("dx", "dt", "domain", "window", "ppc", "n", "size", "spacing", "shape")


def resolution(task) -> dict:
    """What a task models: object points, substeps per env step and the scene's grid."""
    out = {"object_points": int(task.goal.shape[0]), "substeps": task.spec.substeps,
           "horizon": task.horizon, "action_kind": task.spec.action_kind}
    scene = task.spec.scene
    if dataclasses.is_dataclass(scene):
        for f in RESOLUTION_FIELDS:
            if hasattr(scene, f):
                v = getattr(scene, f)
                out[f"scene_{f}"] = list(v) if isinstance(v, tuple) else v
        if hasattr(scene, "dt"):
            out["sim_time_per_step_s"] = round(task.spec.substeps * scene.dt, 6)
    return out


def _timed_compile(fn, *args):
    t0 = time.perf_counter()
    compiled = fn.lower(*args).compile()
    return compiled, time.perf_counter() - t0


def bench_batch(name: str, batch: int | None, reps: int, overrides: dict) -> dict:
    task = make(name, batch_size=batch, **overrides)
    key = jax.random.PRNGKey(0)
    keys = key if batch is None else jax.random.split(key, batch)
    reset, c_reset = _timed_compile(task._reset, keys)
    t_reset, _ = _median_time(lambda: reset(keys), reps)
    _, state = reset(keys)
    if task.has_expert:
        action = task.expert_action(state)
    else:
        mid = 0.5 * (np.asarray(task.spec.action_low) + np.asarray(task.spec.action_high))
        action = jnp.broadcast_to(jnp.asarray(mid, jnp.float32), task.action_shape)
    step, c_step = _timed_compile(task._step, state, action)
    t_step, _ = _median_time(lambda: step(state, action), reps)

    def total_reward(a, s):
        return jnp.sum(task._step(s, a)[2])

    grad = jax.jit(jax.value_and_grad(total_reward))
    grad_c, c_grad = _timed_compile(grad, action, state)
    t_grad, _ = _median_time(lambda: grad_c(action, state), reps)
    g = np.asarray(grad_c(action, state)[1])
    finite = bool(np.all(np.isfinite(g)))  # a NaN gradient is reported (null norm), not hidden
    b = 1 if batch is None else batch
    return {"batch": b, "reset_s": t_reset, "step_s": t_step, "per_env_step_s": t_step / b,
            "step_grad_s": t_grad, "compile_reset_s": c_reset, "compile_step_s": c_step,
            "compile_grad_s": c_grad, "grad_finite": finite,
            "grad_norm": float(np.linalg.norm(g)) if finite else None}


def bench_task(name: str, batches, reps: int, overrides: dict | None = None) -> dict:
    overrides = overrides or {}
    task = make(name, **overrides)
    record = {"bench": "task", "task": name, **resolution(task), "batches": []}
    for b in batches:
        print(f"[dax_tasks.bench] {name} batch {b}", file=sys.stderr, flush=True)
        record["batches"].append(bench_batch(name, None if b == 1 else b, reps, overrides))
    record["peak_rss_mb"] = _peak_rss_mb()
    record["device"] = str(jax.devices()[0])
    return record


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m dax_tasks.bench", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--tasks", default="all",
                   help="comma-separated task names or 'all' (the implemented ones)")
    p.add_argument("--batch", default="1,8", help="comma-separated batch sizes")
    p.add_argument("--reps", type=int, default=3, help="timed calls per measurement")
    p.add_argument("--json", action="store_true", help="one JSON line per task")
    return p


def parse_tasks(text: str) -> list:
    if text == "all":
        return list(available())
    names = [t.strip() for t in text.split(",") if t.strip()]
    bad = [t for t in names if t not in TASKS]
    if bad:
        raise ValueError(f"unknown task(s) {bad}; valid names: {', '.join(TASKS)}")
    return names


def main(argv=None, overrides: dict | None = None) -> list:
    args = build_parser().parse_args(argv)
    try:
        names = parse_tasks(args.tasks)
        batches = [int(b) for b in args.batch.split(",")]
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        raise SystemExit(2) from None
    if any(b < 1 for b in batches) or args.reps < 1:
        print("error: batch sizes and --reps must be >= 1", file=sys.stderr)
        raise SystemExit(2)
    records = []
    for name in names:
        rec = bench_task(name, batches, args.reps, overrides)
        _emit(rec, args.json)
        records.append(rec)
    return records


if __name__ == "__main__":
    main()
