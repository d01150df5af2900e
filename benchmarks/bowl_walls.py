"""Does the water stay out of the bowls' walls? (issue 35, item 5)

Runs the scripted expert's episodes of Pour-Water and Pour-Soup (``--batch`` random starts
from ``--seed``, the whole horizon unless ``--steps``) and reports, after every env step and
for each bowl (source, target), how many particles sit more than ``dx/2`` inside the
bowl's solid (signed distance below ``-dx/2``) and the deepest one [m]. One JSON document:
per task, the worst step over the batch, the first step with a particle beyond the limit,
and the per-step series (``--series``).

    python -m benchmarks.bowl_walls                       # both tasks, batch 8, seed 0
    python -m benchmarks.bowl_walls --tasks pour_water --batch 2 --steps 40
    python -m benchmarks.bowl_walls --out benchmarks/results/DATE-bowl-walls.json
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import time

import jax
import jax.numpy as jnp
import numpy as np

import dax_tasks
from benchmarks._report import write_report
from dax_physics import colliders as col
from dax_tasks.tasks import pour

BOWLS = ("source", "target")


def wall_depths(env, physics):
    """Per bowl, each particle's depth inside its solid [m] (positive inside, 0 outside):
    (2, N)."""
    cfg = env.cfg
    out = []
    for k in (pour.SOURCE, pour.TARGET):
        phi, _ = col.sdf(cfg.colliders[k], physics.colliders.pos[k], physics.colliders.quat[k],
                         physics.x)
        out.append(jnp.maximum(-phi, 0.0))
    return jnp.stack(out)


def run_episodes(env, batch: int, seed: int, steps: int):
    """``(depth_max, count, r_gt)``: (steps, batch, 2) the deepest particle per bowl [m]
    and the number beyond ``dx/2``, and (steps, batch) the reward, after each env step of
    the expert's episodes."""
    venv = dax_tasks.VmapWrapper(env, batch_size=batch)
    params = venv.default_params
    limit = 0.5 * env.cfg.dx

    def body(state, _):
        action = venv.expert_action(state, params)
        _, state, _, _, info = venv.step(state, action, params)
        d = jax.vmap(lambda p: wall_depths(env, p))(state.physics)  # (B, 2, N)
        return state, (jnp.max(d, axis=-1), jnp.sum(d > limit, axis=-1), info["r_gt"])

    @jax.jit
    def episode(key):
        _, state = venv.reset(key, params)
        return jax.lax.scan(body, state, None, length=steps)[1]

    out = jax.block_until_ready(episode(jax.random.PRNGKey(seed)))
    return tuple(np.asarray(a) for a in out)


def summarise(env, depth, count, r_gt, series: bool) -> dict:
    limit = 0.5 * env.cfg.dx
    rec = {"task": env.spec.name, "dx": env.cfg.dx, "limit_m": limit,
           "particles": int(env.n_object_points), "steps": int(depth.shape[0]),
           "batch": int(depth.shape[1]), "project": bool(env.spec.scene.project),
           "final_r_gt_mean": float(r_gt[-1].mean()), "final_r_gt_min": float(r_gt[-1].min())}
    for b, name in enumerate(BOWLS):
        over = count[:, :, b].max(axis=1)
        beyond = np.flatnonzero(over > 0)
        rec[name] = {"max_depth_m": float(depth[:, :, b].max()),
                     "max_count": int(over.max()),
                     "first_step_beyond": int(beyond[0]) + 1 if beyond.size else None,
                     "steps_beyond": int(beyond.size)}
        if series:
            rec[name]["depth_per_step_m"] = [round(float(v), 6)
                                             for v in depth[:, :, b].max(axis=1)]
            rec[name]["count_per_step"] = [int(v) for v in over]
    rec["holds"] = all(rec[n]["max_count"] == 0 for n in BOWLS)
    return rec


