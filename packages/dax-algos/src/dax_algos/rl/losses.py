"""The RL methods' objectives as pure functions of arrays (no networks, no simulator), so
each is tested on its own against values computed by hand (``tests/test_losses.py``).

Shapes: ``(T, B)`` is a batch of ``T`` steps of ``B`` envs, time first. ``done`` marks the
last step of an episode; the tasks end at their horizon, which is terminal, so nothing is
bootstrapped past a ``done``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def td_lambda(rewards, values, done, last_value, discount: float, lam: float):
    """TD(λ) returns ``(T, B)``: ``G_t = r_t + γ (1 - d_t) [(1 - λ) V(s_{t+1}) + λ
    G_{t+1}]`` with ``G_T = V(s_T)`` (``last_value``, ``(B,)``) and ``V(s_{t+1})`` the
    next row of ``values`` ``(T, B)`` (``last_value`` after the last). PPO's value targets
    and SHAC's critic targets (from the target critic's values)."""
    done = done.astype(jnp.float32)
    next_values = jnp.concatenate([values[1:], last_value[None]], axis=0)

    def body(g_next, x):
        r, v_next, d = x
        g = r + discount * (1.0 - d) * ((1.0 - lam) * v_next + lam * g_next)
        return g, g

    _, returns = jax.lax.scan(body, last_value, (rewards, next_values, done), reverse=True)
    return returns


def gae(rewards, values, done, last_value, discount: float, lam: float):
    """``(advantages, returns)``, each ``(T, B)``: the TD(λ) returns (:func:`td_lambda`)
    and GAE(γ, λ) advantages, ``returns - values``."""
    returns = td_lambda(rewards, values, done, last_value, discount, lam)
    return returns - values, returns


def ppo_loss(log_prob, old_log_prob, advantages, values, targets, entropy, clip: float,
             value_cost: float, entropy_cost: float):
    """PPO's minibatch loss (a scalar) over ``(N,)`` samples: ``-mean(min(ρ Â, clip(ρ, 1 -
    ε, 1 + ε) Â)) + value_cost · 0.5 mean((v - target)²) - entropy_cost · mean(entropy)``
    with ``ρ = exp(log_prob - old_log_prob)``, ``ε = clip`` and ``Â`` the advantages
    normalised over the minibatch (zero mean, unit standard deviation, +1e-8 in the
    denominator); ``entropy`` is the policy's, per sample or one scalar."""
    ratio = jnp.exp(log_prob - old_log_prob)
    adv = (advantages - jnp.mean(advantages)) / (jnp.std(advantages) + 1e-8)
    surrogate = jnp.minimum(ratio * adv, jnp.clip(ratio, 1 - clip, 1 + clip) * adv)
    policy_loss = -jnp.mean(surrogate)
    value_loss = 0.5 * jnp.mean((values - targets) ** 2)
    return policy_loss + value_cost * value_loss - entropy_cost * jnp.mean(entropy)


def apg_return(rewards):
    """APG's objective: the mean over envs of the window's summed rewards, ``(T, B) ->
    ()`` (its loss is the negative)."""
    return jnp.mean(jnp.sum(rewards, 0))


def shac_actor_objective(rewards, done, tail_value, discount: float):
    """SHAC's truncated actor objective over a window of ``(T, B)`` steps (a scalar):

        sum over envs and episodes-in-window of  sum_k γ^k r_k  [+ γ^K V(s_T)]

    divided by ``T * B``, each episode's discount restarting at its first step in the
    window; the critic's value of the state after the window, ``tail_value`` ``(B,)``,
    discounted by ``γ^K`` (``K``: the steps of the env's last episode in the window), is
    added for an env whose episode has not ended at the window's last step."""
    def step(carry, x):
        acc, disc, total = carry
        reward, d = x
        acc = acc + disc * reward
        total = total + jnp.where(d, acc, 0.0)
        acc = jnp.where(d, 0.0, acc)
        disc = jnp.where(d, 1.0, disc * discount)
        return (acc, disc, total), None

    zeros = jnp.zeros(rewards.shape[1], jnp.float32)
    (acc, disc, total), _ = jax.lax.scan(step, (zeros, jnp.ones_like(zeros), zeros),
                                         (rewards, done))
    total = total + jnp.where(done[-1], 0.0, acc + disc * tail_value)
    return jnp.sum(total) / (rewards.shape[0] * rewards.shape[1])


def critic_loss(values, targets):
    """SHAC's critic regression: ``mean((values - targets)²)``."""
    return jnp.mean((values - targets) ** 2)
