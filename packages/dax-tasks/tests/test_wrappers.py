"""The wrappers, each on its own and composed: VmapWrapper (keys and params), AutoReset,
EpisodeStatistics, and the training stack running many episodes in one jitted scan without
recompiling when params change.

A coarse Fold-Cloth-1 (4 x 4 vertices, 12 substeps per action) keeps each step cheap; the
physics is the real cloth task's."""

import dataclasses

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import dax_tasks
from dax_tasks.core.wrappers import AutoReset, EpisodeStatistics, VmapWrapper, training_env


@pytest.fixture(scope="module")
def env():
    scene = dataclasses.replace(dax_tasks.get_spec("fold_cloth1").scene, n=4,
                                settle_substeps=6)
    return dax_tasks.make("fold_cloth1", scene=scene, substeps=12, cache_goal=False)


def _random_actions(env, key, batch):
    low = jnp.asarray(env.spec.action_low)
    high = jnp.asarray(env.spec.action_high)
    return jax.random.uniform(key, (batch, env.spec.action_dim), minval=low, maxval=high)


def test_vmap_over_keys_equals_single_envs(env):
    batch = VmapWrapper(env, batch_size=3)
    keys = jax.random.split(jax.random.PRNGKey(4), 3)
    obs, states = jax.jit(batch.reset)(keys)
    actions = _random_actions(env, jax.random.PRNGKey(5), 3)
    _, new, reward, done, _ = jax.jit(batch.step)(states, actions)
    assert obs.shape == (3, *env.observation_space.shape) and reward.shape == (3,)
    for i in range(3):
        o1, s1 = jax.jit(env.reset)(keys[i])
        np.testing.assert_array_equal(np.asarray(obs[i]), np.asarray(o1))
        _, n1, r1, _, _ = jax.jit(env.step)(s1, actions[i])
        np.testing.assert_allclose(np.asarray(new.physics.x[i]), np.asarray(n1.physics.x),
                                   atol=1e-6, err_msg=f"env {i}")
        assert float(reward[i]) == pytest.approx(float(r1), abs=1e-6)
    with pytest.raises(ValueError, match=r"shape \(3, 6\)"):
        batch.step(states, actions[:2])


def test_vmap_over_params_is_domain_randomisation(env):
    """Each env of the batch runs with its own λ and table friction; each equals the
    unbatched env with those params."""
    batch = VmapWrapper(env, batch_size=2, batch_params=True)
    params = batch.default_params
    assert params.lam.shape == (2,) and params.physics.friction_static.shape == (2,)
    params = params.replace(lam=jnp.asarray([10.0, 3.0]), physics=params.physics.replace(
        friction_static=jnp.asarray([1.0, 0.1]), friction_dynamic=jnp.asarray([0.8, 0.05])))
    key = jax.random.PRNGKey(0)
    _, states = jax.jit(batch.reset)(jnp.stack([key, key]), params)
    actions = jnp.stack([jnp.asarray([0.1, 0.1, 0.0, -0.1, -0.1, 0.0])] * 2)
    _, new, reward, _, info = jax.jit(batch.step)(states, actions, params)
    for i in range(2):
        p = jax.tree_util.tree_map(lambda a, i=i: a[i], params)
        _, s1 = jax.jit(env.reset)(key, p)
        _, n1, r1, _, _ = jax.jit(env.step)(s1, actions[i], p)
        np.testing.assert_allclose(np.asarray(new.physics.x[i]), np.asarray(n1.physics.x),
                                   atol=1e-6)
        assert float(reward[i]) == pytest.approx(float(r1), rel=1e-5)
    d = np.asarray(info["distance"])
    np.testing.assert_allclose(np.asarray(reward), np.exp(-np.asarray([10.0, 3.0]) * d),
                               rtol=1e-5)
    moved = float(jnp.max(jnp.abs(new.physics.x[0] - new.physics.x[1])))
    assert moved > 1e-4, f"the friction per env made no difference ({moved} m)"


def test_auto_reset_restarts_inside_the_step_with_a_fresh_start(env):
    wrapped = AutoReset(env)
    reset, step = jax.jit(wrapped.reset), jax.jit(wrapped.step)
    obs0, state = reset(jax.random.PRNGKey(1))
    np.testing.assert_array_equal(np.asarray(obs0), np.asarray(
        jax.jit(env.reset)(jax.random.PRNGKey(1))[0]), err_msg="first episode changed")
    action = jnp.asarray(env.spec.action_low)
    for t in range(env.horizon):
        obs, state, reward, done, info = step(state, action)
        assert bool(done) == (t + 1 == env.horizon), t
        assert int(info["t"]) == t + 1 and np.isfinite(float(reward))
    # the step that ended the episode returns the new episode's state and observation
    assert int(state.t) == 0 and bool(state.finite)
    np.testing.assert_array_equal(np.asarray(obs), np.asarray(env.observe(state.physics)))
    assert not np.allclose(np.asarray(obs), np.asarray(obs0)), "restarted at the same start"
    # deterministic: the same key gives the same second episode
    _, again = reset(jax.random.PRNGKey(1))
    for _ in range(env.horizon):
        _, again, *_ = step(again, action)
    np.testing.assert_array_equal(np.asarray(again.physics.x), np.asarray(state.physics.x))


