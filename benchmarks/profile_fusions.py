"""Where a solver benchmark's time goes on XLA:CPU: the time of each compiled op (a fused
loop, a scatter, a copy), from JAX's own profiler, joined with the op's shape and the JAX
operation it came from.

The workloads are those of ``grad_over_forward.py`` (``cloth``, ``fluid-s1``, ...), run as
the forward (``--mode fwd``) or its gradient (``--mode grad``): compiled ahead of time,
warmed up, then ``--calls`` calls traced with ``jax.profiler.trace``. Each op's time is
summed over the XLA:CPU worker threads that ran it (so ``op_ms_per_call`` can exceed the
wall time when two threads share a loop). Ops are sorted into:

- ``forward``: the forward computation (in a gradient: the forward pass that keeps the
  residuals, their stores included);
- ``reverse``: the transposed (backward) computation;
- ``recomputed``: forward values the backward pass recomputes (``jax.checkpoint``);
- ``residual_init``: the zero-fill of the scan's residual stacks, once per call;
- ``other``: copies and loop bookkeeping with no JAX operation recorded.

``--workload task:NAME[@RESOLUTION]`` profiles one env step of a task instead (its summed
reward as a function of the action). ``--workload train:METHOD:TASK`` profiles a learner's
whole jitted ``train`` for one update (its full-budget config with ``total_env_steps`` one
update's worth and one evaluation episode, as :mod:`benchmarks.rl_speed` builds it; it
contains its own gradient, so ``--mode`` must be ``fwd``). Each op's time is also summed per
MPM substep stage (``by_stage``: the ``jax.named_scope`` of ``dax_physics.mpm.substep``'s
stages, crossed with the categories above; ``other`` outside the stages).

One JSON document to stdout and to ``--out``:

    python -m benchmarks.profile_fusions --workload fluid-s1 --mode grad --top 25
    python -m benchmarks.profile_fusions --workload task:whip_rope@reference --mode fwd
    python -m benchmarks.profile_fusions --workload train:apg:unfold_cloth3 --mode fwd --top 10
"""

from __future__ import annotations

import argparse
import collections
import glob
import re
import statistics
import tempfile
import time

from benchmarks._report import write_report
from benchmarks.grad_over_forward import WORKLOADS, workload

#: ``  %name = shape opcode(...), ... op_name="..."`` of an instruction in the HLO text
_INSTRUCTION = re.compile(r'^\s*(?:ROOT )?%(\S+) = (\S+) [\w-]+\(.*?op_name="([^"]*)"', re.M)


def _category(op: str, op_name: str) -> str:
    if "rematted_computation" in op_name:
        return "recomputed"
    if "transpose(" in op_name:
        return "reverse"
    if "/while" not in op_name and (op.startswith("wrapped_broadcast")
                                     or op_name.endswith("broadcast_in_dim")):
        return "residual_init"  # a broadcast outside the loops: a stack's zero-fill
    return "forward"


#: The MPM substep's named stages (``dax_physics.mpm.substep``), in order; an op whose JAX
#: operation sits under one of these scopes is counted to it.
STAGES = ("stencil", "p2g", "grid_update", "boundaries", "g2p", "deformation", "held",
          "project", "stability")


def _stage(op_name: str) -> str:
    """The substep stage an op's JAX operation name lies under (the innermost scope that is
    a stage name), or ``"other"``."""
    found = "other"
    for part in re.split(r"[/()]", op_name):
        if part in STAGES:
            found = part
    return found


