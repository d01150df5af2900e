"""Distances and rewards (pure JAX, no physics)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dax_tasks import auxiliary_reward, chamfer, ground_truth_reward, l2_correspondence


def test_l2_correspondence_is_mean_distance_of_matching_indices():
    x = jnp.zeros((4, 3))
    g = x.at[:, 0].set(jnp.asarray([1.0, 2.0, 3.0, 4.0]))
    got = float(l2_correspondence(x, g))
    assert got == pytest.approx(2.5, rel=1e-5), f"expected 2.5 m, got {got}"


def test_l2_correspondence_refuses_unequal_shapes():
    with pytest.raises(ValueError, match="equal shapes"):
        l2_correspondence(jnp.zeros((3, 3)), jnp.zeros((4, 3)))


def test_chamfer_ignores_order_and_matches_hand_value():
    g = jnp.asarray([[0.0, 0, 0], [1.0, 0, 0]])
    assert float(chamfer(g[::-1], g)) == pytest.approx(0.0, abs=1e-5)
    x = jnp.asarray([[0.0, 0.5, 0]])
    # x -> g: 0.5; g -> x: (0.5 + sqrt(1.25)) / 2
    want = 0.5 * (0.5 + 0.5 * (0.5 + np.sqrt(1.25)))
    got = float(chamfer(x, g))
    assert got == pytest.approx(want, rel=1e-5), f"expected {want}, got {got}"


def test_rewards_lie_in_unit_interval_and_peak_at_goal():
    assert float(ground_truth_reward(0.0, 20.0)) == 1.0
    r = float(ground_truth_reward(0.05, 20.0))
    assert r == pytest.approx(np.exp(-1.0), rel=1e-6), f"expected exp(-1), got {r}"
    pts = jnp.asarray([[0.0, 0, 0], [2.0, 0, 0]])
    got = float(auxiliary_reward(jnp.asarray([0.0, 0.0, 1.0]), pts))
    assert got == pytest.approx(np.exp(-1.0), rel=1e-5), f"expected exp(-1), got {got}"


def test_distance_gradients_finite_when_points_coincide():
    x = jnp.ones((3, 3))
    for name, f in (("l2", l2_correspondence), ("chamfer", chamfer)):
        g = jax.grad(f)(x, x)
        assert bool(jnp.all(jnp.isfinite(g))), f"{name}: expected finite gradient, got {g}"
