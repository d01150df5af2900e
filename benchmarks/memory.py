"""Memory of the cloth tasks' action gradients and of the learners' training runs (JSON).

Every record is measured in a fresh Python process (a child of this one), so that its peak
resident memory is its own; this process prints the records as JSON lines (and appends
them to ``--out``). Two kinds:

* ``step``: the action gradient of one env step at batch ``--batch`` (4): ``jax.grad`` of
  the summed reward of the batch, ``jax.vmap`` of ``env.step`` over the states of
  ``reset`` from ``--batch`` keys and the scripted expert's actions. ``--baseline`` adds,
  per task, the same gradient with every pair tested (``self_search="all"``) and no
  checkpointing (one segment per scan), compiled only (its memory is not allocated: XLA's
  accounting alone).
* ``train``: a learner's run (train, then evaluate: its
  :class:`dax_algos.method.LearnerRunnable` ``episode``) at the shapes of its full budget
  (``dax_algos.registry``, budget ``"full"``: environments, window, batch, evaluation
  rollouts), with the number of updates cut to one (RL and ILD: ``total_env_steps`` of one
  update; Transporter: ``--transporter-steps`` Adam steps). A run's peak memory is set by
  one update's program, not by the number of updates.

Each record: ``xla_temp_mb`` (``jax.jit(...).lower(...).compile().memory_analysis()``:
XLA's temporaries, the scratch memory of the program), ``xla_argument_output_mb``,
``peak_rss_mb`` (the child's peak resident memory after compiling and running the program
once), ``compile_s``, ``run_s`` and the 1-minute load average.

    python -m benchmarks.memory --kind step --tasks fold_cloth1,fold_tshirt --baseline
    python -m benchmarks.memory --kind train --methods ppo,apg,shac,ild,transporter \\
        --tasks fold_cloth1 --out benchmarks/results/DATE-memory.jsonl

Memory is measured here, never asserted in tests.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import subprocess
import sys
import time

CLOTH_TASKS = ("fold_cloth1", "fold_cloth3", "fold_tshirt", "unfold_cloth1", "unfold_cloth3")
LEARNERS = ("ppo", "apg", "shac", "ild", "transporter", "transporter_rgb")


def _memory(compiled) -> dict:
    mem = compiled.memory_analysis()
    if mem is None:
        return {}
    return dict(xla_temp_mb=round(mem.temp_size_in_bytes / 2**20, 1),
                xla_argument_output_mb=round(
                    (mem.argument_size_in_bytes + mem.output_size_in_bytes) / 2**20, 1))


def _compile_and_run(fn, args, run: bool = True) -> dict:
    import jax

    from benchmarks._timing import peak_rss_mb

    t0 = time.perf_counter()
    compiled = jax.jit(fn).lower(*args).compile()
    record = dict(compile_s=round(time.perf_counter() - t0, 2), **_memory(compiled))
    if run:
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(*args))
        record["run_s"] = round(time.perf_counter() - t0, 2)
    record["peak_rss_mb"] = round(peak_rss_mb(), 1)
    return record


def measure_step(task: str, batch: int = 4, resolution: str = "default",
                 baseline: bool = False) -> dict:
    """The ``step`` record of ``task`` (see the module docstring)."""
    import jax
    import jax.numpy as jnp

    import dax_tasks

    spec = dax_tasks.get_spec(task)
    overrides = {}
    if baseline:
        scene = spec.scene
        if not hasattr(scene, "segment"):
            raise ValueError(f"{task}: --baseline is for the cloth tasks")
        overrides["scene"] = dataclasses.replace(scene, self_search="all",
                                                 segment=10 * spec.substeps)
    env = dax_tasks.make(task, resolution=resolution, cache_goal=False, **overrides)
    params = env.default_params
    keys = jax.random.split(jax.random.PRNGKey(0), batch)
    _, states = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))(keys, params)
    actions = jax.jit(jax.vmap(env.expert_action, in_axes=(0, None)))(states, params)

    def loss(a, s):
        return jnp.sum(jax.vmap(lambda s, a: env.step(s, a, params)[2])(s, a))

    record = dict(kind="step", task=task, resolution=resolution, batch=batch,
                  variant="baseline" if baseline else "default",
                  substeps=env.spec.substeps, n_vertices=int(states.physics.x.shape[1]))
    record.update(_compile_and_run(jax.grad(loss), (actions, states), run=not baseline))
    return record


def _one_update(method: str, env, config):
    """The full budget's config with the number of updates cut to one."""
    from dax_algos import registry

    m = registry.get(method)
    if method.startswith("transporter"):
        return None
    if method == "ild":
        per = config.num_envs * env.horizon
    elif method == "ppo":
        per = config.num_envs * config.unroll_length
    else:
        per = config.num_envs * config.window_for(env)
    return m.config("full", env.spec.name, total_env_steps=per)


