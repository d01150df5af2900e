"""Shared, module-independent fixtures: a small Push-Rope (50 substeps per action, of which
10 lift) so that compiled steps are cheap; each fixture compiles once per session. Also the
determinism check every particle task runs."""

import dataclasses

import jax
import numpy as np
import pytest

import dax_tasks
from dax_tasks import push_rope


def small_overrides(**extra):
    scene = dataclasses.replace(push_rope.PUSH_ROPE.spec.scene, lift_substeps=10)
    return dict(substeps=50, scene=scene, **extra)


@pytest.fixture(scope="session")
def task():
    return dax_tasks.make("push_rope", **small_overrides())


@pytest.fixture(scope="session")
def reset0(task):
    return task.reset(jax.random.PRNGKey(0))


@pytest.fixture(scope="session")
def expert(task):
    return jax.jit(lambda s: push_rope.expert_action(task.spec, s.physics, s.goal))


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
