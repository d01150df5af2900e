"""Ablations of the learners: one method on one task, one config change at a time, the same
budget, seeds, evaluation starts and demonstrations for every variant (JSON lines and a
chart).

Each variant is the method's registry budget (``--budget``) with the variant's config
fields changed (:data:`VARIANTS`, each named after the hypothesis it tests; ``--set``
changes a field in every variant, the baseline included; every learner also has
``to_read``, the budget run until each env has ended 10 episodes, computed per task by
:func:`to_read_variant`, and ``x3`` and ``half``, the budget run three times or half as
long, to read a curve the budget table calls rising or falling). Per (variant, seed) one record:

* ``score``: the trained policy's evaluation, the mean final-step r_gt of ``n_eval``
  rollouts from the runner's evaluation starts for that seed, and ``rollouts`` each one;
* ``untrained``: the same rollouts of the policy before training (the network's
  initial parameters from the seed's key, the normaliser's initial statistics);
* ``curve``: per training update, the training episodes' mean final-step r_gt (the first
  point is the untrained policy's where an update is one whole episode) and
  ``return_curve`` their mean return (the training reward the method maximises);
  ``grad_norm``: per update, the raw (unclipped) global norm of the policy gradient;
* ``wall_s`` (training and evaluation of the seed, compiled), ``compile_s``,
  ``env_steps`` and ``env_steps_per_s`` (training env steps over ``wall_s``), the 1-minute
  load average before the seed, and ``provenance``: what the runner's rows record of the
  code, task and config (:func:`dax_algos.bench.provenance.of_run`).

Summary lines (``"summary": true``), per variant: mean ± SE over seeds of the score and
of the untrained score, and the paired difference from the baseline (same seeds) with its
SE: a change is kept only where it is better than the baseline by more than 2 SE.
Records are appended as each seed finishes; a rerun with the same ``--out`` skips the
(variant, seed) pairs already there, so a long ablation runs in chunks
(``--max-minutes``), or in pieces (``--seeds 3-4`` beside ``--seeds 3``, each into its own
``--out``; ``--join PIECE`` then adds a piece's seed records to ``--out``).

    python -m benchmarks.ablate apg fold_cloth1 --variants baseline,raw_obs --seeds 3 \\
        --out benchmarks/results/2026-11-27-ablate-apg-fold_cloth1.jsonl

writes the JSON lines to ``--out`` and the chart beside it (``.png``). With
``--baseline-from GRID_DIR`` the baseline's seeds are the benchmark grid's rows of the same
budget, config and task code, run on this machine class (:func:`grid_baseline`), instead of
being trained again.
Speed and scores are measured here, never asserted in tests.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

import jax
import numpy as np

import dax_tasks
from benchmarks._report import read_records
from benchmarks.rl_speed import parse_sets
from dax_algos import registry
from dax_algos.bench import execute, grid, learning, provenance, report, rundir
from dax_algos.bench import rows as rows_mod
from dax_algos.learner import untrained_key
from dax_algos.method import BUDGETS
from dax_tasks.io import atomic_write

#: PPO's batch of 64 whole Whip-Rope episodes per update (64 envs x 50 steps), 5 updates:
#: ``big_batch`` and the variants built on it.
_PPO_WHOLE_EPISODES_64 = {"num_envs": 64, "unroll_length": 50, "total_env_steps": 16000}

#: Per method: variant name -> config fields changed from the budget's. Names say the
#: hypothesis (issue 36): the normaliser inside the differentiated rollout (``raw_obs``),
#: Adam after the gradient clip (``no_clip``, ``lr_low``), the training objective against
#: the score (``final_reward``, ``no_aux``), SHAC's window (``window1``), ILD's targets
#: from random starts (``aligned``, ``goal_aligned``), Transporter's goal picture of the
#: unaligned goal (``aligned_goal``, ``no_goal``) and its augmentation against starts at any heading
#: (``rotate_any``), an MLP policy that sees a cloth at any place and heading in table
#: coordinates (``object_frame``: :class:`dax_tasks.ObjectFrame`), a PPO budget in which
#: no training episode reaches its end (``whole_episodes``), and with a discount that sees
#: the end of an MPM episode (``whole_episodes_d99``).
VARIANTS = {
    "apg": {"baseline": {}, "raw_obs": {"normalize_obs": False},
            "object_frame": {"frame": "object"},
            "no_clip": {"max_grad_norm": None}, "lr_low": {"learning_rate": 1e-4},
            "final_reward": {"objective": "final"}, "no_aux": {"aux_weight": 0.0},
            # a curve that peaks and falls (the budget table's verdict on Fold-Cloth-1)
            "lr_linear": {"lr_schedule": "linear"},
            # a batch whose gradient has a direction (benchmarks.gradient_noise): the same
            # 40 updates with 8x the episodes
            "big_batch": {"num_envs": 32, "total_env_steps": 3840},
            # a budget read off the curve: Whip-Rope's heavy budget (7 updates of 4 x 10
            # steps) ends where its curve is still "too short" to read; 5x the updates
            "long": {"total_env_steps": 1400},
            # and twice that: on Pour-Water (100-step episodes) `long` is 3.5 training
            # episodes per env whose final scores still rise from one to the next
            "longer": {"total_env_steps": 2800},
            # Whip-Rope: the fewest updates whose curve splits in fifths (benchmarks.budgets:
            # 10 updates that end an episode; 4 envs x 10 steps end one per env every 5)
            "longest": {"total_env_steps": 2000},
            # Push-Rope: the first gradient of 4 episodes has SNR 0.5 (benchmarks.
            # gradient_noise: about 96 samples for SNR 1), so 16 episodes per update, on
            # the final-step objective that measured better there; the same 7 updates
            "big_batch_final": {"num_envs": 16, "total_env_steps": 1120, "objective": "final"},
            # Unfold-Cloth-3: the object frame at the budget splits the seeds (three well
            # above their untrained policy, two below); 4x its updates, as PPO's budget
            # there took
            "object_frame_long": {"frame": "object", "total_env_steps": 1920},
            # the raw cloth gradient norms span orders of magnitude between updates: a
            # batch gradient led by one env's step through contact; each env's action
            # gradient clipped to the batch's median norm at every step
            "median_clip": {"action_grad": "median_clip"},
            # SHAC, above its untrained policy on Fold-T-shirt and Unfold-Cloth-1 where APG
            # is not, trains a stochastic policy (pre-tanh std 0.37 at its initial log-std
            # -1): the same exploration noise on APG's training actions, a Gaussian
            # smoothing of a return that is rough in the picks
            "noise": {"action_noise": 0.37}},
    "shac": {"baseline": {}, "raw_obs": {"normalize_obs": False}, "window1": {"window": 1},
             "object_frame": {"frame": "object"},
             "no_clip": {"max_grad_norm": None}, "no_aux": {"aux_weight": 0.0},
             # Whip-Rope's heavy budget (8 updates of 4 x 10 steps), 5x the updates
             "long": {"total_env_steps": 1600},
             # and a smaller actor step (the raw gradient norm grows as `long`'s curve falls)
             "long_lr_low": {"total_env_steps": 1600, "actor_learning_rate": 2e-4},
             # the unfold tasks' curve, too short at 60 updates of 8 envs x window 1 (6
             # episode ends per env), read: 100 updates end 10 (benchmarks.budgets: to read)
             "steps_800": {"total_env_steps": 800},
             # a tenth of the actor step: where the gradient's direction is mostly noise
             # (Push-Rope), a clipped Adam step of full size is a random walk (hypothesis 2)
             "lr_low": {"actor_learning_rate": 1e-4},
             # training rollouts near the deterministic policy that is scored (std 0.05
             # pre-tanh instead of 0.37): APG, deterministic, learns Pour-Water at the same
             # window and a smaller budget, SHAC barely
             "std_low": {"init_log_std": -3.0}},
    "ild": {"baseline": {}, "raw_obs": {"normalize_obs": False},
            "aligned": {"align": "start"},
            # the demonstration moved by the task's own goal alignment (Push-Rope: slid
            # along the goal line only, where `aligned`'s rigid fit would also turn it)
            "goal_aligned": {"align": "goal"}, "no_clip": {"max_grad_norm": None},
            "lr_low": {"learning_rate": 1e-4},
            # a budget read off the curve: the MPM tasks' heavy budget is 5-10 updates of
            # 2 episodes (Whip-Rope: 10, about 50 gradient steps for a policy that has to
            # learn a 50-step throw); 5x the updates
            "long": {"total_env_steps": 5000},
            # the gradient of 2 starts per update being too noisy to follow: the same
            # updates on 8 starts each
            "envs_8": {"num_envs": 8, "total_env_steps": 4000},
            # or long's 50 updates at a tenth of the step
            "long_lr_low": {"total_env_steps": 5000, "learning_rate": 1e-4},
            # the gripper's path alone (Whip-Rope: the rope's states through a 50-step
            # whip give a gradient that more starts per update or more updates follow
            # to lower scores; the gripper's is the smooth part of the state)
            "effector_only": {"object_weight": 0.0},
            "object_low": {"object_weight": 0.1},
            # the pusher's path alone, moved by the task's goal alignment (Push-Rope: the
            # demonstration's pushes slid along the goal line onto the rope)
            "goal_effector": {"align": "goal", "object_weight": 0.0}},
    "ppo": {"baseline": {}, "no_aux": {"aux_weight": 0.0}, "object_frame": {"frame": "object"},
            # a budget read off the curve: on the unfold tasks the cloth budget's 12 updates
            # end too few episodes to split its curve in fifths (budgets table: too short);
            # on the pours (8 envs x 12 steps) 96 updates, 11.5 episodes per env
            "long": {"total_env_steps": 9216},
            # the same 12 updates on 4x the envs: on the cloth the first gradient of the
            # budget's 192 samples is noise (benchmarks.gradient_noise, Fold-Cloth-1 SNR
            # 0.11), and more updates of it (long) stay flat
            "batch_256": {"num_envs": 256, "total_env_steps": 9216},
            # fewer envs, longer unrolls: every env finishes several episodes in training
            "whole_episodes": {"num_envs": 8, "unroll_length": 12, "total_env_steps": 1920},
            # and a discount that sees the episode's end (0.9 per step is a 10-step horizon;
            # the score is the 50th or 100th step's r_gt on the MPM tasks)
            "whole_episodes_d99": {"num_envs": 8, "unroll_length": 12,
                                   "total_env_steps": 1920, "discount": 0.99},
            "lr_high": {"learning_rate": 3e-3},
            # the cloth curves too short to read (benchmarks.budgets: to read): 10 episode
            # ends per env of 64 envs x 3 steps, Fold-Cloth-3 (horizon 4), Fold-T-shirt (5)
            # and Unfold-Cloth-1 (10)
            "steps_2688": {"total_env_steps": 2688},
            "steps_3264": {"total_env_steps": 3264},
            "steps_6528": {"total_env_steps": 6528},
            # the object's frame (start-invariant observations and picks) and the curve's
            # length: on Unfold-Cloth-3 the object frame alone splits the seeds between
            # unfolding and not
            "object_frame_long": {"frame": "object", "total_env_steps": 9216},
            # and twice that, where the long run's training curve still rises
            "object_frame_longer": {"frame": "object", "total_env_steps": 18432},
            # Push-Rope in the object's frame at PPO's default step (its budget takes a
            # tenth of it so as not to walk the policy off): which side of the goal line a
            # push must cross depends on where the rope lies, which the frame removes
            "object_frame_lr_default": {"frame": "object", "learning_rate": 1e-3},
            # a tenth of the default step (1e-3): on Push-Rope, where APG's and SHAC's
            # budget step walked their policies under the untrained one
            "lr_low": {"learning_rate": 1e-4},
            # the policy mean drifting under noisy advantages (a smaller step, a narrower
            # Gaussian), on whole episodes so the curve is read
            "whole_episodes_lr_low": {"num_envs": 8, "unroll_length": 12,
                                      "total_env_steps": 1920, "learning_rate": 1e-4},
            "whole_episodes_std_low": {"num_envs": 8, "unroll_length": 12,
                                       "total_env_steps": 1920, "init_log_std": -1.5},
            # on the pours: the whole-episode budget's 96 samples per update, in minibatches
            # of 24, may be why its seeds end anywhere from under their untrained score to
            # far above it: 4x the envs per update (minibatches of 96), or a third of the
            # step on the same samples
            "whole_episodes_envs_32": {"num_envs": 32, "unroll_length": 12,
                                       "total_env_steps": 7680},
            "whole_episodes_lr_mid": {"num_envs": 8, "unroll_length": 12,
                                      "total_env_steps": 1920, "learning_rate": 3e-4},
            # a batch whose gradient has a direction (benchmarks.gradient_noise): 64 whole
            # episodes per update
            "big_batch": _PPO_WHOLE_EPISODES_64,
            # and a discount that sees the score's step (0.9 per step: a 10-step horizon)
            "big_batch_d99": {**_PPO_WHOLE_EPISODES_64, "discount": 0.99},
            # and a step matched to that gradient's signal-to-noise (benchmarks.gradient_noise):
            # the baseline is this batch at the default rate since it became the budget
            "big_batch_lr_low": {**_PPO_WHOLE_EPISODES_64, "learning_rate": 1e-4},
            # and exploration noise that keeps the training episodes near what the
            # deterministic policy scores (std 0.22 pre-tanh instead of 0.61)
            "big_batch_std_low": {**_PPO_WHOLE_EPISODES_64, "init_log_std": -1.5},
            # a batch at the size where the first gradient's signal-to-noise reaches 1 on
            # Whip-Rope (benchmarks.gradient_noise's "samples for SNR 1"), 5 updates
            "huge_batch": {"num_envs": 64, "unroll_length": 250, "total_env_steps": 80000},
            # the same batch for 2 updates: huge_batch's training return peaks at its
            # second update on Whip-Rope and falls after
            "huge_batch_2": {"num_envs": 64, "unroll_length": 250, "total_env_steps": 32000},
            # the budget's first 1-4 updates (a constant step size: each is the start of
            # the baseline's run), scored as the baseline is: the curve of the
            # deterministic policy that the training episodes' curve does not show
            **{f"updates_{k}": {**_PPO_WHOLE_EPISODES_64, "total_env_steps": 3200 * k}
               for k in range(1, 5)}},
    "transporter": {"baseline": {}, "aligned_goal": {"align_goal": True},
                    "no_goal": {"goal_image": False},
                    "rotate_any": {"augment_rotation": 3.141592653589793}},
}


def make_scorer(env, method, config):
    """``score(policy, seed) -> (n_eval,)``: the final-step r_gt of each evaluation rollout
    of ``policy`` from the seed's evaluation starts, as the runner evaluates a trained
    policy (:func:`dax_algos.learner.learner_episode`: the starts of
    ``fold_in(PRNGKey(seed), 0)``), compiled once."""
    lrn = method.learner
    evaluate = jax.jit(lrn.make_evaluate(env, config, lrn.make_act(env, config),
                                         per_rollout=True))

    def score(policy, seed: int) -> np.ndarray:
        out = evaluate(policy, jax.random.fold_in(jax.random.PRNGKey(seed), 0),
                       env.default_params)
        return np.asarray(jax.device_get(out.score), np.float64)

    return score


def untrained_policy(env, method, config, seed: int):
    """The policy before training (:meth:`dax_algos.learner.Learner.untrained`): the
    network's initial parameters drawn from the seed's key as the runner draws them
    (:func:`dax_algos.learner.untrained_key`) and the normaliser's initial statistics."""
    return method.learner.untrained(env, config, untrained_key(jax.random.PRNGKey(seed)))


