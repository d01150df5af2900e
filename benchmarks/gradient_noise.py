"""How much of a learner's first policy gradient is signal: the gradient at the initial
policy from independent batches of the task, compared (JSON).

For one task, one method and one batch shape, ``--batches`` K independent batches are drawn
(fresh starts per batch; the initial networks of ``--seed``; the normaliser's initial
statistics) and for each the policy gradient g_k of the method's first update:

* ``ppo`` (``--num-envs`` x ``--unroll`` steps): collected as PPO's first update collects
  them (:func:`dax_algos.rl.ppo.make_collect`: auto-resetting envs, GAE advantages), the
  gradient of the policy part of :func:`dax_algos.rl.losses.ppo_loss` over the whole batch
  (at the initial policy the ratio is 1: the advantage-weighted score function);
* ``apg`` (``--num-envs`` episodes, or windows of ``--unroll`` steps): the gradient of
  APG's objective through the simulator (:func:`dax_algos.rl.apg.make_rollout`), where
  the batches differ only in their starts;
* ``shac`` (``--num-envs`` envs, the first window of ``--unroll`` steps, default the
  budget's): the gradient of SHAC's actor objective through the simulator
  (:func:`dax_algos.rl.shac.make_actor_loss`: the reparameterised stochastic policy over
  the window, closed by the untrained target critic's value), where the batches differ
  in their starts and their exploration noise;
* ``ild`` (``--num-envs`` episodes, or their first window of ``--unroll`` steps): the
  gradient of ILD's tracking loss through the simulator
  (:func:`dax_algos.il.ild.make_window_loss`) towards the task's standard demonstration,
  moved onto each start as the budget's ``align`` says; the batches differ only in their
  starts.

Reported, for the whole policy gradient and for its output bias alone (the direction the
deterministic action's mean moves):

* ``cosine_mean``: the mean cosine similarity of the K(K-1)/2 pairs (0 for pure noise, 1
  for one direction);
* ``snr``: the signal-to-noise ratio of one batch's gradient, ``sqrt(max(|ḡ|² - s²/K, 0) /
  s²)`` with ``ḡ`` the mean over batches and ``s²`` the batches' total variance (an
  unbiased estimate of ``|E g|² / E|g - E g|²`` under the square root);
* ``samples_for_snr_1``: the batch size at which one batch's gradient would have SNR 1
  (the noise falls as 1 / batch), ``samples_per_batch / snr²``.

PPO's value network is at its initialisation, as at its first update, so the advantages
are close to the discounted rewards-to-go normalised over the batch. Measurements only:
nothing here is asserted in a test.

    python -m benchmarks.gradient_noise whip_rope --num-envs 32 --unroll 3 \\
        --batches 8 --out benchmarks/results/2026-11-28-gradient-noise.jsonl
    python -m benchmarks.gradient_noise fold_cloth1 --method apg --num-envs 4 \\
        --batches 8 --out benchmarks/results/2026-11-28-gradient-noise.jsonl
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import dax_tasks
from dax_algos import registry
from dax_algos.bench import execute, provenance
from dax_algos.il import demos, ild
from dax_algos.mlp_policy import ObsNorm, feature_dim
from dax_algos.rl import apg, gaussian, losses, ppo, shac
from dax_algos.rl.training import training_params


def batch_gradients(method: str, task: str, num_envs: int, unroll: int | None,
                    batches: int, seed: int, budget: str = "full"):
    """``(config, grads, bias_grads)``: the method's config used, the ``(batches,
    n_params)`` policy gradients (flattened) and the ``(batches, act_dim)`` output-bias
    gradients (for ``apg`` ``unroll=None`` is the episode)."""
    if method == "apg":
        return _apg_gradients(task, num_envs, unroll, batches, seed, budget)
    if method == "ild":
        return _ild_gradients(task, num_envs, unroll, batches, seed, budget)
    if method == "shac":
        return _shac_gradients(task, num_envs, unroll, batches, seed, budget)
    env = dax_tasks.make(task)
    config = registry.get("ppo").config(budget, task, num_envs=num_envs,
                                        unroll_length=unroll, minibatches=1)
    penv = ppo.policy_env(env, config)
    venv = dax_tasks.training_env(penv, num_envs)
    pnet, vnet = ppo.policy_network(penv, config), ppo.value_network(penv, config)
    collect = ppo.make_collect(penv, venv, pnet, vnet, config)
    params = training_params(env.default_params, config.aux_weight)
    k_pi, k_v = jax.random.split(jax.random.PRNGKey(seed))
    net = {"policy": pnet.init(k_pi), "value": vnet.init(k_v)}
    norm = ObsNorm.create(feature_dim(penv))

    def loss(policy, data):
        inputs, u, old_logp, adv, target = data
        mean, log_std = pnet.apply(policy, inputs)
        return losses.ppo_loss(gaussian.log_prob(u, mean, log_std), old_logp, adv,
                               jnp.zeros_like(target), target, gaussian.entropy(log_std),
                               config.clip, 0.0, config.entropy_cost)

    @jax.jit
    def one(key):
        k_env, k_act = jax.random.split(key)
        obs, state = venv.reset(k_env, params)
        _, _, data = collect(net, norm, obs, state, k_act, params)
        g = jax.grad(loss)(net["policy"], data)
        return _flat_and_bias(g)

    return config, *_per_batch(one, batches, seed)


def _apg_gradients(task, num_envs, window, batches, seed, budget):
    env = dax_tasks.make(task)
    config = registry.get("apg").config(budget, task, num_envs=num_envs, window=window)
    penv = apg.policy_env(env, config)
    venv = dax_tasks.training_env(penv, num_envs)
    pnet = apg.network(penv, config)
    rollout = apg.make_rollout(penv, venv, pnet, config, config.window_for(penv))
    params = training_params(env.default_params, config.aux_weight)
    policy = pnet.init(jax.random.PRNGKey(seed))
    norm = ObsNorm.create(feature_dim(penv))

    @jax.jit
    def one(key):
        k_env, k_run = jax.random.split(key)
        obs, state = venv.reset(k_env, params)
        g = jax.grad(lambda p: -rollout(p, norm, obs, state, k_run, params)[0])(policy)
        return _flat_and_bias(g)

    return config, *_per_batch(one, batches, seed)


def _shac_gradients(task, num_envs, window, batches, seed, budget):
    env = dax_tasks.make(task)
    config = registry.get("shac").config(budget, task, num_envs=num_envs,
                                         **({"window": window} if window else {}))
    penv = shac.policy_env(env, config)
    venv = dax_tasks.training_env(penv, num_envs)
    pnet, vnet = shac.policy_network(penv, config), shac.value_network(penv, config)
    loss = shac.make_actor_loss(penv, venv, pnet, vnet, config, config.window_for(penv))
    params = training_params(env.default_params, config.aux_weight)
    k_pi, k_v = jax.random.split(jax.random.PRNGKey(seed))
    policy, target = pnet.init(k_pi), vnet.init(k_v)
    norm = ObsNorm.create(feature_dim(penv))

    @jax.jit
    def one(key):
        k_env, k_run = jax.random.split(key)
        obs, state = venv.reset(k_env, params)
        g = jax.grad(lambda p: loss(p, target, norm, obs, state, k_run, params)[0])(policy)
        return _flat_and_bias(g)

    return config, *_per_batch(one, batches, seed)


def _ild_gradients(task, num_envs, window, batches, seed, budget):
    env = dax_tasks.make(task)
    config = registry.get("ild").config(budget, task, num_envs=num_envs,
                                        **({"window": window} if window else {}))
    demo = ild.load_data(env, demos.locate(env, ild.demo_spec(config)))
    venv = dax_tasks.VmapWrapper(env, num_envs)
    pnet = ild.network(env, config)
    loss = ild.make_window_loss(env, venv, pnet, config, config.window_for(env))
    params = env.default_params
    policy = pnet.init(jax.random.PRNGKey(seed))
    norm = ObsNorm.create(feature_dim(env))

    @jax.jit
    def one(key):
        obs, state = venv.reset(jax.random.split(key, num_envs), params)
        targets = ild.episode_targets(env, demo, state.physics, params, config)
        g = jax.grad(lambda p: loss(p, norm, obs, state, params, targets)[0])(policy)
        return _flat_and_bias(g)

    return config, *_per_batch(one, batches, seed)


def _per_batch(one, batches: int, seed: int):
    keys = jax.random.split(jax.random.PRNGKey(1000 + seed), batches)
    out = [jax.device_get(one(k)) for k in keys]
    return np.stack([o[0] for o in out]), np.stack([o[1] for o in out])


def _flat_and_bias(grads):
    """``(flat, bias)``: a policy gradient as one vector and its output bias's part."""
    flat = jnp.concatenate([jnp.ravel(x) for x in jax.tree_util.tree_leaves(grads)])
    return flat, _output_bias(grads)


