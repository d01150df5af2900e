"""APG's gradient stability against its backpropagation horizon (JSON lines + a chart).

For each window ``h`` (1 to the whole episode) and seed: the raw global norm of APG's
policy gradient at initialisation (the loss over ``h`` steps from a reset, ``num_envs``
envs), then APG trained with that window for the same number of environment steps at
every ``h`` and evaluated (final-step r_gt, ``n_eval`` rollouts). The chart
``apg_horizon_<task>.png`` shows the gradient norm (log scale) and the score against ``h``.

    python -m benchmarks.horizon_sweep --task whip_rope --horizons 1,4,16,70 --out DIR
    python -m benchmarks.horizon_sweep --task unfold_cloth1 --horizons 1,2,5,10 --out DIR

Long windows through a chaotic or contact-rich simulation make the gradient's norm grow
(or vanish) with ``h``; the clip (``max_grad_norm``) bounds the step, not the direction's
quality. Speed is not measured here.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import dax_tasks
from dax_algos import learner, mlp_policy, registry
from dax_algos.rl import apg, training
from dax_tasks.core.wrappers import training_env
from dax_tasks.io import atomic_write


def initial_gradient_norm(env, config: apg.APGConfig, key, params=None) -> float:
    """Raw global norm of APG's gradient at a fresh policy over ``config.window`` steps."""
    params = env.default_params if params is None else params
    tparams = training.training_params(params, config.aux_weight)
    window = config.window_for(env)
    venv = training_env(env, config.num_envs)
    pnet = apg.network(env, config)
    rollout = apg.make_rollout(env, venv, pnet, config, window)
    k_pi, k_env, k_run = jax.random.split(key, 3)

    def norm(k_pi, k_env, k_run):
        policy = pnet.init(k_pi)
        obs, state = venv.reset(k_env, tparams)
        obs_norm = mlp_policy.ObsNorm.create(mlp_policy.feature_dim(env))
        grads = jax.grad(lambda p: rollout(p, obs_norm, obs, state, k_run, tparams)[0])(policy)
        return jnp.sqrt(sum(jnp.sum(g**2) for g in jax.tree_util.tree_leaves(grads)))

    return float(jax.jit(norm)(k_pi, k_env, k_run))


def sweep(task: str, horizons, seeds: int, env_steps: int, base: dict | None = None,
          task_overrides: dict | None = None):
    env = dax_tasks.make(task, **(task_overrides or {}))
    method = registry.get("apg")
    for h in horizons:
        config = method.config("full", task, **{**(base or {}), "window": h,
                                                "total_env_steps": env_steps})
        episode = jax.jit(jax.vmap(learner.learner_episode(apg.LEARNER, env, config),
                                   in_axes=(0, None)))
        keys = jax.vmap(jax.random.PRNGKey)(jnp.arange(seeds))
        out = jax.device_get(episode(keys, env.default_params))
        for s in range(seeds):
            g0 = initial_gradient_norm(env, config, jax.random.fold_in(keys[s], 1))
            gn = np.asarray(out.metrics.grad_norm[s])
            yield {"task": task, "window": h, "seed": s, "grad_norm_init": g0,
                   "grad_norm_median": float(np.median(gn[np.isfinite(gn)]))
                   if np.isfinite(gn).any() else None,
                   "nonfinite_grads": int(np.sum(out.metrics.nonfinite[s])),
                   "score": float(out.episode.score[s]), "updates": int(gn.size),
                   "env_steps": env_steps,
                   "config": {k: (list(v) if isinstance(v, tuple) else v)
                              for k, v in dataclasses.asdict(config).items()}}


def chart(records, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    hs = sorted({r["window"] for r in records})
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    series = (("grad_norm_init", axes[0], "C0", "at initialisation"),
              ("grad_norm_median", axes[0], "C1", "median over training updates"),
              ("score", axes[1], "C0", None))
    for key, ax, colour, label in series:
        vals = [[r[key] for r in records if r["window"] == h and r[key] is not None]
                for h in hs]
        for h, v in zip(hs, vals, strict=True):
            ax.scatter([h] * len(v), v, color=colour, alpha=0.4, s=14)
        ax.plot(hs, [np.median(v) if v else np.nan for v in vals], "o-", color=colour,
                label=label)
    axes[0].set_ylabel("raw policy-gradient norm")
    axes[0].legend(fontsize=8)
    axes[1].set_ylabel("final-step r_gt after training")
    for ax in axes:
        ax.set_xscale("log")
        ax.set_xlabel("backpropagation window [env steps]")
        ax.grid(True, alpha=0.3)
    axes[0].set_yscale("log")
    task = records[0]["task"]
    fig.suptitle(f"{task}: APG against its backpropagation horizon "
                 f"({records[0]['env_steps']} training env steps at every window)")
    fig.tight_layout()
    atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=100))
    plt.close(fig)