def grid_baseline(grid_dir, task: str, method_name: str, seeds, budget: str,
                  sets: dict, any_machine: bool = False) -> list[dict]:
    """The baseline's seed records taken from a benchmark grid's rows instead of trained
    again: the grid's ``ok`` row of (``task``, ``method_name``, seed, ``budget``) for each
    of ``seeds`` it has, its score, untrained score and learning curve (the training
    episodes' score per update), marked ``"source"``. A row counts only if it was measured
    on what today's baseline would run: its task fingerprint and method config digest are
    today's (:func:`dax_algos.bench.provenance.stale_reason`, with ``sets`` applied),
    and it ran on this device and machine class (:func:`dax_algos.bench.rundir.
    machine_class`; a row that does not record its class is of an unknown one), since
    training repeats to the bit only within one class; otherwise ``ValueError`` says which
    seed and why. ``any_machine`` takes rows of another or unknown class (each record's
    provenance says which, :func:`record_machine`, and the table notes the mix).
    Per-rollout scores and gradient norms are not in a grid row, so those fields are
    empty."""
    grid_dir = Path(grid_dir)
    rows = {int(r["seed"]): r
            for r in rows_mod.latest(rows_mod.read_rows(grid_dir / "results.csv"))
            if r["task"] == task and r["method"] == method_name and r["budget"] == budget
            and r["status"] == "ok"}
    runs = {(task, method_name, s, budget) for s in seeds}
    curves: dict = {}
    for c in learning.read_curves(learning.learning_path(grid_dir, task), keep=runs):
        curves.setdefault(c["seed"], []).append(c["score"])
    today = provenance.Today(method_overrides={method_name: sets})
    here, device = rundir.machine_class(), provenance.device()
    out = []
    for seed in seeds:
        row = rows.get(int(seed))
        if row is None:
            continue
        why = provenance.stale_reason(row, today)  # a row without provenance: unknown
        if why:
            raise ValueError(f"{grid_dir}: {task} {method_name} seed {seed} is not today's "
                             f"baseline ({why})")
        machine = row.get("machine") or "unknown"
        if not any_machine and (machine == "unknown" or machine != here
                                or row["device"] != device):
            raise ValueError(
                f"{grid_dir}: {task} {method_name} seed {seed} ran on device "
                f"{row['device'] or 'unknown'}, machine class {machine!r}, not this one "
                f"({device}, {here!r}): a seed trained again need not repeat it (training "
                f"repeats to the bit only within one class); train the baseline here, or "
                f"pass --baseline-any-machine to borrow it anyway")
        prov = {k: row.get(k, "") for k in (*provenance.COLUMNS, "machine")}
        out.append(_json_safe({
            "method": method_name, "task": task, "budget": budget, "variant": "baseline",
            "changes": {}, "sets": sets, "seed": int(seed), "source": f"grid:{grid_dir}",
            "provenance": prov, "status": "ok", "score": float(row["score"]),
            "rollouts": None, "untrained": float(row["untrained_score"]),
            "untrained_rollouts": None, "curve": curves.get(int(seed), []),
            "return_curve": [], "grad_norm": [],
            "nonfinite_grads": int(row["nonfinite_grads"] or 0),
            "wall_s": float(row["wall_s"] or "nan"),
            "compile_s": float(row["compile_s"] or "nan"),
            "env_steps": int(row["env_steps"] or 0),
            "env_steps_per_s": (round(int(row["env_steps"]) / float(row["wall_s"]), 2)
                                if row["env_steps"] and row["wall_s"] else None)}))
    return out