def speed(name: str, batch: int, rounds: int, resolution: str = "default",
          clock=time.perf_counter) -> dict:
    """One env step of ``name`` (the expert's first action, ``batch`` envs; 1: unbatched)
    forward and with the action gradient, with and without the bowls' particle projection,
    timed in alternation: ``rounds`` rounds, each one call of every variant (medians [s]),
    the 1-minute load average before and after. ``clock``: as in
    :func:`benchmarks._timing.median_time`."""
    from benchmarks._timing import median_time, timed_compile

    load0 = os.getloadavg()[0]
    calls = {}
    for project in (False, True):
        env = dax_tasks.make(name, resolution=resolution)
        env = dax_tasks.make(name, resolution=resolution,
                             scene=dataclasses.replace(env.spec.scene, project=project))
        if batch > 1:
            env = dax_tasks.VmapWrapper(env, batch_size=batch)
        params = env.default_params
        state = jax.jit(env.reset)(jax.random.PRNGKey(0), params)[1]
        action = jax.jit(env.expert_action)(state, params)

        def loss(a, s, p, env=env):
            return jnp.sum(env.step(s, a, p)[2])

        fwd, _ = timed_compile(jax.jit(env.step), state, action, params)
        grad, _ = timed_compile(jax.jit(jax.grad(loss)), action, state, params)
        calls[f"step_project_{project}"] = (fwd, (state, action, params))
        calls[f"grad_project_{project}"] = (grad, (action, state, params))
    times = {k: [] for k in calls}
    for _ in range(rounds):
        for k, (f, args) in calls.items():
            times[k].append(median_time(lambda f=f, args=args: f(*args), 1,
                                        clock=clock)[0])
    med = {k: float(np.median(v)) for k, v in times.items()}
    return {"task": name, "batch": batch, "rounds": rounds, "median_s": med,
            "step_ratio": med["step_project_True"] / med["step_project_False"],
            "grad_ratio": med["grad_project_True"] / med["grad_project_False"],
            "clock": "process" if clock is time.process_time else "wall",
            "load_1min": [load0, os.getloadavg()[0]]}


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m benchmarks.bowl_walls", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--tasks", default="pour_water,pour_soup")
    p.add_argument("--batch", type=int, default=8)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--steps", type=int, default=None, help="env steps (default: horizon)")
    p.add_argument("--resolution", default="default")
    p.add_argument("--no-project", action="store_true",
                   help="the bowls without the particle projection (PourScene.project "
                        "False): the grid condition alone")
    p.add_argument("--speed", type=int, default=0, metavar="ROUNDS",
                   help="instead: time one env step with and without the projection, "
                        "interleaved, ROUNDS rounds")
    p.add_argument("--clock", choices=("wall", "process"), default="wall",
                   help="--speed's clock: wall time, or the process's CPU time (steadier on "
                        "a shared machine; pin the process to one core with taskset)")
    p.add_argument("--series", action="store_true", help="per-step series in the output")
    p.add_argument("--out", default=None, help="write the JSON document here too")
    return p


def main(argv=None) -> dict:
    args = build_parser().parse_args(argv)
    doc = {"bench": "bowl_walls", "batch": args.batch, "seed": args.seed,
           "resolution": args.resolution, "load_1min": os.getloadavg()[0], "tasks": []}
    names = [t.strip() for t in args.tasks.split(",") if t.strip()]
    clock = time.process_time if args.clock == "process" else time.perf_counter
    if args.speed:
        doc = {"bench": "bowl_walls_speed", "tasks": [
            speed(n, b, args.speed, args.resolution, clock)
            for n in names for b in sorted({1, args.batch})]}
        write_report(doc, args.out)
        return doc
    for name in names:
        env = dax_tasks.make(name, resolution=args.resolution)
        if args.no_project:
            env = dax_tasks.make(name, resolution=args.resolution, scene=dataclasses.replace(
                env.spec.scene, project=False))
        steps = args.steps or env.horizon
        t0 = time.perf_counter()
        depth, count, r_gt = run_episodes(env, args.batch, args.seed, steps)
        rec = summarise(env, depth, count, r_gt, args.series)
        rec["wall_s"] = time.perf_counter() - t0
        doc["tasks"].append(rec)
    doc["holds"] = all(r["holds"] for r in doc["tasks"])
    write_report(doc, args.out)
    return doc


if __name__ == "__main__":
    main()
