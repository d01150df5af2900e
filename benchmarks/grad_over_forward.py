"""Gradient time over forward time on the solver benchmarks (issue target: at most 3x).

Workloads, each the forward rollout of a scalar loss and its gradient wrt the initial
velocities, both compiled ahead of time and called alternately ``--reps`` times in one
process (so that their ratio sees one machine state):

- ``cloth``: the 64 x 64 cloth-drop scene of the side-by-side benchmark, 1000 substeps of
  1e-4 s; loss: mean height.
- ``fluid-s1`` / ``elastic-s1``: the 8192-particle block drop on a 32^3 grid, 100
  substeps, no checkpointing; loss: mean height. ``fluid-s10`` / ``elastic-s10``: the same
  in 10 checkpointed segments of 10 substeps (the memory-saving setting, which recomputes
  each segment once more).

Each workload runs in a subprocess of its own, in ``--rounds`` rounds. With
``--baseline-src`` (the ``src`` directories of another checkout's packages, joined with
``:``), every run is paired with the same run on that code, alternately, so that a slow
phase of a shared machine hits both. One JSON document to stdout and to ``--out``.

    python -m benchmarks.grad_over_forward --rounds 3 \\
        --out benchmarks/results/DATE-grad-over-forward.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time

from benchmarks._report import write_report

WORKLOADS = {
    "cloth": {},
    "fluid-s1": {"material": "fluid", "segments": 1},
    "elastic-s1": {"material": "elastic", "segments": 1},
    "fluid-s10": {"material": "fluid", "segments": 10},
    "elastic-s10": {"material": "elastic", "segments": 10},
}


def workload(name: str):
    """``(loss, arg)`` of a workload: a scalar loss of the initial velocities ``arg``."""
    import jax.numpy as jnp

    if name == "cloth":
        from dax_physics import cloth as c

        if not hasattr(c, "grid_rollout"):  # a checkout after the grid cloth left the library
            from benchmarks import cloth_grid as c
        cfg, cloth, state = c.cloth_drop_scene(64, dt=1e-4)

        def loss(v0):
            out = c.grid_rollout(cfg, cloth, c.GridState(state.x, v0), 1000)
            return jnp.mean(out.x[2])
    else:
        from benchmarks.physics import block_drop_scene
        from dax_physics import mpm

        spec = WORKLOADS[name]
        cfg, state = block_drop_scene(spec["material"], 32, 8192)
        seg = None if spec["segments"] <= 1 else 100 // spec["segments"]

        def loss(v0):
            out = mpm.rollout(cfg, cfg.params, state.replace(v=v0), 100, segment=seg)
            return jnp.mean(out.x[:, 2])
    return loss, state.v


def _worker(name: str, reps: int) -> dict:
    import jax
    import jax.numpy as jnp
    import numpy as np

    loss, arg = workload(name)
    # timed here, not with benchmarks._timing.grad_vs_forward, so that a baseline
    # checkout that predates that helper runs exactly the same measurement
    grad = jax.jit(jax.grad(loss)).lower(arg).compile()
    fwd = jax.jit(loss).lower(arg).compile()
    g = jax.block_until_ready(grad(arg))
    jax.block_until_ready(fwd(arg))
    tf, tg = [], []
    for _ in range(reps):
        t0 = time.perf_counter()
        jax.block_until_ready(fwd(arg))
        tf.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        jax.block_until_ready(grad(arg))
        tg.append(time.perf_counter() - t0)
    f, gr = float(np.median(tf)), float(np.median(tg))
    mem = grad.memory_analysis()
    return dict(workload=name, forward_s=f, grad_s=gr, grad_over_forward=gr / f,
                xla_temp_mb=None if mem is None else mem.temp_size_in_bytes / 2 ** 20,
                grad_norm=float(jnp.linalg.norm(g)), finite=bool(jnp.all(jnp.isfinite(g))))


def _run(name: str, reps: int, src: str | None) -> dict:
    env = dict(os.environ)
    if src:
        env["PYTHONPATH"] = src
    out = subprocess.run([sys.executable, __file__, "--worker", name, "--reps", str(reps)],
                         env=env, capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--workloads", default=",".join(WORKLOADS))
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--reps", type=int, default=5)
    p.add_argument("--baseline-src", default=None,
                   help="PYTHONPATH of the code to compare with (its packages' src dirs)")
    p.add_argument("--out", default=None)
    p.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.worker:
        print(json.dumps(_worker(args.worker, args.reps)), flush=True)
        return
    names = args.workloads.split(",")
    for n in names:
        if n not in WORKLOADS:
            raise SystemExit(f"unknown workload {n!r}; known: {', '.join(WORKLOADS)}")
    sides = ["current"] + (["baseline"] if args.baseline_src else [])
    runs = []
    for r in range(args.rounds):
        for n in names:
            for side in sides:
                rec = _run(n, args.reps, args.baseline_src if side == "baseline" else None)
                rec.update(round=r, side=side, load_1min=os.getloadavg()[0])
                runs.append(rec)
                print(json.dumps(rec), file=sys.stderr, flush=True)
    summary = {}
    for n in names:
        for side in sides:
            mine = [x for x in runs if x["workload"] == n and x["side"] == side]
            ratios = sorted(x["grad_over_forward"] for x in mine)
            summary[f"{n}/{side}"] = dict(
                grad_over_forward_median=ratios[len(ratios) // 2],
                grad_over_forward_range=[ratios[0], ratios[-1]],
                grad_s_median=sorted(x["grad_s"] for x in mine)[len(mine) // 2],
                forward_s_median=sorted(x["forward_s"] for x in mine)[len(mine) // 2],
                xla_temp_mb=mine[0]["xla_temp_mb"])
    doc = dict(bench="grad-over-forward", rounds=args.rounds, reps=args.reps,
               baseline_src=bool(args.baseline_src), machine=platform.machine(),
               cpus=os.cpu_count(), python=platform.python_version(), summary=summary,
               runs=runs)
    write_report(doc, args.out)


if __name__ == "__main__":
    main()
