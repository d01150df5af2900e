"""Shared, module-independent fixtures: a small Push-Rope (50 substeps per action, of which
10 lift) so that compiled steps are cheap; each fixture compiles once per session."""

import dataclasses

import jax
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
