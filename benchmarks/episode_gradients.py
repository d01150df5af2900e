"""Gradients over a whole expert episode, for every task: finite, and not all zero.

Per task and seed: the scripted expert plays one episode of the task's horizon (closed
loop, forward only), then the gradient of the episode's summed reward with respect to the
whole action sequence is taken through every env step (reverse mode, the substeps inside
each step checkpointed as the tasks do). The record says whether every entry is finite,
its norm, the share of non-zero entries, and whether the forward pass stayed finite.
This is the issue-16 check "gradients finite over an episode", too slow for the test
suite (cloth episodes with self-collision), so it is a script with JSON output:

    python -m benchmarks.episode_gradients --tasks all --seeds 0,1 --out DIR/grads.jsonl
"""

from __future__ import annotations

import argparse
import json
import sys
import time


def episode_gradient(name: str, seed: int) -> dict:
    import jax
    import jax.numpy as jnp
    import numpy as np

    import dax_tasks

    env = dax_tasks.make(name)
    t0 = time.perf_counter()
    _, state0 = env.reset(jax.random.PRNGKey(seed))
    H = env.spec.horizon

    def play(state, _):
        a = env.expert_action(state)
        _, state, _, _, info = env.step(state, a)
        return state, a

    _, actions = jax.jit(lambda s: jax.lax.scan(play, s, None, length=H))(state0)

    def episode_return(acts):
        def body(s, a):
            _, s, r, _, info = env.step(s, a)
            return s, (r, info["r_gt"], info["finite"])
        _, (r, r_gt, finite) = jax.lax.scan(body, state0, acts)
        return jnp.sum(r), (r_gt[-1], jnp.all(finite))

    (ret, (final_r_gt, fwd_finite)), g = jax.jit(
        jax.value_and_grad(episode_return, has_aux=True))(actions)
    g = np.asarray(g, np.float64)
    finite = bool(np.all(np.isfinite(g)))
    return dict(task=name, seed=seed, horizon=H, action_dim=env.spec.action_dim,
                return_=float(ret), final_r_gt=float(final_r_gt),
                forward_finite=bool(fwd_finite), grad_finite=finite,
                grad_norm=float(np.linalg.norm(g)) if finite else None,
                nonzero_share=float(np.mean(g != 0)) if finite else None,
                per_step_grad_norm=[float(v) for v in np.linalg.norm(g, axis=1)]
                if finite else None,
                seconds=round(time.perf_counter() - t0, 1), jax=jax.__version__)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--tasks", default="all")
    p.add_argument("--seeds", default="0")
    p.add_argument("--out", help="also append the JSON lines here")
    args = p.parse_args(argv)
    import dax_tasks

    names = dax_tasks.TASKS if args.tasks == "all" else args.tasks.split(",")
    bad = 0
    for name in names:
        for seed in (int(s) for s in args.seeds.split(",")):
            rec = episode_gradient(name, seed)
            bad += not (rec["grad_finite"] and rec["forward_finite"])
            line = json.dumps(rec)
            print(line, flush=True)
            if args.out:
                with open(args.out, "a") as f:
                    f.write(line + "\n")
    print(f"{bad} episode(s) with a non-finite gradient or state", file=sys.stderr)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
