"""``make(name, resolution="reference")``: every task at the original benchmark's particle or
vertex count and substeps per step, built and stepped (a cheap task), and bad values refused."""

import jax
import numpy as np
import pytest
from benchmarks.tasks import DAXBENCH

import dax_tasks
from dax_tasks.core.registry import env_class


@pytest.mark.parametrize("name", dax_tasks.TASKS)
def test_reference_spec_matches_the_original_benchmark(name):
    ref = DAXBENCH[name]
    spec = dax_tasks.get_spec(name, "reference")
    default = dax_tasks.get_spec(name)
    assert spec.name == name and spec.horizon == default.horizon
    env = env_class(name)(spec)  # the scene is built (and its time step checked), no goal
    points = env.n_object_points
    assert abs(points - ref["object_points"]) <= 0.12 * ref["object_points"], (
        f"{name}: expected about {ref['object_points']} object points, got {points}")
    if name == "pour_water":  # its 23 substeps would be unstable here: the default's stay
        assert spec.substeps == default.substeps == 30
    elif name != "pour_soup":  # a finer grid needs more substeps of a smaller dt
        assert spec.substeps == ref["substeps"], (
            f"{name}: expected {ref['substeps']} substeps per step, got {spec.substeps}")


def test_reference_fold_cloth1_builds_and_steps():
    env = dax_tasks.make("fold_cloth1", resolution="reference", cache_goal=False, horizon=1)
    assert env.spec.substeps == 2000 and env.spec.horizon == 1  # overrides apply on top
    assert env.n_object_points == 529 and env.goal.shape == (529, 3)
    params = env.default_params
    _, state = jax.jit(env.reset)(jax.random.PRNGKey(0), params)
    action = jax.jit(env.expert_action)(state, params)
    _, state, reward, done, info = jax.jit(env.step)(state, action, params)
    x = np.asarray(state.physics.x)
    assert x.shape == (529, 3) and np.all(np.isfinite(x)), "expected a finite 529-vertex cloth"
    assert bool(done) and bool(info["finite"])
    # the expert's diagonal fold brings the cloth much closer to the folded goal than the
    # flat start is (flat: about 0.09 m at the default resolution)
    assert float(info["distance"]) < 0.05, f"expected a fold, got D = {info['distance']}"
    np.testing.assert_allclose(float(env.dt), 0.5, rtol=1e-6)


def test_unknown_resolution_lists_the_valid_ones():
    with pytest.raises(ValueError, match="default, reference"):
        dax_tasks.make("fold_cloth1", resolution="fine")
    with pytest.raises(ValueError, match="default, reference"):
        dax_tasks.get_spec("fold_cloth1", "coarse")
