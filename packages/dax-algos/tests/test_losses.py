"""The RL objectives (:mod:`dax_algos.rl.losses`) and the Gaussian policy's maths on
examples of 2-3 steps whose values are worked out by hand in the comments: TD(λ) returns
and GAE with an episode ending inside the batch, PPO's clipped surrogate on either side of
the clip, APG's return, SHAC's truncated objective (the discount restarting after an
episode's end, the critic's value added only where the episode goes on) and its gradient."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dax_algos.rl import gaussian, losses

# two envs, three steps (time first); env 0's episode ends at step 1
REWARDS = jnp.asarray([[1.0, 0.0], [2.0, 0.0], [3.0, 1.0]])
VALUES = jnp.asarray([[0.5, 0.0], [1.0, 0.0], [1.5, 0.0]])
DONE = jnp.asarray([[False, False], [True, False], [False, False]])
LAST = jnp.asarray([2.0, 0.0])


def test_td_lambda_by_hand():
    # γ = λ = 0.5, G_t = r_t + γ (1 - d_t) [(1 - λ) V_{t+1} + λ G_{t+1}], G_3 = V_3 = last
    # env 0: G_2 = 3 + 0.5 (0.5·2 + 0.5·2) = 4; G_1 = 2 (done); G_0 = 1 + 0.5 (0.5·1 + 0.5·2)
    #        = 1.75
    # env 1: G_2 = 1; G_1 = 0.5 (0.5·0 + 0.5·1) = 0.25; G_0 = 0.5 (0 + 0.5·0.25) = 0.0625
    g = losses.td_lambda(REWARDS, VALUES, DONE, LAST, 0.5, 0.5)
    np.testing.assert_allclose(g, [[1.75, 0.0625], [2.0, 0.25], [4.0, 1.0]], rtol=1e-6)


@pytest.mark.parametrize("lam, want", [
    (0.0, [1.5, 2.0, 4.0]),  # one-step TD: r_t + γ V_{t+1} (no bootstrap at the done)
    (1.0, [2.0, 2.0, 4.0]),  # Monte Carlo within each episode, V(s_3) after the last step
])
def test_td_lambda_ends_are_one_step_td_and_monte_carlo(lam, want):
    g = losses.td_lambda(REWARDS, VALUES, DONE, LAST, 0.5, lam)
    np.testing.assert_allclose(g[:, 0], want, rtol=1e-6)


def test_gae_is_returns_minus_values():
    adv, ret = losses.gae(REWARDS, VALUES, DONE, LAST, 0.5, 0.5)
    np.testing.assert_allclose(ret[:, 0], [1.75, 2.0, 4.0], rtol=1e-6)
    np.testing.assert_allclose(adv[:, 0], [1.25, 1.0, 2.5], rtol=1e-6)


def test_td_lambda_matches_a_direct_loop_on_random_data():
    rng = np.random.default_rng(0)
    r, v = rng.normal(size=(5, 2)), rng.normal(size=(5, 2))
    done = np.zeros((5, 2), bool)
    done[2, 0] = True
    last = rng.normal(size=2)
    g = np.asarray(losses.td_lambda(jnp.asarray(r), jnp.asarray(v), jnp.asarray(done),
                                    jnp.asarray(last), 0.9, 0.8))
    want = np.zeros((5, 2))
    nxt_g, vals = last.copy(), np.vstack([v[1:], last[None]])
    for t in reversed(range(5)):
        want[t] = r[t] + 0.9 * (1 - done[t]) * (0.2 * vals[t] + 0.8 * nxt_g)
        nxt_g = want[t]
    np.testing.assert_allclose(g, want, rtol=1e-5)


def _ppo(log_prob, advantages, values=(0.0, 0.0), targets=(0.0, 0.0), entropy=0.0,
         value_cost=0.0, entropy_cost=0.0):
    return losses.ppo_loss(jnp.log(jnp.asarray(log_prob)), jnp.zeros(2),
                           jnp.asarray(advantages), jnp.asarray(values), jnp.asarray(targets),
                           jnp.asarray(entropy), 0.2, value_cost, entropy_cost)


def test_ppo_loss_by_hand_with_both_samples_clipped():
    # ratios 1.5 and 0.5, advantages (3, 1) normalised to (1, -1), ε = 0.2:
    # min(1.5·1, 1.2·1) = 1.2 and min(0.5·-1, 0.8·-1) = -0.8: surrogate 0.2, policy loss -0.2;
    # value loss 0.5 mean((1-2)², (2-0)²) = 1.25, times 0.5; entropy 1.5, times 0.1
    loss = _ppo((1.5, 0.5), (3.0, 1.0), values=(1.0, 2.0), targets=(2.0, 0.0),
                entropy=1.5, value_cost=0.5, entropy_cost=0.1)
    assert float(loss) == pytest.approx(-0.2 + 0.5 * 1.25 - 0.1 * 1.5, rel=1e-6)
    # both ratios are clipped: the surrogate passes no gradient to the log-probabilities
    grad = jax.grad(lambda lp: losses.ppo_loss(lp, jnp.zeros(2), jnp.asarray([3.0, 1.0]),
                                               jnp.zeros(2), jnp.zeros(2), 0.0, 0.2, 0.0,
                                               0.0))(jnp.log(jnp.asarray([1.5, 0.5])))
    np.testing.assert_allclose(grad, [0.0, 0.0], atol=1e-7)


def test_ppo_loss_by_hand_with_the_unclipped_ratio_the_smaller():
    # advantages (1, 3) normalised to (-1, 1): min(1.5·-1, 1.2·-1) = -1.5 and
    # min(0.5·1, 0.8·1) = 0.5; the surrogate is the unclipped one: -0.5, loss 0.5
    assert float(_ppo((1.5, 0.5), (1.0, 3.0))) == pytest.approx(0.5, rel=1e-6)
    # its gradient in log ρ_i is -ρ_i Â_i / 2: (0.75, -0.25)
    grad = jax.grad(lambda lp: losses.ppo_loss(lp, jnp.zeros(2), jnp.asarray([1.0, 3.0]),
                                               jnp.zeros(2), jnp.zeros(2), 0.0, 0.2, 0.0,
                                               0.0))(jnp.log(jnp.asarray([1.5, 0.5])))
    np.testing.assert_allclose(grad, [0.75, -0.25], rtol=1e-5)


def test_apg_return_by_hand():
    # the envs' window sums (1 + 3, 2 + 4) = (4, 6), their mean 5; each reward weighs 1/2
    rewards = jnp.asarray([[1.0, 2.0], [3.0, 4.0]])
    assert float(losses.apg_return(rewards)) == 5.0
    np.testing.assert_allclose(jax.grad(losses.apg_return)(rewards), np.full((2, 2), 0.5))


def test_apg_median_clip_caps_each_env_s_action_gradient_at_the_batch_median():
    from dax_algos.rl.apg import median_clipped

    # the rows' cotangents have norms 1, 2, 5 and 100 (and one zero row): median 2, so
    # the 5- and 100-long rows shrink to length 2 along their own direction
    w = jnp.asarray([[1.0, 0.0], [0.0, 2.0], [3.0, 4.0], [60.0, -80.0], [0.0, 0.0]])
    z = jnp.linspace(-0.5, 0.5, 10).reshape(5, 2)
    np.testing.assert_array_equal(median_clipped(z), z)
    grad = jax.grad(lambda z: jnp.sum(w * median_clipped(z)))(z)
    np.testing.assert_allclose(grad, [[1.0, 0.0], [0.0, 2.0], [1.2, 1.6], [1.2, -1.6],
                                      [0.0, 0.0]], rtol=1e-6)


SHAC_REWARDS = jnp.asarray([[1.0, 1.0], [2.0, 1.0], [4.0, 1.0]])
SHAC_DONE = jnp.asarray([[False, False], [True, False], [False, True]])
SHAC_TAIL = jnp.asarray([8.0, 100.0])


def test_shac_actor_objective_by_hand():
    # γ = 0.5. env 0: an episode ends at step 1 (1 + 0.5·2 = 2), the next starts at step 2
    # with the discount restarted (4) and goes on: + γ¹ V(s_3) = 0.5·8: in all 10.
    # env 1: its episode ends at the window's last step: 1 + 0.5 + 0.25 = 1.75, no V.
    # Divided by T·B = 6.
    value = losses.shac_actor_objective(SHAC_REWARDS, SHAC_DONE, SHAC_TAIL, 0.5)
    assert float(value) == pytest.approx((10.0 + 1.75) / 6, rel=1e-6)


def test_shac_actor_objective_gradient_is_the_discounts():
    grad_r, grad_v = jax.grad(losses.shac_actor_objective, argnums=(0, 2))(
        SHAC_REWARDS, SHAC_DONE, SHAC_TAIL, 0.5)
    np.testing.assert_allclose(grad_r, np.asarray([[1.0, 1.0], [0.5, 0.5], [1.0, 0.25]]) / 6,
                               rtol=1e-6)
    np.testing.assert_allclose(grad_v, [0.5 / 6, 0.0], rtol=1e-6)


def test_critic_loss_by_hand():
    assert float(losses.critic_loss(jnp.asarray([1.0, 2.0]), jnp.zeros(2))) == 2.5


def test_gaussian_log_prob_and_entropy_by_hand():
    half_log_2pi = 0.5 * math.log(2 * math.pi)
    # one axis, std 2, half a std from the mean: -0.5 (1/2)² - ln 2 - ½ ln 2π
    lp = gaussian.log_prob(jnp.asarray([1.0]), jnp.asarray([0.0]), jnp.log(jnp.asarray([2.0])))
    assert float(lp) == pytest.approx(-0.125 - math.log(2.0) - half_log_2pi, rel=1e-6)
    # summed over two axes at the mean with unit std
    lp2 = gaussian.log_prob(jnp.zeros(2), jnp.zeros(2), jnp.zeros(2))
    assert float(lp2) == pytest.approx(-2 * half_log_2pi, rel=1e-6)
    assert float(gaussian.entropy(jnp.zeros(2))) == pytest.approx(1 + math.log(2 * math.pi),
                                                                 rel=1e-6)
