"""The nine tasks reproduce, bit for bit, their recorded trajectories (fixtures/trajectories,
written by fixtures/record_trajectories.py): the goal, every observation, action, reward,
info value and the final physics state of two scripted-expert steps on small scenes. They
were first recorded to check the move to the env core; a task's file is re-recorded only
when a deliberate change to the physics or the task moves its numbers, and the commit that
does so says why and by how much (``git log`` of the fixtures).

Run with the default params closed over, the step compiles to the program the old ``Task``
compiled, and everything is identical. Run with the params passed as data (as a learner
does), the physics and observations are still identical; ``r_gt = exp(-λ D)`` may differ
by an ulp, because XLA folds a constant λ into the exponential. The first step's action
gradient is compared on the cloth tasks (float32 round-off: the reverse pass reassociates
sums); the MPM tasks' gradients are checked against finite differences in their own test
files and take 10-25 s each to compile.
"""

import sys
from pathlib import Path

import jax
import numpy as np
import pytest

import dax_tasks

sys.path.insert(0, str(Path(__file__).parent / "fixtures"))
import record_trajectories as rt  # noqa: E402

CLOTH = {"fold_cloth1", "fold_cloth3", "fold_tshirt", "unfold_cloth1", "unfold_cloth3"}


def _fixture(name):
    with np.load(rt.HERE / f"{name}.npz") as data:
        return {k: data[k] for k in data.files}


@pytest.mark.skipif(jax.default_backend() != "cpu", reason=(
    "the trajectories were recorded on CPU; another backend rounds differently (on an H100 "
    "the cloth goals, simulated folds through self-collision, differ by up to 4 mm)"))
@pytest.mark.parametrize("name", dax_tasks.TASKS)
def test_trajectory_is_bit_identical_to_the_recorded_one(name):
    want = _fixture(name)
    env = dax_tasks.make(name, cache_goal=False, **rt.small_overrides(name))
    np.testing.assert_array_equal(env.goal, want["goal"], err_msg=f"{name}: goal")
    # default params closed over: the program the old Task compiled
    obs, state = jax.jit(lambda k: env.reset(k))(jax.random.PRNGKey(rt.SEED))
    step = jax.jit(lambda s, a: env.step(s, a))
    expert = jax.jit(lambda s: env.expert_action(s))
    got = {"obs_0": obs}
    start = state
    for t in range(rt.STEPS):
        got[f"action_{t}"] = action = expert(state)
        obs, state, reward, done, info = step(state, action)
        got.update({f"obs_{t + 1}": obs, f"reward_{t + 1}": reward, f"done_{t + 1}": done})
        got.update({f"info_{k}_{t + 1}": info[k] for k in rt.INFO_KEYS})
    for path, leaf in jax.tree_util.tree_flatten_with_path(state.physics)[0]:
        got["physics" + jax.tree_util.keystr(path)] = leaf
    for key, value in got.items():
        np.testing.assert_array_equal(np.asarray(value), want[key], err_msg=f"{name}: {key}")

    # params as data: the same physics; r_gt to within float32 round-off
    params = env.default_params
    _, s1, reward, _, info = jax.jit(env.step)(start, want["action_0"], params)
    np.testing.assert_array_equal(np.asarray(s1.physics.x), np.asarray(
        step(start, want["action_0"])[1].physics.x), err_msg=f"{name}: physics, params as data")
    np.testing.assert_allclose(float(reward), float(want["reward_1"]), rtol=3e-7,
                               err_msg=f"{name}: reward, params as data")
    if name in CLOTH:
        grad = jax.jit(jax.grad(lambda a, s, p: env.step(s, a, p)[2]))(
            want["action_0"], start, params)
        scale = float(np.max(np.abs(want["grad_0"])))
        np.testing.assert_allclose(np.asarray(grad), want["grad_0"], rtol=1e-4,
                                   atol=1e-5 * scale, err_msg=f"{name}: first-step gradient")
