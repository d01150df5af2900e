"""The RL methods (PPO, APG, SHAC) on the analytic toy task: they learn (≥ 0.9 of the
optimal return, the optimum known in closed form), deterministically for a seed; seeds
vmap; non-finite gradients are counted and their updates skipped; configs are checked."""

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import dax_tasks
from dax_algos import learner, mlp_policy, toy
from dax_algos.rl import apg, ppo, shac, training

CONFIGS = {
    "ppo": (ppo, ppo.PPOConfig(total_env_steps=20_000, num_envs=16, unroll_length=10,
                               discount=0.99, n_eval=20)),
    "apg": (apg, apg.APGConfig(total_env_steps=4_000, learning_rate=1e-3,
                               policy_hidden=(64, 64), n_eval=20)),
    "shac": (shac, shac.SHACConfig(total_env_steps=8_000, window=5, actor_hidden=(64, 64),
                                   critic_hidden=(64, 64), n_eval=20)),
}


@pytest.fixture(scope="module")
def env():
    return toy.point_reach(horizon=10)


@pytest.fixture(scope="module")
def optimum(env):
    keys = jax.random.split(jax.random.fold_in(jax.random.PRNGKey(0), 0), 20)
    return float(np.mean(toy.optimal_return(env, keys)))


@pytest.mark.parametrize("name", list(CONFIGS))
def test_method_learns_the_toy_task_deterministically(env, optimum, name):
    module, config = CONFIGS[name]
    episode = jax.jit(learner.learner_episode(module.LEARNER, env, config))
    out = episode(jax.random.PRNGKey(0), env.default_params)
    ret = float(jnp.sum(out.episode.r_gt))  # mean return of the 20 evaluation rollouts
    assert ret >= 0.9 * optimum, f"{name}: return {ret:.3f}, optimum {optimum:.3f}"
    first = float(np.nanmean(np.asarray(out.metrics.score)[:3]))
    last = float(np.nanmean(np.asarray(out.metrics.score)[-3:]))
    assert last > first + 0.3, f"{name}: the training curve did not rise ({first} -> {last})"
    assert int(np.sum(out.metrics.nonfinite)) == 0
    again = episode(jax.random.PRNGKey(0), env.default_params)
    chex.assert_trees_all_equal(out, again)  # same seed, same numbers


def test_seeds_vmap_and_differ(env):
    module, config = CONFIGS["apg"]
    config = apg.APGConfig(**{**vars(config), "total_env_steps": 400, "n_eval": 2})
    episode = learner.learner_episode(module.LEARNER, env, config)
    keys = jnp.stack([jax.random.PRNGKey(0), jax.random.PRNGKey(1)])
    batched = jax.jit(jax.vmap(episode, in_axes=(0, None)))(keys, env.default_params)
    single = jax.jit(episode)(keys[1], env.default_params)
    np.testing.assert_allclose(np.asarray(batched.metrics.loss[1]),
                               np.asarray(single.metrics.loss), rtol=1e-5)
    assert not np.allclose(np.asarray(batched.metrics.loss[0]),
                           np.asarray(batched.metrics.loss[1]))


@pytest.mark.parametrize("name", ["apg", "shac"])
def test_nonfinite_gradients_are_counted_and_skipped(env, name):
    module, config = CONFIGS[name]
    config = type(config)(**{**vars(config), "total_env_steps": 200})
    train = jax.jit(module.make_train(env, config))
    bad = env.default_params.replace(lam=jnp.nan)  # every reward NaN: every gradient too
    policy, metrics = train(jax.random.PRNGKey(3), bad)
    updates = len(metrics.env_steps)
    assert int(np.sum(metrics.nonfinite)) == updates
    assert not np.any(np.isfinite(np.asarray(metrics.grad_norm)))
    # every update was skipped: the policy is still its initialisation
    net = module.LEARNER.network(env, config)
    k_pi = jax.random.split(jax.random.PRNGKey(3), 4 if name == "shac" else 3)[0]
    init = jax.jit(net.init)(k_pi)  # as inside the jitted train
    chex.assert_trees_all_equal(policy.params, init)
    good_policy, good = train(jax.random.PRNGKey(3), env.default_params)
    assert int(np.sum(good.nonfinite)) == 0


def test_training_reward_has_aux_and_evaluation_does_not(env):
    params = training.training_params(env.default_params, 1.0)
    _, state = env.reset(jax.random.PRNGKey(0), params)
    _, _, reward, _, info = env.step(state, jnp.zeros(3), params)
    assert float(reward) == pytest.approx(float(info["r_gt"] + info["r_aux"]))
    _, _, reward, _, info = env.step(state, jnp.zeros(3), env.default_params)
    assert float(reward) == float(info["r_gt"])


