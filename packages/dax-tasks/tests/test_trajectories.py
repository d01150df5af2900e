"""The nine tasks reproduce their recorded trajectories (fixtures/trajectories, written by
fixtures/record_trajectories.py): the goal, every observation, action, reward, info value
and the final physics state of two scripted-expert steps on small scenes. A task's file is
re-recorded only when a deliberate change to the physics or the task moves its numbers,
and the commit that does so says why and by how much (``git log`` of the fixtures).

Bit for bit on the machine class that recorded them (the CPU's instruction-set features,
jax and jaxlib: ``record_trajectories.machine_class``, stored with each file). On another
class XLA compiles for another instruction set, which rounds some sums differently, so the
floats are compared within tolerances measured by recording under
``XLA_FLAGS=--xla_cpu_max_isa=AVX2`` (and ``AVX``) on an AVX-512 machine: the MPM tasks
then agreed within 128 float32 spacings of each array's largest magnitude (``ULPS`` allows
512); the cloth tasks' stick-slip contact amplifies a rounding difference over a
pick-and-place (Unfold-Cloth-3 ended 5.5 cm and 0.5 m/s apart after two steps, its
simulated start already 2.8 mm), so there only rewards (within ``CLOTH_REWARD``) and
positions (within ``CLOTH_POSITION`` metres) are compared, velocities not. Integers and
flags match exactly everywhere.

The trajectories are run with the default params closed over. Run with the params passed
as data (as a learner does), the physics is identical to that on the same machine;
``r_gt = exp(-λ D)`` may differ by an ulp, because XLA folds a constant λ into the
exponential. The first step's action gradient is compared on the cloth tasks on the
recording machine class (to float32 round-off: the reverse pass reassociates sums); the
MPM tasks' gradients are checked against finite differences in their own test files.
"""

import json
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

import dax_tasks

sys.path.insert(0, str(Path(__file__).parent / "fixtures"))
import record_trajectories as rt  # noqa: E402

CLOTH = {"fold_cloth1", "fold_cloth3", "fold_tshirt", "unfold_cloth1", "unfold_cloth3"}
#: On another machine class: MPM floats agree to this many float32 spacings of each
#: array's largest magnitude; cloth rewards to within CLOTH_REWARD and positions (goal,
#: observations, vertices) to within CLOTH_POSITION metres (see the module docstring).
ULPS = 512
CLOTH_REWARD = 0.05
CLOTH_POSITION = 0.1


def _fixture(name):
    with np.load(rt.HERE / f"{name}.npz") as data:
        return {k: data[k] for k in data.files}


@pytest.mark.skipif(jax.default_backend() != "cpu", reason=(
    "the trajectories were recorded on CPU; another backend rounds differently (on an H100 "
    "the cloth goals, simulated folds through self-collision, differ by up to 4 mm)"))
@pytest.mark.parametrize("name", dax_tasks.TASKS)
def test_trajectory_reproduces_the_recorded_one(name):
    want = _fixture(name)
    env = dax_tasks.make(name, cache_goal=False, **rt.small_overrides(name))
    same_class = json.loads(str(want["machine_class"])) == rt.machine_class()
    _assert_recorded(np.asarray(env.goal), want["goal"], same_class, name, "goal")
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
        _assert_recorded(np.asarray(value), want[key], same_class, name, key)

    # params as data: the same physics as the closed-over program on this machine; r_gt
    # to within round-off (XLA folds a constant lambda into the exponential)
    params = env.default_params
    _, s1, reward, _, info = jax.jit(env.step)(start, want["action_0"], params)
    _, c1, closed_reward, _, _ = step(start, want["action_0"])
    np.testing.assert_array_equal(np.asarray(s1.physics.x), np.asarray(c1.physics.x),
                                  err_msg=f"{name}: physics, params as data")
    np.testing.assert_allclose(float(reward), float(closed_reward), rtol=3e-7,
                               err_msg=f"{name}: reward, params as data")
    if name in CLOTH and same_class:  # elsewhere the contact's rounding moves it further
        grad = jax.jit(jax.grad(lambda a, s, p: env.step(s, a, p)[2]))(
            want["action_0"], start, params)
        scale = float(np.max(np.abs(want["grad_0"])))
        np.testing.assert_allclose(np.asarray(grad), want["grad_0"], rtol=1e-4,
                                   atol=1e-5 * scale, err_msg=f"{name}: first-step gradient")


def _cloth_tolerance(key: str) -> float | None:
    """The absolute tolerance of a cloth task's recorded array on another machine class
    (``None``: not compared there)."""
    if key.startswith(("reward_", "info_r_gt_", "info_r_aux_")):
        return CLOTH_REWARD
    if key in ("goal", "physics.x", "physics.gripper_pos") or key.startswith(
            ("obs_", "info_distance_", "action_")):
        return CLOTH_POSITION
    return None


def _assert_recorded(got, want, same_class: bool, name: str, key: str) -> None:
    """``got`` equals the recorded ``want``: bit for bit on the recording machine class;
    elsewhere integers and flags exactly, floats within the tolerances of the module
    docstring."""
    what = f"{name}: {key}"
    if same_class or not np.issubdtype(want.dtype, np.floating):
        np.testing.assert_array_equal(got, want, err_msg=what)
        return
    if name in CLOTH:
        atol = _cloth_tolerance(key)
        if atol is None:
            return
        note = f"cloth on another machine class: within {atol}"
    else:
        scale = float(np.max(np.abs(want))) if want.size else 0.0
        atol = ULPS * float(np.spacing(np.float32(scale)))
        note = f"another machine class: within {ULPS} float32 spacings of {scale:.3g}"
    np.testing.assert_allclose(got, want, rtol=0, atol=atol, err_msg=f"{what} ({note})")