def _output_bias(grads):
    """The gradient of the mean network's last bias (``(act_dim,)``)."""
    tree = jax.tree_util.tree_flatten_with_path(grads)[0]
    biases = [(jax.tree_util.keystr(p), v) for p, v in tree if "bias" in jax.tree_util.keystr(p)]
    return biases[-1][1]  # the layers in order: the last bias is the output layer's


def agreement(g: np.ndarray) -> dict:
    """``cosine_mean`` and ``snr`` (module docstring) of ``(K, n)`` gradients."""
    g = np.asarray(g, np.float64)
    k = g.shape[0]
    unit = g / np.maximum(np.linalg.norm(g, axis=1, keepdims=True), 1e-30)
    cos = unit @ unit.T
    cosine_mean = float((np.sum(cos) - k) / (k * (k - 1)))
    mean = g.mean(0)
    s2 = float(np.sum((g - mean) ** 2) / (k - 1))
    signal2 = max(float(np.sum(mean**2)) - s2 / k, 0.0)
    return {"cosine_mean": round(cosine_mean, 4),
            "snr": round(float(np.sqrt(signal2 / s2)), 4) if s2 > 0 else None}


def render_table(path) -> str:
    """The Markdown table of a file of :func:`main`'s JSON lines: per task, method and
    batch, the signal-to-noise ratio of one batch's policy gradient and of its output
    bias, their mean pairwise cosine and the samples one batch would need for SNR 1."""
    from benchmarks._report import file_date, read_result

    path, recs = read_result(path)
    out = ["| task | method | batch (envs × steps) | samples | SNR | cosine | samples for "
           "SNR 1 | output bias SNR | output bias cosine |",
           "|---|---|---|---|---|---|---|---|---|"]

    def n(x):
        return "—" if x is None else (f"{x:,}" if isinstance(x, int) else f"{x:.2f}")

    for r in recs:
        pol, bias = r["policy"], r["output_bias"]
        need = ("noise only" if not pol["snr"] else n(pol["samples_for_snr_1"]))
        out.append(f"| {r['task']} | {r['method']} | {r['num_envs']} × {r['unroll_length']} "
                   f"| {r['samples_per_batch']} | {n(pol['snr'])} | {n(pol['cosine_mean'])} "
                   f"| {need} | {n(bias['snr'])} | {n(bias['cosine_mean'])} |")
    loads = [r["load_1min"] for r in recs if r.get("load_1min") is not None]
    batches = sorted({r["batches"] for r in recs})
    out += ["", f"{'/'.join(map(str, batches))} independent batches per row (fresh starts), "
            "the initial networks of seed 0, the gradient of the method's first update "
            "(PPO: its clipped objective at ratio 1 with GAE advantages from an "
            "untrained critic; APG: its objective through the simulator; SHAC: its actor "
            "objective through the simulator, closed by its untrained critic; ILD: its "
            "tracking loss through the simulator). SNR: |mean "
            "gradient| over one batch's noise (0: no direction above the noise); cosine: "
            "mean over pairs of batches; samples for SNR 1: the batch whose noise variance, "
            "falling as 1 / samples, would equal the squared signal. "
            f"1-minute load {min(loads, default=0):.1f}-{max(loads, default=0):.1f}, 2 CPU "
            f"cores; `{path.as_posix()}` ({file_date(path) or 'date not recorded'})."]
    return "\n".join(out) + "\n"


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("task", choices=sorted(dax_tasks.TASKS))
    p.add_argument("--method", choices=("ppo", "apg", "shac", "ild"), default="ppo")
    p.add_argument("--num-envs", type=int, default=32)
    p.add_argument("--unroll", type=int, default=None,
                   help="steps per env in a batch (default: 3 for ppo, the episode for apg, "
                        "the budget's window for shac and ild)")
    p.add_argument("--batches", type=int, default=8)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", required=True, help="JSON lines file (appended)")
    args = p.parse_args(argv)
    if args.batches < 2:
        p.error("--batches must be at least 2")
    execute.use_default_compilation_cache()
    load = round(os.getloadavg()[0], 2)
    t0 = time.perf_counter()
    unroll = args.unroll if args.unroll or args.method != "ppo" else 3
    config, g, gb = batch_gradients(args.method, args.task, args.num_envs, unroll,
                                    args.batches, args.seed)
    env = dax_tasks.make(args.task)
    steps = (config.window_for(env) if args.method in ("shac", "ild")
             else unroll or env.horizon)
    samples = args.num_envs * steps
    rec = {"task": args.task, "method": args.method, "num_envs": args.num_envs,
           "unroll_length": steps, "samples_per_batch": samples,
           "batches": args.batches, "seed": args.seed, "load_1min": load,
           "wall_s": round(time.perf_counter() - t0, 1),
           "provenance": provenance.of_run(env, config)}
    for name, arr in (("policy", g), ("output_bias", gb)):
        a = agreement(arr)
        a["samples_for_snr_1"] = (round(samples / a["snr"] ** 2) if a["snr"] else None)
        a["grad_norm_median"] = float(np.median(np.linalg.norm(arr, axis=1)))
        rec[name] = a
    rec["output_bias_mean"] = np.round(gb.mean(0), 6).tolist()
    rec["output_bias_sd"] = np.round(gb.std(0, ddof=1), 6).tolist()
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with out.open("a") as f:
        f.write(json.dumps(rec) + "\n")
    print(json.dumps({k: rec[k] for k in ("task", "method", "samples_per_batch", "policy",
                                          "output_bias")}))


if __name__ == "__main__":
    main()
