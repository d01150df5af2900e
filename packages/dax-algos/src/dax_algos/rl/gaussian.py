"""The diagonal Gaussian over pre-squash actions that the stochastic RL policies sample
(PPO, SHAC; :class:`dax_algos.nets.GaussianPolicy` gives its mean and log standard
deviation)."""

from __future__ import annotations

import jax.numpy as jnp

LOG_2PI = float(jnp.log(2.0 * jnp.pi))


def log_prob(u, mean, log_std):
    """``log N(u; mean, exp(log_std)^2)`` summed over the last (action) axis: ``(...,
    d) -> (...)``."""
    return jnp.sum(-0.5 * ((u - mean) / jnp.exp(log_std)) ** 2 - log_std - 0.5 * LOG_2PI,
                   axis=-1)


def entropy(log_std):
    """The Gaussian's differential entropy [nats], summed over the last axis: ``(..., d)
    -> (...)``."""
    return jnp.sum(log_std + 0.5 * (1.0 + LOG_2PI), axis=-1)
