"""Gymnasium adapters: importing dax_tasks.gym (or naming it as an id's module prefix)
registers the nine ids, check_env passes, vector env shapes, bad actions are refused with a
clear error and out-of-bound actions are clipped."""

import subprocess
import sys
import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import dax_tasks
from dax_tasks.gym import GYM_IDS


def test_all_nine_ids_registered():
    assert set(GYM_IDS) == set(dax_tasks.TASKS)
    for env_id in GYM_IDS.values():
        assert env_id in gym.registry, env_id


# all nine ids, and the image observation modes
@pytest.mark.parametrize("env_id, kwargs", [(i, {}) for i in GYM_IDS.values()] + [
    ("dax/FoldCloth1-v0", {"obs_mode": "rgb", "image_size": 32}),
    ("dax/UnfoldCloth3-v0", {"obs_mode": "height", "image_size": 32}),
    ("dax/FoldTShirt-v0", {"obs_mode": "rgbd", "image_size": 32})])
def test_check_env_passes(env_id, kwargs):
    env = gym.make(env_id, render_mode="rgb_array", **kwargs)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*infinity.*")  # positions are unbounded
        # a recommendation for RL libraries: our bounds are in physical units (m/s, m)
        warnings.filterwarnings("ignore", message=".*symmetric and normalized.*")
        check_env(env.unwrapped, skip_render_check=False)


@pytest.fixture(scope="module")
def env():
    return gym.make("dax/FoldCloth1-v0", render_mode="rgb_array")


def test_reset_is_deterministic_and_episode_truncates_at_horizon(env):
    o1, _ = env.reset(seed=5)
    o2, _ = env.reset(seed=5)
    o3, _ = env.reset(seed=6)
    np.testing.assert_array_equal(o1, o2)
    assert not np.array_equal(o1, o3)
    assert o1.dtype == np.float32 and env.observation_space.shape == o1.shape
    horizon = env.unwrapped.task.horizon
    for t in range(horizon):
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        assert 0.0 <= reward <= 1.0 and not terminated
        assert truncated == (t + 1 == horizon)
        assert float(info["r_gt"]) == pytest.approx(reward)


def test_bad_actions_are_refused_with_a_clear_error(env):
    env.reset(seed=0)
    with pytest.raises(ValueError, match="NaN or inf"):
        env.step(np.array([0.0, 0.0, np.nan, 0.0, 0.0, 0.0]))
    with pytest.raises(ValueError, match=r"shape \(6,\), got \(4,\)"):
        env.step(np.zeros(4))
    with pytest.raises(ValueError, match="not an array of numbers"):
        env.step(["a"] * 6)


def test_out_of_bound_actions_are_clipped_like_the_task(env):
    space = env.action_space
    env.reset(seed=1)
    far = space.high + 1.0
    o_far, r_far, *_, info = env.step(far)
    assert bool(info["clipped"])
    env.reset(seed=1)
    o_edge, r_edge, *_, info = env.step(space.high)
    assert not bool(info["clipped"])
    np.testing.assert_array_equal(o_far, o_edge)
    assert r_far == r_edge


def test_render_gives_an_rgb_frame(env):
    env.reset(seed=0)
    frame = env.render()
    assert frame.shape == (256, 256, 3) and frame.dtype == np.uint8


def test_vector_env_steps_the_batch_and_autoresets():
    venv = gym.make_vec("dax/FoldCloth1-v0", num_envs=3,
                        vectorization_mode="vector_entry_point")
    obs, _ = venv.reset(seed=2)
    assert obs.shape == (3, *venv.single_observation_space.shape)
    horizon = venv.unwrapped.task.horizon
    truncs = []
    for _ in range(horizon):
        obs, reward, terminated, truncated, info = venv.step(venv.action_space.sample())
        assert reward.shape == (3,) and not terminated.any()
        assert np.all((reward >= 0) & (reward <= 1))
        truncs.append(truncated.copy())
    assert truncs[-1].all() and not any(t.any() for t in truncs[:-1])
    obs2, reward, _, truncated, _ = venv.step(venv.action_space.sample())  # the reset step
    assert not truncated.any() and np.all(reward == 0)
    with pytest.raises(ValueError, match=r"shape \(3, 6\)"):
        venv.step(np.zeros((2, 6)))


def test_make_kwargs_pass_through_to_dax_tasks_make():
    env = gym.make("dax/FoldCloth1-v0", seed=3, horizon=2, aux_weight=1.0)
    task = env.unwrapped.task
    assert env.unwrapped.seed == 3 and task.spec.horizon == 2
    assert float(task.default_params.aux_weight) == 1.0
    with pytest.raises(ValueError, match="unknown override"):
        gym.make("dax/FoldCloth1-v0", horizon_steps=2)
    first = [gym.make("dax/FoldCloth1-v0", seed=s).reset()[0] for s in (3, 3, 4)]
    np.testing.assert_array_equal(first[0], first[1])  # make's seed drives the first reset
    assert not np.array_equal(first[0], first[2])


def test_importing_dax_tasks_registers_no_gymnasium_id():
    code = ("import sys, dax_tasks; assert 'gymnasium' not in sys.modules, 'imported'; "
            "import gymnasium; print('dax/PushRope-v0' in gymnasium.registry)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "False", out.stdout


def test_the_module_prefix_of_an_id_imports_dax_tasks_gym_in_a_fresh_process():
    """Gymnasium's documented ``"module:id"`` form: nothing imported first."""
    code = ("import gymnasium\n"
            "env = gymnasium.make('dax_tasks.gym:dax/FoldCloth1-v0', seed=1)\n"
            "obs, _ = env.reset()\n"
            "print(env.spec.id, env.spec.entry_point, obs.shape)\n"
            "venv = gymnasium.make_vec('dax_tasks.gym:dax/FoldCloth1-v0', num_envs=2,\n"
            "                          vectorization_mode='vector_entry_point')\n"
            "print(venv.reset(seed=0)[0].shape)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    single, batch = out.stdout.strip().splitlines()
    assert single == "dax/FoldCloth1-v0 dax_tasks.gym:DaxEnv (366,)", single
    assert batch == "(2, 366)", batch