def measure_train(task: str, method: str, transporter_steps: int = 2,
                  demo_dir: str | None = None) -> dict:
    """The ``train`` record of (``method``, ``task``) (see the module docstring)."""
    import jax

    import dax_tasks
    from dax_algos import registry
    from dax_algos.il import demos

    env = dax_tasks.make(task)
    m = registry.get(method)
    full = m.config("full", task)
    config = _one_update(method, env, full)
    if config is None:
        config = m.config("full", task, train_steps=transporter_steps)
    runnable = m.build(env, config)
    data = ()
    if runnable.demos is not None:
        path = demos.locate(env, runnable.demos, demo_dir)
        data = (runnable.demos.load(env, path),)
    record = dict(kind="train", task=task, method=method,
                  full_budget={k: v for k, v in vars(full).items()
                               if isinstance(v, int | float | str | bool)},
                  cut_to=dict(total_env_steps=getattr(config, "total_env_steps", None),
                              train_steps=getattr(config, "train_steps", None)),
                  train_env_steps=runnable.train_env_steps)
    record.update(_compile_and_run(runnable.episode,
                                   (jax.random.PRNGKey(0), env.default_params, *data)))
    return record


def _child(job: dict) -> dict:
    """Run one job in a fresh process; its record (or the error it raised)."""
    cmd = [sys.executable, "-m", "benchmarks.memory", "--job", json.dumps(job)]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("{")]
    if proc.returncode == 0 and lines:
        return json.loads(lines[-1])
    return dict(job, error=(proc.stderr.strip().splitlines() or ["?"])[-1][:500],
                returncode=proc.returncode)


def _run_job(job: dict) -> dict:
    import jax

    kind = job.pop("kind")
    record = measure_step(**job) if kind == "step" else measure_train(**job)
    record.update(load_1min=round(os.getloadavg()[0], 2), backend=jax.default_backend(),
                  jax=jax.__version__)
    return record


def jobs(args) -> list[dict]:
    """The jobs of the command line, in order."""
    tasks = args.tasks.split(",")
    if args.kind == "step":
        out = []
        for task in tasks:
            for res in args.resolutions.split(","):
                out.append(dict(kind="step", task=task, batch=args.batch, resolution=res))
                if args.baseline:
                    out.append(dict(kind="step", task=task, batch=args.batch, resolution=res,
                                    baseline=True))
        return out
    extra = dict(transporter_steps=args.transporter_steps, demo_dir=args.demo_dir)
    return [dict(kind="train", task=t, method=m, **extra)
            for t in tasks for m in args.methods.split(",")]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.memory",
                                description=__doc__.split("\n\n")[0])
    p.add_argument("--kind", choices=["step", "train"], default="step")
    p.add_argument("--tasks", default=",".join(CLOTH_TASKS))
    p.add_argument("--methods", default=",".join(LEARNERS))
    p.add_argument("--resolutions", default="default", help="step: comma-separated")
    p.add_argument("--batch", type=int, default=4)
    p.add_argument("--baseline", action="store_true",
                   help="step: also all pairs without checkpointing (compiled only)")
    p.add_argument("--transporter-steps", type=int, default=2)
    p.add_argument("--demo-dir", default=None)
    p.add_argument("--out", default=None, help="append the JSON lines to this file")
    p.add_argument("--job", default=None, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.job is not None:  # in the child
        print(json.dumps(_run_job(json.loads(args.job))), flush=True)
        return 0
    failed = 0
    for job in jobs(args):
        record = _child(dict(job))
        failed += "error" in record
        line = json.dumps(record)
        print(line, flush=True)
        if args.out:
            with open(args.out, "a") as f:
                f.write(line + "\n")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