def run_seeds(task: str, method_name: str, variant: str, changes: dict, seeds, budget: str,
              sets: dict, demo_dir=None):
    """The seed records of one variant (a generator): the method's episode (train, then
    evaluate) compiled once and called per seed with ``PRNGKey(seed)`` as the runner calls
    it (:func:`dax_algos.bench.execute.run_method`), the trained policy then evaluated per
    rollout beside its untrained one."""
    env = dax_tasks.make(task)
    method = registry.get(method_name)
    overrides = {**sets, **changes}
    config = method.config(budget, task, **overrides)
    run = method.build(env, config)
    data = execute.demonstrations(env, run, demo_dir, None)
    params = env.default_params
    t0 = time.perf_counter()
    compiled = jax.jit(run.episode).lower(jax.random.PRNGKey(0), params, *data).compile()
    compile_s = time.perf_counter() - t0
    score = make_scorer(env, method, config)
    prov = provenance.of_run(env, config)  # what the runner's rows record of the code
    machine = rundir.cpu_info()  # training repeats to the bit only on one machine class
    for seed in seeds:
        rec = {"method": method_name, "task": task, "budget": budget, "variant": variant,
               "changes": changes, "sets": sets, "seed": seed,
               "load_1min": round(os.getloadavg()[0], 2), "provenance": prov,
               "machine": machine}
        t0 = time.perf_counter()
        out = jax.device_get(jax.block_until_ready(
            compiled(jax.random.PRNGKey(seed), params, *data)))
        wall = time.perf_counter() - t0
        rollouts = score(out.policy, seed)
        untrained = score(untrained_policy(env, method, config, seed), seed)
        m = out.metrics
        steps = int(run.train_env_steps)
        finite = bool(np.all(np.isfinite(rollouts)))
        rec.update(status="ok" if finite else "failed",
                   score=float(np.mean(rollouts)), rollouts=rollouts.tolist(),
                   untrained=float(np.mean(untrained)), untrained_rollouts=untrained.tolist(),
                   curve=np.asarray(m.score, np.float64).tolist(),
                   return_curve=np.asarray(m.episode_return, np.float64).tolist(),
                   grad_norm=np.asarray(m.grad_norm, np.float64).tolist(),
                   nonfinite_grads=int(np.sum(m.nonfinite)),
                   wall_s=round(wall, 2), compile_s=round(compile_s, 2), env_steps=steps,
                   env_steps_per_s=round(steps / wall, 2) if steps else None)
        yield _json_safe(rec)


