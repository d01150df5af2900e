"""Normalised actions: every method chooses actions in normalised coordinates ``z`` in
``[-1, 1]^d``, the task's action box mapped affinely, so one step size, standard deviation
or ``tanh`` squash fits every task; :func:`to_action` maps ``z`` back to the task's units
(pick-and-place / push coordinates [m], velocities [m/s]).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np


def action_scale(env) -> tuple[jnp.ndarray, jnp.ndarray]:
    """``(mid, half)`` of the env's action box, each ``(d,)`` float32: ``action = mid +
    half * z``."""
    low = np.asarray(env.spec.action_low, np.float32)
    high = np.asarray(env.spec.action_high, np.float32)
    return jnp.asarray(0.5 * (low + high)), jnp.asarray(0.5 * (high - low))


def to_action(env, z):
    """The action ``(..., d)`` [task units] of normalised coordinates ``z`` ``(..., d)``,
    clipped to [-1, 1] first (so the action is always inside the box)."""
    mid, half = action_scale(env)
    return mid + half * jnp.clip(z, -1.0, 1.0)


def to_normalised(env, action):
    """Inverse of :func:`to_action` on the box: ``(action - mid) / half``, 0 along an axis
    where the box has zero width."""
    mid, half = action_scale(env)
    return jnp.where(half > 0, (action - mid) / jnp.where(half > 0, half, 1.0), 0.0)