@pytest.mark.parametrize("objective", ["sum", "final"])
def test_apg_objective_is_the_summed_reward_or_the_final_r_gt(env, objective):
    config = apg.APGConfig(num_envs=2, policy_hidden=(8,), objective=objective)
    venv = dax_tasks.training_env(env, 2)
    pnet = apg.network(env, config)
    rollout = apg.make_rollout(env, venv, pnet, config, env.horizon)
    params = training.training_params(env.default_params, config.aux_weight)
    obs, state = venv.reset(jax.random.PRNGKey(0), params)
    norm = mlp_policy.ObsNorm.create(mlp_policy.feature_dim(env))
    value, (_, _, _, reward, done, info) = rollout(
        pnet.init(jax.random.PRNGKey(1)), norm, obs, state, jax.random.PRNGKey(2), params)
    assert bool(jnp.all(done[-1])) and not bool(jnp.any(done[:-1]))
    want = (jnp.mean(jnp.sum(reward, 0)) if objective == "sum"
            else jnp.mean(info["r_gt"][-1]))  # the score: each env's final-step r_gt
    assert float(value) == pytest.approx(float(want), rel=1e-6)


@pytest.mark.parametrize("cls, kwargs, match", [
    (ppo.PPOConfig, dict(num_envs=0), "num_envs"),
    (ppo.PPOConfig, dict(num_envs=5, unroll_length=3, minibatches=4), "minibatches"),
    (ppo.PPOConfig, dict(discount=1.5), "discount"),
    (apg.APGConfig, dict(window=0), "window"),
    (apg.APGConfig, dict(policy_hidden=()), "policy_hidden"),
    (apg.APGConfig, dict(objective="last"), "objective"),
    (shac.SHACConfig, dict(target_alpha=-0.1), "target_alpha"),
    (shac.SHACConfig, dict(actor_learning_rate=float("nan")), "actor_learning_rate"),
    (ppo.PPOConfig, dict(frame="goal"), "unknown frame"),
    (apg.APGConfig, dict(lr_schedule="cosine"), "lr_schedule"),
])
def test_bad_config_is_refused(cls, kwargs, match):
    with pytest.raises(ValueError, match=match):
        cls(**kwargs)



@pytest.mark.parametrize("name", ["apg", "ppo"])
def test_a_policy_in_the_object_frame_records_the_actions_the_task_stepped(name):
    """``frame="object"``: the policy trains and is evaluated through
    :class:`dax_tasks.ObjectFrame`, and the episode the runner records holds the task's own
    (table-frame) actions: replayed on the bare task from the same start they give the
    recorded final r_gt."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    from algos_helpers import cheap_cloth_overrides

    from dax_algos import registry

    env = dax_tasks.make("fold_cloth1", cache_goal=False, **cheap_cloth_overrides(horizon=2))
    tiny = {"apg": dict(total_env_steps=4, num_envs=2, n_eval=2, policy_hidden=(16,)),
            "ppo": dict(total_env_steps=16, num_envs=8, unroll_length=2, minibatches=2,
                        n_eval=2, policy_hidden=(16,), value_hidden=(16,))}[name]
    m = registry.get(name)
    config = m.config("quick", "fold_cloth1", frame="object", **tiny)
    key = jax.random.PRNGKey(3)
    out = jax.jit(learner.learner_episode(m.learner, env, config))(key, env.default_params)
    assert np.isfinite(float(out.episode.score)) and np.isfinite(float(out.untrained_score))
    start = jax.random.split(jax.random.fold_in(key, 0), config.n_eval)[0]
    _, state = env.reset(start)
    for a in out.episode.actions:
        _, state, _, _, info = env.step(state, a)
    # (eager steps against the jitted, batched evaluation: equal up to rounding)
    assert float(info["r_gt"]) == pytest.approx(float(out.episode.actions_score), abs=1e-4)
    in_frame = m.config("quick", "fold_cloth1", **tiny)
    plain = jax.jit(learner.learner_episode(m.learner, env, in_frame))(key, env.default_params)
    assert not np.allclose(np.asarray(plain.episode.actions), np.asarray(out.episode.actions))


def test_a_linear_learning_rate_schedule_decays_the_step_to_zero():
    from dax_algos.optim import make_optimiser

    opt = make_optimiser(0.5, None, optimiser="sgd", lr_schedule="linear", steps=4)
    x, g = jnp.zeros(2), jnp.ones(2)
    state, steps = opt.init(x), []
    for _ in range(5):
        u, state = opt.update(g, state, x)
        steps.append(float(-u[0]))
    np.testing.assert_allclose(steps, [0.5, 0.375, 0.25, 0.125, 0.0], atol=1e-7)
    with pytest.raises(ValueError, match="optimiser steps"):
        make_optimiser(0.5, None, lr_schedule="linear")