def _mean_or_none(values):
    """The mean of the values that are not ``None`` (``None`` if every one is)."""
    xs = [v for v in values if v is not None]
    return float(np.mean(xs)) if xs else None


def _json_safe(x):
    """``x`` with non-finite floats as ``None`` (JSON has no NaN)."""
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, dict):
        return {k: _json_safe(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_json_safe(v) for v in x]
    return x


def summarise(records: list[dict]) -> list[dict]:
    """One summary per variant (see the module docstring), baseline first."""
    ok = [r for r in records if r["status"] == "ok"]
    by_variant: dict[str, dict[int, dict]] = {}
    for r in ok:
        by_variant.setdefault(r["variant"], {})[r["seed"]] = r
    base = by_variant.get("baseline", {})
    out = []
    for variant in sorted(by_variant, key=lambda v: (v != "baseline", v)):
        runs = by_variant[variant]
        scores = [r["score"] for r in runs.values()]
        untrained = [r["untrained"] for r in runs.values()]
        mean, se = report.mean_se(scores)
        umean, use = report.mean_se(untrained)
        paired = [runs[s]["score"] - base[s]["score"] for s in runs if s in base]
        dmean, dse = report.mean_se(paired) if variant != "baseline" else (math.nan, math.nan)
        first = next(iter(runs.values()))
        out.append({"summary": True, "method": first["method"], "task": first["task"],
                    "budget": first["budget"], "variant": variant,
                    "changes": first["changes"], "seeds": sorted(runs),
                    "score_mean": mean, "score_se": se, "untrained_mean": umean,
                    "untrained_se": use, "minus_baseline": dmean,
                    "minus_baseline_se": dse,
                    "better": bool(len(paired) > 1 and dmean > 2 * dse),
                    "grad_norm_median": _median_norm(runs.values()),
                    # None for a method trained on demonstrations only (Transporter)
                    "env_steps_per_s": _mean_or_none([r["env_steps_per_s"]
                                                      for r in runs.values()])})
    return out


def _median_norm(runs) -> float | None:
    """The median raw policy-gradient norm over every update of ``runs`` (None where none
    was recorded, e.g. PPO's is not a simulator gradient)."""
    norms = [g for r in runs for g in r.get("grad_norm") or () if g is not None]
    return float(np.median(norms)) if norms else None


def chart(records: list[dict], summaries: list[dict], path) -> Path:
    """Evaluation score per variant (mean ± SE over seeds, dots: seeds; the untrained
    policy's as a hollow marker) and the mean training curve per variant."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(11, 4))
    names = [s["variant"] for s in summaries]
    for i, s in enumerate(summaries):
        ax.errorbar([i], [s["score_mean"]], yerr=[s["score_se"] or 0.0], fmt="o",
                    color=f"C{i}", capsize=4)
        ax.errorbar([i + 0.25], [s["untrained_mean"]], yerr=[s["untrained_se"] or 0.0],
                    fmt="o", mfc="none", color=f"C{i}", capsize=3)
        seeds = [r["score"] for r in records
                 if r["variant"] == s["variant"] and r["status"] == "ok"]
        ax.plot([i - 0.15] * len(seeds), seeds, "k.", alpha=0.5)
        curves = [r["curve"] for r in records
                  if r["variant"] == s["variant"] and r["status"] == "ok" and r["curve"]]
        if curves:  # an update in which no episode ended has no point (None)
            n = min(len(c) for c in curves)
            arr = np.asarray([[np.nan if x is None else x for x in c[:n]] for c in curves],
                             np.float64)
            ended = np.isfinite(arr).any(0)
            if ended.any():
                ax2.plot(np.arange(n)[ended], np.nanmean(arr[:, ended], 0), ".-",
                         color=f"C{i}", label=s["variant"])
    ax.set_xticks(range(len(names)), names, rotation=20)
    ax.set_ylabel("evaluation score (final-step r_gt)")
    ax.set_title("filled: trained, mean ± SE over seeds; hollow: untrained", fontsize=9)
    ax.grid(True, axis="y", alpha=0.3)
    ax2.set_xlabel("update")
    ax2.set_ylabel("training episodes' final-step r_gt (mean over seeds)")
    ax2.legend(fontsize=8)
    ax2.grid(True, alpha=0.3)
    s0 = summaries[0]
    fig.suptitle(f"{s0['method']} on {s0['task']}: ablations ({s0['budget']} budget)")
    fig.tight_layout()
    path = Path(path)
    atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=100))
    plt.close(fig)
    return path


def write(path, records: list[dict]) -> list[dict]:
    """Rewrite ``path`` atomically: the seed records, then the summaries."""
    summaries = [_json_safe(s) for s in summarise(records)]
    atomic_write(path, "".join(json.dumps(r) + "\n" for r in records + summaries))
    return summaries


def render_table(*paths) -> str:
    """The Markdown table of ablation files (their summary lines, recomputed from the seed
    records): per method, task and variant, the change, the evaluation score and the
    untrained policy's (mean ± SE over seeds), the paired difference from the baseline
    and whether the change is kept."""
    from benchmarks._report import load_range, read_result

    lines = ["| method | task | variant | change | seeds | score | untrained | "
             "− baseline (paired) | kept | gradient norm |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    loads, names, borrowed, mixed = [], [], [], []
    for path in paths:
        _, records = read_result(path)
        seeds = [r for r in records if not r.get("summary")]
        if not seeds or "variant" not in seeds[0]:
            raise KeyError("variant")
        classes = {record_machine(r) for r in seeds}
        if len(classes) > 1:
            mixed.append(f"`{Path(path).as_posix()}` ({len(classes)} classes)")
        loads += [r["load_1min"] for r in seeds if "load_1min" in r]
        names.append(Path(path).as_posix())
        sources = sorted({r["source"].removeprefix("grid:") for r in seeds if "source" in r})
        if sources:
            borrowed.append(f"{seeds[0]['method']} on {seeds[0]['task']}: the grid "
                            f"{', '.join(f'`{s}`' for s in sources)}")

        def pm(m, se):
            return "—" if m is None else (f"{m:.3f} ± {se:.3f}" if se is not None
                                           else f"{m:.3f} (n=1)")

        for s in [_json_safe(x) for x in summarise(seeds)]:
            change = ", ".join(f"{k}={v}" for k, v in s["changes"].items()) or "—"
            kept = "baseline" if s["variant"] == "baseline" else (
                "yes" if s["better"] else "no")
            g = s["grad_norm_median"]
            norm = "—" if g is None else f"{g:.2g}"
            lines.append(
                f"| {s['method']} | {s['task']} | {s['variant']} | {change} | "
                f"{len(s['seeds'])} | {pm(s['score_mean'], s['score_se'])} | "
                f"{pm(s['untrained_mean'], s['untrained_se'])} | "
                f"{pm(s['minus_baseline'], s['minus_baseline_se'])} | {kept} | {norm} |")
    lines += ["", f"From {', '.join(f'`{n}`' for n in names)} (`python -m benchmarks.ablate`; "
              f"{seeds[0]['budget']} budgets; 1-minute load {load_range(loads)}, 2 CPU "
              "cores). Score: the trained policy's mean final-step r_gt over its evaluation "
              "rollouts, mean ± SE over training seeds; untrained: the same network at "
              "initialisation on the same starts; a change is kept only where it beats the "
              "baseline by more than 2 SE of the difference paired by seed. Gradient norm: "
              "the median raw (unclipped) policy-gradient norm over every update and seed."]
    if borrowed:
        lines[-1] += (" Baseline seeds taken from a benchmark grid's rows of the same config "
                      "and task code instead of trained again (`--baseline-from`): "
                      + "; ".join(borrowed) + ".")
    if mixed:
        lines[-1] += (" Seeds of more than one machine class (the CPU features XLA compiles "
                      "for; unknown where a record or grid row does not say), on which one "
                      "seed's training need not repeat, so that a paired difference may "
                      "compare two machines' runs: " + "; ".join(mixed) + ".")
    return "\n".join(lines) + "\n"


def record_machine(record: dict) -> str:
    """The machine class a seed record ran on (:func:`dax_algos.bench.rundir.
    machine_class`): its provenance's ``machine`` (a grid row's, or
    :func:`dax_algos.bench.provenance.of_run`'s), else the class of its ``machine`` CPU
    info (records of before provenance held it), else ``"unknown"``."""
    machine = (record.get("provenance") or {}).get("machine")
    if machine:
        return machine
    return rundir.machine_class(record["machine"]) if record.get("machine") else "unknown"


def stale_seeds(records: list[dict], method: str, task: str, variant: str, overrides: dict,
                budget: str) -> list[int]:
    """The seeds of ``variant``'s records measured on something else than today's code
    builds: their method config (recorded ``config_digest``) is not the one ``overrides``
    on today's ``budget`` give (a variant is its changes from the budget, so a budget
    changed since leaves them another run), or their task (recorded ``task_fingerprint``:
    the spec and the dax-tasks / dax-physics sources) is not today's: the runner's rule
    (:func:`dax_algos.bench.provenance.stale_reason`), except that a record without
    provenance is not stale (the oldest files predate it)."""
    today = provenance.Today(method_overrides={method: overrides})
    return sorted(r["seed"] for r in records if r["variant"] == variant
                  and provenance.has_provenance(prov := r.get("provenance", {}))
                  and provenance.stale_reason(
                      {**r, **prov, "method": method, "task": task, "budget": budget}, today))


def join(records: list[dict], piece, method: str, task: str) -> list[dict]:
    """The seed records of the ablation file ``piece`` (one run in pieces, each into its
    own ``--out``) that ``records`` lacks, by (variant, seed). A piece of another method or
    task, or one whose record of a (variant, seed) that ``records`` holds has another score,
    is refused (ValueError naming it): those are two runs, not pieces of one."""
    have = {(r["variant"], r["seed"]): r for r in records}
    added = []
    for r in read_records(piece):
        if (r.get("method"), r.get("task")) != (method, task):
            raise ValueError(f"{piece}: a record of {r.get('method')} on {r.get('task')}, "
                             f"not {method} on {task}")
        key = (r["variant"], r["seed"])
        if key in have:
            if have[key].get("score") != r.get("score"):
                raise ValueError(f"{piece}: variant {key[0]!r} seed {key[1]} scores "
                                 f"{r.get('score')} there and {have[key].get('score')} in "
                                 f"--out: two runs of one seed, not pieces of one run")
            continue
        have[key] = r
        added.append(r)
    return added


#: The variant every learner has on every task, its config fields computed by
#: :func:`to_read_variant`: the budget trained until every env has ended
#: :data:`benchmarks.budgets.MIN_UPDATES` episodes, to read a curve the budget table calls
#: too short. The ``steps_N`` variants above are the same run on the tasks they name,
#: under the names the result files of its first reads record.
TO_READ = "to_read"


def to_read_variant(method: str, task: str, budget: str, sets: dict) -> dict:
    """The config fields of :data:`TO_READ` for ``method``'s ``budget`` config on ``task``
    with ``sets``: ``total_env_steps`` from :func:`benchmarks.budgets.steps_to_read` at the
    config's own env steps per update (those of a config asked for one env step, which
    every learner rounds up to one update)."""
    from benchmarks.budgets import steps_to_read

    m = registry.get(method)
    one = m.config(budget, task, **{**sets, "total_env_steps": 1})
    per_update = m.learner.train_env_steps(dax_tasks.make(task), one)
    return {"total_env_steps": steps_to_read(task, method, budget, per_update, **sets)}


#: The variants every learner has on every task: the budget's config trained for a multiple
#: of its env steps (:func:`scaled_variant`): ``x3`` to read a curve the budget table calls
#: rising (its last fifth still above the fifth before by more than 2 SE and the evaluation
#: SE), ``half`` one it calls falling (a run that may have peaked before its budget ended).
SCALED = {"x3": 3.0, "half": 0.5}


def scaled_variant(method: str, task: str, budget: str, sets: dict, factor: float) -> dict:
    """The config fields of a :data:`SCALED` variant for ``method``'s ``budget`` config on
    ``task`` with ``sets``: its ``total_env_steps`` times ``factor`` (rounded, at least 1;
    the learner rounds it to whole updates); ``{}`` for a method without env steps."""
    steps = getattr(registry.get(method).config(budget, task, **sets), "total_env_steps",
                    None)
    return {} if steps is None else {"total_env_steps": max(1, round(factor * steps))}


def _seeds(text: str) -> range:
    try:
        return grid.parse_seeds(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.ablate",
                                description=__doc__.split("\n\n")[0])
    p.add_argument("method", choices=sorted(VARIANTS))
    p.add_argument("task", choices=sorted(dax_tasks.TASKS))
    p.add_argument("--variants", default=None,
                   help="comma-separated (default: all of the method's)")
    p.add_argument("--seeds", type=_seeds, default=range(3), metavar="K|A-B",
                   help="seeds 0..K-1, or A..B (a piece run beside another process into "
                        "its own --out; default 3)")
    p.add_argument("--budget", default="full", choices=BUDGETS)
    p.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                   help="config override for every variant (Python literal)")
    p.add_argument("--demos", default=None, help="demonstration directory")
    p.add_argument("--baseline-from", default=None, metavar="GRID_DIR",
                   help="take the baseline's seeds from this benchmark grid's rows (same "
                        "task code and config as today's baseline) instead of training them")
    p.add_argument("--baseline-any-machine", action="store_true",
                   help="with --baseline-from: take rows run on another device or machine "
                        "class (or one the row does not record) too; the table says so")
    p.add_argument("--max-minutes", type=float, default=None,
                   help="start no new seed after this many minutes (resume later)")
    p.add_argument("--join", action="append", default=[], metavar="PIECE",
                   help="first add this file's seed records (a piece of the same ablation "
                        "run with its own --out) that --out lacks; repeatable")
    p.add_argument("--out", required=True, help="JSON lines file (the chart goes beside)")
    args = p.parse_args(argv)
    sets = parse_sets(args.set)
    table = dict(VARIANTS[args.method])
    valid = [*table, TO_READ, *SCALED]
    names = [n.strip() for n in (args.variants or ",".join(valid)).split(",")]
    unknown = [n for n in names if n not in valid]
    if unknown:
        p.error(f"unknown variant(s) {unknown}; valid for {args.method}: {', '.join(valid)}")
    if TO_READ in names:  # (builds the task: seconds for a cloth task, so only when asked)
        table[TO_READ] = to_read_variant(args.method, args.task, args.budget, sets)
    for name in SCALED.keys() & set(names):
        table[name] = scaled_variant(args.method, args.task, args.budget, sets, SCALED[name])
    execute.use_default_compilation_cache()
    out = Path(args.out)
    records = read_records(out)
    for piece in args.join:
        try:
            records += join(records, piece, args.method, args.task)
        except ValueError as err:
            p.error(str(err))
    if args.join:
        write(out, records)
    done = {(r["variant"], r["seed"]) for r in records}
    t0 = time.monotonic()

    def expired() -> bool:
        return args.max_minutes is not None and time.monotonic() - t0 > 60 * args.max_minutes

    if args.baseline_from and "baseline" in names:
        todo = [s for s in args.seeds if ("baseline", s) not in done]
        try:
            records += grid_baseline(args.baseline_from, args.task, args.method, todo,
                                     args.budget, sets, args.baseline_any_machine)
        except ValueError as err:
            p.error(str(err))
        write(out, records)
        done = {(r["variant"], r["seed"]) for r in records}
    for name in names:
        todo = [s for s in args.seeds if (name, s) not in done]
        if not todo:
            continue
        if expired():
            break
        stale = stale_seeds(records, args.method, args.task, name, {**sets, **table[name]},
                            args.budget)
        if stale:
            p.error(f"{out}: variant {name!r} seeds {stale} were run with another config "
                    f"than today's {args.budget} budget gives it, or on other task code "
                    f"(a budget, spec or physics changed since); resuming would mix the "
                    f"two: write to a new --out")
        for rec in run_seeds(args.task, args.method, name, table[name], todo, args.budget,
                             sets, args.demos):
            records.append(rec)
            print(json.dumps({k: rec.get(k) for k in ("variant", "seed", "status", "score",
                                                      "untrained", "wall_s", "error")}),
                  file=sys.stderr, flush=True)
            write(out, records)
            if expired():  # between seeds too: one variant's seeds can take hours
                break
    summaries = write(out, records)
    for s in summaries:
        print(json.dumps(s))
    if summaries:
        print(chart(records, summaries, out.with_suffix(".png")), file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
