"""The computations the multi-device tests compare, run in a process whose device count is
fixed before JAX is imported (``XLA_FLAGS=--xla_force_host_platform_device_count=N``):

* ``env``: ``training_env`` of a coarse Fold-Cloth-1 (4 x 4 vertices, 12 substeps per
  action), 8 envs: reset, one step, 3 random steps in a ``lax.scan`` (rewards, final vertices) and
  the gradient of the summed reward wrt the actions (forward and backward);
* ``env6``: reset and one step with 6 envs (not a multiple of 4: the divisibility
  rule);
* ``cem``: ``cem_optimise`` on that task's planning objective, population 8;
* ``ppo``, ``apg``, ``shac``: a few training updates on the toy task with 8 envs.

``python sharded_job.py OUT`` writes ``OUT.npz`` (every number) and ``OUT.json`` (the
device count, the shardings of the env's arrays, and whether each compiled program
communicates between devices).
"""

from __future__ import annotations

import dataclasses
import json
import re
import sys

import jax
import jax.numpy as jnp
import numpy as np

import dax_tasks
from dax_algos import learner, toy
from dax_algos.planning import cem_mpc, planner
from dax_algos.rl import apg, ppo, shac
from dax_tasks.core.wrappers import training_env

#: An op that moves data between devices: present only in a program XLA partitioned.
COLLECTIVE = re.compile(r"\b(all-reduce|all-gather|all-to-all|collective-permute|"
                        r"reduce-scatter)(-start)?\(")


def compiled(jitted, *args):
    """``jitted`` compiled for ``args`` (once: it is then called compiled), and whether the
    program communicates between devices."""
    program = jitted.lower(*args).compile()
    return program, bool(COLLECTIVE.search(program.as_text()))


def describe(x) -> dict:
    """The sharding of ``x``: its spec and the shape of every addressable shard."""
    s = x.sharding
    spec = str(s.spec) if hasattr(s, "spec") else type(s).__name__
    return {"spec": spec, "shards": [list(sh.data.shape) for sh in x.addressable_shards]}


def cloth():
    scene = dataclasses.replace(dax_tasks.get_spec("fold_cloth1").scene, n=4,
                                settle_substeps=6)
    return dax_tasks.make("fold_cloth1", scene=scene, substeps=12, cache_goal=False)


def env_job(env, batch, out, info, tag, rollout=True):
    venv = training_env(env, batch)
    reset = jax.jit(venv.reset)
    obs, state = reset(jax.random.PRNGKey(0))
    low, high = jnp.asarray(env.spec.action_low), jnp.asarray(env.spec.action_high)
    actions = jax.random.uniform(jax.random.PRNGKey(1), (3, batch, env.spec.action_dim),
                                 minval=low, maxval=high)
    step = jax.jit(venv.step)
    obs1, state1, r1, _, info1 = step(state, actions[0])
    out[f"{tag}_obs"] = np.asarray(obs)
    out[f"{tag}_step_obs"] = np.asarray(obs1)
    out[f"{tag}_step_reward"] = np.asarray(r1)
    arrays = {"reset_obs": obs, "reset_x": state.physics.x, "step_obs": obs1,
              "step_x": state1.physics.x, "step_reward": r1, "step_r_gt": info1["r_gt"]}
    info[tag] = {k: describe(v) for k, v in arrays.items()}
    if not rollout:
        return

    def total(acts, state):
        def body(s, a):
            _, s, r, _, _ = venv.step(s, a)
            return s, r
        final, rewards = jax.lax.scan(body, state, acts)
        return jnp.sum(rewards), (rewards, final)

    run, talks = compiled(jax.jit(jax.value_and_grad(total, has_aux=True)), actions, state)
    (_, (rewards, final)), grad = run(actions, state)
    out[f"{tag}_rewards"] = np.asarray(rewards)
    out[f"{tag}_vertices"] = np.asarray(final.physics.x)
    out[f"{tag}_grad"] = np.asarray(grad)
    info[tag]["rollout_x"] = describe(final.physics.x)
    info[tag]["rollout_rewards"] = describe(rewards)
    info[tag]["rollout_communicates"] = talks


def cem_job(env, out, info):
    value = planner.make_objective(env, "final")
    _, state = jax.jit(env.reset)(jax.random.PRNGKey(2))
    config = cem_mpc.CEMConfig(population=8, elites=2, iterations=2, horizon=2)

    def optimise(key):
        return cem_mpc.cem_optimise(lambda z: value(state, z, env.default_params),
                                    jnp.zeros((2, env.spec.action_dim)), key, config)

    run, talks = compiled(jax.jit(optimise), jax.random.PRNGKey(3))
    best_z, best_v = run(jax.random.PRNGKey(3))
    out["cem_best_z"], out["cem_best_v"] = np.asarray(best_z), np.asarray(best_v)
    info["cem"] = {"communicates": talks}


RL = {
    "ppo": (ppo, ppo.PPOConfig(total_env_steps=160, num_envs=8, unroll_length=5,
                               minibatches=2, epochs=2, policy_hidden=(16,),
                               value_hidden=(16,), n_eval=8)),
    "apg": (apg, apg.APGConfig(total_env_steps=160, num_envs=8, policy_hidden=(16,),
                               n_eval=8)),
    "shac": (shac, shac.SHACConfig(total_env_steps=160, num_envs=8, window=5,
                                   actor_hidden=(16,), critic_hidden=(16,), n_eval=8)),
}


def rl_job(out, info):
    env = toy.point_reach(horizon=5)
    for name, (module, config) in RL.items():
        episode = jax.jit(learner.learner_episode(module.LEARNER, env, config))
        key = jax.random.PRNGKey(0)
        episode, talks = compiled(episode, key, env.default_params)
        res = episode(key, env.default_params)
        out[f"{name}_loss"] = np.asarray(res.metrics.loss)
        out[f"{name}_score"] = np.asarray(res.episode.score)
        out[f"{name}_r_gt"] = np.asarray(res.episode.r_gt)
        leaves = jax.tree_util.tree_leaves(res.policy)
        out[f"{name}_policy"] = np.concatenate([np.ravel(np.asarray(x)) for x in leaves])
        info[name] = {"communicates": talks}


def main(path: str) -> None:
    out, info = {}, {"device_count": jax.device_count()}
    env = cloth()
    env_job(env, 8, out, info, "env")
    env_job(env, 6, out, info, "env6", rollout=False)
    cem_job(env, out, info)
    rl_job(out, info)
    np.savez(path + ".npz", **out)
    with open(path + ".json", "w") as f:
        json.dump(info, f, indent=1)


if __name__ == "__main__":
    main(sys.argv[1])