def _norm(x) -> str:
    """A gradient norm with two significant figures (``-``: none)."""
    if x is None:
        return "-"
    if abs(x) >= 1e4:
        m, e = f"{x:.1e}".split("e")
        return f"{m}e{int(e)}"
    return f"{x:.0f}" if abs(x) >= 100 else f"{x:#.2g}".rstrip(".")


def render_table(*paths) -> str:
    """The Markdown table of sweeps written by :func:`main` (JSON lines, one per window and
    seed; one file per task): per task and window the updates, the gradient norm at
    initialisation, its median during training and the score after training, one value per
    training seed (in seed order), with the budget, clip and evaluation under the table."""
    from benchmarks._report import file_date, read_result

    recs, names = [], []
    for path in paths:
        path, lines = read_result(path)
        recs += lines if isinstance(lines, list) else [lines]
        names.append(f"`{path.as_posix()}` ({file_date(path) or 'date not recorded'})")
    out = ["| task | window [env steps] | updates | gradient norm at init | median during "
           "training | score after training |", "|---|---|---|---|---|---|"]
    groups = {}
    for r in recs:
        groups.setdefault((r["task"], r["window"]), []).append(r)
    for (task, window), rs in groups.items():
        rs = sorted(rs, key=lambda r: r["seed"])
        updates = ", ".join(dict.fromkeys(str(r["updates"]) for r in rs))
        scores = ", ".join("-" if r["score"] is None else f"{r['score']:.2f}" for r in rs)
        out.append(f"| {task} | {window} | {updates} | "
                   + " | ".join(", ".join(_norm(r[k]) for r in rs)
                                for k in ("grad_norm_init", "grad_norm_median"))
                   + f" | {scores} |")
    seeds = sorted({r["seed"] for r in recs})
    budget = "; ".join(
        f"{task}: {rs[0]['env_steps']} training env steps at every window, "
        f"{rs[0]['config'].get('num_envs')} envs"
        for task, rs in {r["task"]: [x for x in recs if x["task"] == r["task"]]
                         for r in recs}.items())
    cfg = recs[0]["config"] if recs else {}
    out += ["", f"One value per training seed (seeds {', '.join(map(str, seeds))}), no "
            f"standard error. Gradient norm: the raw global norm of APG's policy gradient "
            f"(before the clip at {cfg.get('max_grad_norm')}), at initialisation over the "
            f"window from a reset, and its median over the training updates; score: the "
            f"mean final-step r_gt of {cfg.get('n_eval')} evaluation rollouts of the "
            f"seed's trained policy. {budget}. Non-finite gradients: "
            f"{sum(r.get('nonfinite_grads', 0) for r in recs)}. The files record neither "
            f"the machine nor its load; " + ", ".join(names) + "."]
    return "\n".join(out) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.horizon_sweep",
                                description=__doc__.split("\n\n")[0])
    p.add_argument("--task", default="whip_rope")
    p.add_argument("--horizons", default="1,4,16,70")
    p.add_argument("--seeds", type=int, default=2)
    p.add_argument("--env-steps", type=int, default=560,
                   help="training environment steps at every window")
    p.add_argument("--out", default="horizon_sweep")
    p.add_argument("--replot", metavar="JSONL", help="only redraw the chart of a sweep's "
                   "JSON lines (written next to it)")
    args = p.parse_args(argv)
    if args.replot:
        path = Path(args.replot)
        records = [json.loads(line) for line in path.read_text().splitlines() if line]
        chart(records, path.with_suffix(".png"))
        return 0
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    records = []
    horizons = [int(h) for h in args.horizons.split(",")]
    for rec in sweep(args.task, horizons, args.seeds, args.env_steps):
        print(json.dumps(rec), flush=True)
        records.append(rec)
    atomic_write(out / f"apg_horizon_{args.task}.jsonl",
                 "".join(json.dumps(r) + "\n" for r in records))
    chart(records, out / f"apg_horizon_{args.task}.png")
    print(f"chart: {out / f'apg_horizon_{args.task}.png'}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
