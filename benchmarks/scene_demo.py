"""Sample pictures of the oblique scene renderer (:mod:`dax_tasks.viz.scene`) for a person to
look at: for each task, the scripted expert's episode from seed 0, rendered as one PNG of
its last frame, a filmstrip (key frames beside the goal) and a looping GIF; the render
time per frame and the files' sizes are printed (one JSON line per task on stdout).

    python -m benchmarks.scene_demo --out /tmp/scenes
    python -m benchmarks.scene_demo --out /tmp/scenes --tasks fold_cloth1 --res 480 360

Expert episodes of the MPM tasks cost minutes on a CPU at full horizon: ``--steps N``
stops an episode after N steps (the default, the whole horizon).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import jax

from dax_tasks import make
from dax_tasks.viz import (
    SceneView,
    filmstrip,
    goal_frame,
    save_animation,
    save_png,
    scene_frames,
)

DEMO_TASKS = ("fold_cloth1", "fold_tshirt", "push_rope", "pour_water")


def expert_states(env, steps: int | None = None, seed: int = 0):
    """The states (stacked, leading time axis: the start and one per step) of the scripted
    expert's episode from ``seed``, ``steps`` steps (default the horizon)."""
    params = env.default_params
    steps = env.horizon if steps is None else min(steps, env.horizon)

    def body(state, _):
        _, nxt, _, _, _ = env.step(state, env.expert_action(state, params), params)
        return nxt, nxt

    @jax.jit
    def run(key):
        _, s0 = env.reset(key, params)
        _, rest = jax.lax.scan(body, s0, None, length=steps)
        return jax.tree_util.tree_map(lambda a, b: jax.numpy.concatenate([a[None], b]),
                                      s0, rest)

    return run(jax.random.PRNGKey(seed))


def demo(task: str, out: Path, res=(320, 240), steps: int | None = None,
         fps: float = 8.0, max_frames: int | None = 40) -> dict:
    """Render ``task``'s expert episode into ``out``; returns what was written and timed."""
    env = make(task)
    t0 = time.perf_counter()
    states = jax.block_until_ready(expert_states(env, steps))
    sim_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    view = SceneView.for_env(env)
    view_s = time.perf_counter() - t0
    scene_frames(env, jax.tree_util.tree_map(lambda a: a[:1], states), view=view, res=res)
    t0 = time.perf_counter()
    frames = scene_frames(env, states, view=view, res=res)
    render_s = time.perf_counter() - t0
    s0 = jax.tree_util.tree_map(lambda a: a[0], states)
    goal = goal_frame(env, s0, view, res)
    out.mkdir(parents=True, exist_ok=True)
    files = {
        "first": save_png(frames[0], out / f"{task}_first.png"),
        "last": save_png(frames[-1], out / f"{task}_last.png"),
        "goal": save_png(goal, out / f"{task}_goal.png"),
        "filmstrip": save_png(filmstrip(frames, 5, goal), out / f"{task}_filmstrip.png"),
        "gif": save_animation(frames, out / f"{task}.gif", fps=fps, max_frames=max_frames),
    }
    return {"task": task, "frames": len(frames), "res": list(res),
            "object_points": int(env.n_object_points), "episode_s": round(sim_s, 2),
            "view_s": round(view_s, 3), "render_s": round(render_s, 3),
            "render_ms_per_frame": round(1e3 * render_s / len(frames), 2),
            "bytes": {k: Path(v).stat().st_size for k, v in files.items()},
            "files": {k: str(v) for k, v in files.items()}}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True, type=Path, help="directory for the pictures")
    ap.add_argument("--tasks", default=",".join(DEMO_TASKS),
                    help=f"comma-separated task names (default {','.join(DEMO_TASKS)})")
    ap.add_argument("--res", type=int, nargs=2, default=(320, 240), metavar=("W", "H"))
    ap.add_argument("--steps", type=int, default=None,
                    help="env steps per episode (default: the task's horizon)")
    ap.add_argument("--max-frames", type=int, default=40, help="frames kept in the GIF")
    args = ap.parse_args(argv)
    for task in [t for t in args.tasks.split(",") if t]:
        row = demo(task, args.out, tuple(args.res), args.steps, max_frames=args.max_frames)
        print(json.dumps(row), flush=True)
        print(f"{task}: {row['frames']} frames, {row['render_ms_per_frame']} ms/frame, "
              f"gif {row['bytes']['gif'] / 1024:.0f} KiB", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())