def test_episode_statistics_report_the_finished_episode(env):
    wrapped = EpisodeStatistics(AutoReset(env))
    _, state = jax.jit(wrapped.reset)(jax.random.PRNGKey(2))
    step = jax.jit(wrapped.step)
    rewards = []
    for t in range(env.horizon + 1):
        action = _random_actions(env, jax.random.PRNGKey(10 + t), 1)[0]
        _, state, reward, done, info = step(state, action)
        rewards.append(float(reward))
        if t + 1 == env.horizon:
            assert bool(info["episode_done"])
            assert float(info["episode_return"]) == pytest.approx(sum(rewards), rel=1e-6)
            assert int(info["episode_length"]) == env.horizon
            assert float(info["episode_final_r_gt"]) == pytest.approx(float(info["r_gt"]))
            final = float(info["episode_return"])
        elif t < env.horizon:
            assert not bool(info["episode_done"]) and float(info["episode_return"]) == 0.0
    # one step into the next episode: the last finished episode is still reported
    assert float(info["episode_return"]) == pytest.approx(final)
    assert float(state.extras["episode"]["return"]) == pytest.approx(rewards[-1])


def test_64_auto_resetting_envs_run_1000_steps_in_one_scan_without_recompiling(env):
    """The training stack (vmap of episode statistics of auto-reset) over 64 envs, 1000
    steps in one jitted lax.scan; changing λ or a friction coefficient in the params
    reuses the compiled program (chex counts the traces)."""
    batch, n_steps = 64, 1000
    stack = training_env(env, batch_size=batch)

    @jax.jit
    @chex.assert_max_traces(n=1)
    def rollout(key, params):
        _, state = stack.reset(key, params)

        def body(state, k):
            _, state, reward, done, info = stack.step(
                state, _random_actions(env, k, batch), params)
            return state, (reward, done, info["episode_return"], info["episode_length"],
                           state.t)

        return jax.lax.scan(body, state, jax.random.split(key, n_steps))

    params = env.default_params
    state, (reward, done, ret, length, t) = rollout(jax.random.PRNGKey(0), params)
    done, length, t = np.asarray(done), np.asarray(length), np.asarray(t)
    episodes = n_steps // env.horizon
    assert done.shape == (n_steps, batch)
    assert np.all(done.sum(0) == episodes), f"expected {episodes} episodes per env"
    assert t.max() < env.horizon and np.all(length[done] == env.horizon)
    last = slice((episodes - 1) * env.horizon, episodes * env.horizon)
    np.testing.assert_allclose(np.asarray(ret)[-1], np.asarray(reward)[last].sum(0),
                               rtol=1e-5, err_msg="the last episode's return")
    assert bool(jnp.all(state.finite)), "a state went non-finite"
    # other numbers, same program: no retrace (assert_max_traces would raise)
    other = params.replace(lam=3.0, physics=params.physics.replace(friction_static=0.2))
    _, (reward2, *_) = rollout(jax.random.PRNGKey(0), other)
    assert not np.allclose(np.asarray(reward2), np.asarray(reward)), "params had no effect"


def test_object_frame_factors_out_the_start_pose(env):
    """Two starts of the cloth differ by a rigid motion in the table plane: seen through
    ObjectFrame their points are the same, one action given in the object frame is moved
    onto each cloth (``info["world_action"]``, what the task steps) and leaves the two
    cloths in the same shape (the same r_gt), and the task stepped with that world action
    gives the same state."""
    from dax_tasks.core.wrappers import ObjectFrame

    frame = ObjectFrame(env)
    assert frame.observation_space.shape == env.observation_space.shape
    (o1, s1), (o2, s2) = (jax.jit(frame.reset)(jax.random.PRNGKey(k)) for k in (1, 2))
    x1, x2 = (env.object_points(s.physics) for s in (s1, s2))
    assert float(jnp.max(jnp.abs(x1[:, :2] - x2[:, :2]))) > 0.02, "the starts coincide"
    n = x1.shape[0] * 3
    np.testing.assert_allclose(np.asarray(o1[:n]), np.asarray(o2[:n]), atol=1e-5)
    # pick the corner at the goal's vertex 0 and lay it 6 cm inwards, in the object frame
    p = np.asarray(o1[:n]).reshape(-1, 3)
    a = jnp.asarray([*p[0, :2], 0.0, *(0.94 * p[0, :2]), 0.02], jnp.float32)
    step = jax.jit(frame.step)
    (n1, t1, _, _, i1), (n2, _, _, _, i2) = step(s1, a), step(s2, a)
    assert not np.allclose(np.asarray(i1["world_action"]), np.asarray(i2["world_action"]))
    np.testing.assert_allclose(float(i1["r_gt"]), float(i2["r_gt"]), atol=2e-3)
    np.testing.assert_allclose(np.asarray(n1[:n]), np.asarray(n2[:n]), atol=2e-3)
    _, direct, _, _, info = jax.jit(env.step)(s1, i1["world_action"])
    np.testing.assert_array_equal(np.asarray(direct.physics.x), np.asarray(t1.physics.x))
    assert float(info["r_gt"]) == float(i1["r_gt"])
    with pytest.raises(ValueError, match="macro-action task"):
        ObjectFrame(dax_tasks.make("whip_rope", cache_goal=False))