def task_workload(spec: str):
    """``(loss, arg)`` of one env step of a task, ``spec`` = ``task:NAME[@RESOLUTION]``: the
    summed reward as a function of the action (the scripted expert's first action, else
    the middle of the action box), from the start of key 0."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    import dax_tasks

    name, _, res = spec.split(":", 1)[1].partition("@")
    env = dax_tasks.make(name, resolution=res or "default")
    params = env.default_params
    state = jax.jit(env.reset)(jax.random.PRNGKey(0), params)[1]
    if env.has_expert:
        action = jax.jit(env.expert_action)(state, params)
    else:
        action = jnp.asarray(0.5 * (np.asarray(env.spec.action_low)
                                    + np.asarray(env.spec.action_high)), jnp.float32)

    def loss(a):
        return jnp.sum(env.step(state, a, params)[2])

    return loss, action


def train_workload(spec: str):
    """``(train, key)`` of ``spec`` = ``train:METHOD:TASK``: the method's ``train`` for one
    update (see the module docstring), as a function of its ``PRNGKey``."""
    import jax

    import dax_tasks
    from benchmarks.rl_speed import RL_METHODS, config_for_updates
    from dax_algos import registry

    _, method, task = spec.split(":")
    if method not in RL_METHODS:
        raise ValueError(f"train workloads take one of {', '.join(RL_METHODS)}, got "
                         f"{method!r}")
    env = dax_tasks.make(task)
    config, _ = config_for_updates(method, task, env, 1, n_eval=1)
    train = registry.get(method).learner.make_train(env, config)
    params = env.default_params
    return (lambda key: train(key, params)), jax.random.PRNGKey(0)


def _workload(name: str):
    if name.startswith("task:"):
        return task_workload(name)
    if name.startswith("train:"):
        return train_workload(name)
    return workload(name)


def profile(name: str, mode: str, calls: int, top: int) -> dict:
    import jax

    loss, arg = _workload(name)
    fn = jax.jit(jax.grad(loss) if mode == "grad" else loss).lower(arg).compile()
    ops = {m.group(1): (m.group(2), m.group(3)) for m in _INSTRUCTION.finditer(fn.as_text())}
    for _ in range(2):
        jax.block_until_ready(fn(arg))
    walls = []
    with tempfile.TemporaryDirectory() as tmp:
        with jax.profiler.trace(tmp):
            for _ in range(calls):
                t0 = time.perf_counter()
                jax.block_until_ready(fn(arg))
                walls.append(time.perf_counter() - t0)
        trace = jax.profiler.ProfileData.from_file(
            glob.glob(f"{tmp}/**/*.xplane.pb", recursive=True)[0])
        total, count = collections.Counter(), collections.Counter()
        for plane in trace.planes:
            for line in plane.lines:
                for ev in line.events:
                    if ev.name in ops or re.fullmatch(r"copy(\.\d+)?|while(\.\d+)?", ev.name):
                        total[ev.name] += ev.duration_ns
                        count[ev.name] += 1
    by_category, by_stage = collections.Counter(), collections.Counter()
    rows = []
    for op, ns in total.most_common():
        shape, op_name = ops.get(op, ("", ""))
        cat = _category(op, op_name) if op_name else "other"
        ms = ns / 1e6 / calls
        by_category[cat] += ms
        by_stage[f"{_stage(op_name)}/{cat}" if op_name else "other"] += ms
        if len(rows) < top:
            rows.append(dict(op=op, ms_per_call=round(ms, 3), runs_per_call=count[op] / calls,
                             shape=shape, category=cat, jax_op=op_name))
    return dict(bench="profile-fusions", workload=name, mode=mode, calls=calls,
                wall_ms_per_call=1e3 * statistics.median(walls),
                op_ms_per_call=round(sum(by_category.values()), 2),
                by_category={k: round(v, 2) for k, v in by_category.most_common()},
                by_stage={k: round(v, 2) for k, v in by_stage.most_common()},
                top=rows)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--workload", default="fluid-s1",
                   help=f"one of {', '.join(WORKLOADS)}, task:NAME[@RESOLUTION] (one env "
                        "step of a task, e.g. task:whip_rope@reference), or "
                        "train:METHOD:TASK (one update of an RL method's train, --mode fwd)")
    p.add_argument("--mode", default="grad", choices=["fwd", "grad"])
    p.add_argument("--calls", type=int, default=3)
    p.add_argument("--top", type=int, default=25)
    p.add_argument("--out", default=None)
    args = p.parse_args(argv)
    if args.workload not in WORKLOADS and not args.workload.startswith(("task:", "train:")):
        p.error(f"unknown workload {args.workload!r}")
    if args.workload.startswith("train:"):
        if args.workload.count(":") != 2:
            p.error(f"a train workload is train:METHOD:TASK, got {args.workload!r}")
        if args.mode != "fwd":
            p.error("a train workload holds its own gradient: profile it with --mode fwd")
    write_report(profile(args.workload, args.mode, args.calls, args.top), args.out)


if __name__ == "__main__":
    main()
