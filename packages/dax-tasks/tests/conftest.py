"""Shared fixtures: a small Push-Rope (50 substeps per action, of which 10 lift) so that
compiled steps are cheap; each fixture compiles once per session. ``Jitted`` gives a pure
env jitted ``reset``/``step``/``expert_action`` for eager test code. Also the determinism
check every particle task runs. Same seed, same bits on a GPU too: XLA is asked for
scatter-adds in a fixed order before JAX starts (CPU ignores it)."""

import dataclasses

import jax
import numpy as np
import pytest

import dax_tasks
from dax_physics.precision import deterministic_gpu_ops
from dax_tasks.core.wrappers import VmapWrapper
from dax_tasks.tasks import push_rope

deterministic_gpu_ops()


def small_overrides(**extra):
    scene = dataclasses.replace(push_rope.PUSH_ROPE.scene, lift_substeps=10)
    return dict(substeps=50, scene=scene, **extra)


class Jitted:
    """``env``'s pure functions, jitted (params default to the env's), for eager tests;
    ``batch_size`` wraps the env in a :class:`VmapWrapper` first."""

    def __init__(self, env, batch_size=None):
        if batch_size is not None:
            env = VmapWrapper(env, batch_size=batch_size)
        self.env = env
        self.reset = jax.jit(lambda key, params=None: env.reset(key, params))
        self.step = jax.jit(lambda state, action, params=None: env.step(state, action, params))
        self.expert_action = jax.jit(
            lambda state, params=None: env.expert_action(state, params))

    def __getattr__(self, name):
        if name == "env":
            raise AttributeError(name)
        return getattr(self.env, name)


@pytest.fixture(scope="session")
def task():
    return Jitted(dax_tasks.make("push_rope", **small_overrides()))


@pytest.fixture(scope="session")
def reset0(task):
    return task.reset(jax.random.PRNGKey(0))


@pytest.fixture(scope="session")
def expert(task):
    return task.expert_action


def _same_seed_same_trajectory(task, policy, steps=2):
    """Seed 3 twice gives bit-identical observations and rewards over ``steps`` steps of
    ``policy(state)``; seed 4 starts elsewhere."""

    def run(seed):
        obs, s = task.reset(jax.random.PRNGKey(seed))
        out = [obs]
        for _ in range(steps):
            obs, s, r, _, _ = task.step(s, policy(s))
            out += [obs, r]
        return out

    a, b, c = run(3), run(3), run(4)
    for u, v in zip(a, b, strict=True):
        np.testing.assert_array_equal(np.asarray(u), np.asarray(v))
    assert not np.allclose(np.asarray(a[0]), np.asarray(c[0])), "seeds 3 and 4 gave equal obs"


@pytest.fixture(scope="session")
def check_same_seed_same_trajectory():
    """The determinism check as a function ``check(task, policy, steps=2)``."""
    return _same_seed_same_trajectory
