"""Where the trained Transporter networks pick and place against the scripted expert, along
their own evaluation episodes (JSON lines).

For each saved policy ``policies/<task>/<transporter|transporter_rgb>/seed<k>.msgpack``
under ``--out`` (a ``dax-bench`` output directory), the runner's evaluation episodes of
that seed are replayed (starts ``split(fold_in(PRNGKey(k), 0), n_eval)``, the task's
default params, the network's own actions) and at every step the network's pick and place
are compared, in the table plane, with the expert's (:meth:`dax_tasks.Env.expert_action`)
on the same state:

* ``pick_err_cm`` / ``place_err_cm``: per start and step ``(n_eval, H)``, the horizontal
  distance [cm] between the network's pick (place) point and the expert's;
* ``r_gt``: per start and step, the r_gt after the network's action (the last column
  is the row's score), and ``expert_r_gt_first``: per start, after the expert's first
  action instead.

It measures the premise of the finding "Transporter on RGB above Transporter on height
maps": that the RGB picture (the object's texture: a cloth's corners, a rope's ends)
lets the network pick where the expert would, and at which step of the episode the two
networks part. Measurements only: nothing here is asserted in a test.

    python -m benchmarks.transporter_picks --out benchmarks/results/2026-11-27-paper \\
        --json benchmarks/results/2026-11-29-transporter-picks.jsonl
"""

from __future__ import annotations

import argparse
import json
import math
import sys

import jax
import numpy as np

import dax_tasks
from benchmarks.eval_trained import saved_policies
from dax_algos.actions import to_action
from dax_algos.bench import episodes, execute, trained
from dax_algos.il import transporter
from dax_tasks.io import atomic_write

METHODS = ("transporter", "transporter_rgb")


def replay_against_expert(path, env, method: str, seed: int) -> dict:
    """The record of one policy file (see the module docstring)."""
    config = trained.saved_config(path, method)
    act, policy = trained.load_trained(path, env, method, config)
    oenv = transporter.observation_env(env, config)
    params = env.default_params
    keys = episodes.learner_reset_keys(seed, config.n_eval)

    @jax.jit
    def one(key):
        obs, state = oenv.reset(key, params)
        first = oenv.step(state, oenv.expert_action(state, params), params)[4]["r_gt"]

        def body(carry, _):
            obs, state = carry
            ours = to_action(oenv, act(policy, obs))
            theirs = oenv.expert_action(state, params)
            obs, state, _, _, info = oenv.step(state, ours, params)
            return (obs, state), (ours, theirs, info["r_gt"])

        _, (ours, theirs, r_gt) = jax.lax.scan(body, (obs, state), None, length=env.horizon)
        return ours, theirs, r_gt, first

    ours, theirs, r_gt, first = jax.device_get(jax.vmap(one)(keys))
    pick = 100 * np.linalg.norm(ours[..., :2] - theirs[..., :2], axis=-1)
    place = 100 * np.linalg.norm(ours[..., 3:5] - theirs[..., 3:5], axis=-1)
    return {"task": env.spec.name, "method": method, "seed": seed, "n_starts": len(keys),
            "pick_err_cm": np.round(pick, 3).tolist(),
            "place_err_cm": np.round(place, 3).tolist(),
            "r_gt": np.round(r_gt, 5).tolist(),
            "expert_r_gt_first": np.round(first, 5).tolist()}


def _mean_se(values) -> tuple[float, float]:
    x = np.asarray(values, np.float64)
    return float(x.mean()), float(x.std(ddof=1) / math.sqrt(x.size)) if x.size > 1 else math.nan


def render_table(path) -> str:
    """Per task and method: the median pick and place error at the first step and over
    the later steps (every start of every seed), the share of picks within 2 cm of the
    expert's, the median pick error and the mean r_gt at each step (where along the
    episode the two networks part), and the r_gt after the first and the last action
    (mean ± SE over seeds)."""
    from benchmarks._report import file_date, read_result

    path, recs = read_result(path)
    groups: dict[tuple, list] = {}
    for r in recs:
        groups.setdefault((r["task"], r["method"]), []).append(r)
    out = ["| task | method | seeds | pick off the expert's [cm]: first step / later "
           "(median) | picks within 2 cm: first / later | place off [cm]: first / later | "
           "pick off [cm], per step (median) | r_gt after each step (mean) | "
           "r_gt after the first action (expert's) | score |",
           "|---|---|---|---|---|---|---|---|---|---|"]
    for (task, method), rs in sorted(groups.items()):
        pick = np.concatenate([np.asarray(r["pick_err_cm"]) for r in rs])
        place = np.concatenate([np.asarray(r["place_err_cm"]) for r in rs])
        first = _mean_se([np.mean(np.asarray(r["r_gt"])[:, 0]) for r in rs])
        score = _mean_se([np.mean(np.asarray(r["r_gt"])[:, -1]) for r in rs])
        expert = np.mean([np.mean(r["expert_r_gt_first"]) for r in rs])
        per_step = np.mean([np.mean(np.asarray(r["r_gt"]), axis=0) for r in rs], axis=0)
        out.append(f"| {task} | {method} | {len(rs)} | {np.median(pick[:, 0]):.1f} / "
                   f"{np.median(pick[:, 1:]):.1f} | {np.mean(pick[:, 0] < 2):.0%} / "
                   f"{np.mean(pick[:, 1:] < 2):.0%} | {np.median(place[:, 0]):.1f} / "
                   f"{np.median(place[:, 1:]):.1f} | "
                   + " / ".join(f"{x:.1f}" for x in np.median(pick, axis=0)) + " | "
                   + " / ".join(f"{x:.3f}" for x in per_step) + " | "
                   f"{first[0]:.3f} ± {first[1]:.3f} "
                   f"({expert:.3f}) | {score[0]:.3f} ± {score[1]:.3f} |")
    out += ["", "Each trained policy of the grid replayed on its own evaluation episodes (20 "
            "starts per seed, its own actions), its pick and place at every step against "
            "what the scripted expert would do in the same state; distances in the table "
            "plane; r_gt mean ± SE over seeds; score: the replay's final-step r_gt (its "
            "program is not the runner's, and another program's round-off can flip an "
            "argmax pick, so it may differ a little from the rows). "
            f"`{path.as_posix()}` ({file_date(path) or 'date not recorded'})."]
    return "\n".join(out) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.transporter_picks",
                                description=__doc__.split("\n\n")[0])
    p.add_argument("--out", required=True, help="the dax-bench output directory")
    p.add_argument("--tasks", default=None, help="comma-separated (default: every task)")
    p.add_argument("--json", required=True, help="JSON lines file (rewritten)")
    args = p.parse_args(argv)
    execute.use_default_compilation_cache()
    tasks = set(args.tasks.split(",")) if args.tasks else None
    recs = []
    for path, task, method, seed in saved_policies(args.out, tasks, set(METHODS)):
        rec = replay_against_expert(path, dax_tasks.make(task), method, seed)
        print(json.dumps({k: rec[k] for k in ("task", "method", "seed")}
                         | {"score": float(np.mean(np.asarray(rec["r_gt"])[:, -1]))}),
              file=sys.stderr, flush=True)
        recs.append(rec)
        jax.clear_caches()
    atomic_write(args.json, "".join(json.dumps(r) + "\n" for r in recs))
    print(render_table(args.json))
    return 0


if __name__ == "__main__":
    sys.exit(main())
