"""The MLP policies of PPO, APG, SHAC and ILD: what they see and how they act.

* **Input.** The task's ``state`` observation flattened, plus the fraction of the episode
  elapsed, ``t / horizon`` (:func:`features`): every task has a fixed horizon and is
  scored on its *final* step, so the time left is part of the state (without it the value
  of a state is not defined). :class:`ObsNorm` keeps running mean and variance of these
  features (updated from each batch of collected observations, outside any gradient) and
  normalises them, clipped to ±10.
* **Action.** The network gives the mean (and log std) of a diagonal Gaussian over
  pre-squash actions ``u``; the normalised action is ``z = tanh(u)`` in ``(-1, 1)^d``
  (:mod:`dax_algos.actions` maps it onto the task's box). The deterministic action,
  for evaluation, is ``tanh(mean)`` (:func:`deterministic_act`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp

import dax_tasks

from .checks import check_choice

#: Where an MLP policy sees the scene from (its config's ``frame``): ``table`` (the task's
#: own observation and actions) or ``object`` (:class:`dax_tasks.ObjectFrame`: a macro
#: task's points and actions in the object's own frame, its place and heading on the table
#: factored out).
FRAMES = ("table", "object")


def check_frame(frame: str) -> None:
    """``ValueError`` naming the valid frames unless ``frame`` is one of :data:`FRAMES`."""
    check_choice("frame", frame, FRAMES)


def policy_env(env, config):
    """The env the policy of ``config`` acts in: ``env`` itself, or
    :class:`dax_tasks.ObjectFrame` of it for ``config.frame == "object"`` (a config
    without a ``frame`` field: ``env``)."""
    if getattr(config, "frame", "table") == "object":
        return dax_tasks.ObjectFrame(env)
    return env


def features(obs, t, horizon: int):
    """The policy input ``(feature_dim,)`` float32 of one env: the flattened observation
    and ``t / horizon``."""
    return jnp.concatenate([jnp.ravel(obs).astype(jnp.float32),
                            jnp.reshape(t / horizon, (1,)).astype(jnp.float32)])


def batch_features(obs, t, horizon: int):
    """:func:`features` of a batch of envs: ``(B, ...)`` observations, ``(B,)`` steps."""
    return jax.vmap(lambda o, tt: features(o, tt, horizon))(obs, t)


def feature_dim(env) -> int:
    """The length of :func:`features` for ``env``: its observation's size plus 1."""
    return int(jnp.size(jnp.zeros(env.observation_space.shape))) + 1


class ObsNorm(NamedTuple):
    """Running mean / variance ``(feature_dim,)`` of the policy's input features (Chan et
    al.'s parallel update); ``count`` starts at a tiny value so the first batch sets the
    statistics."""

    mean: jnp.ndarray
    var: jnp.ndarray
    count: jnp.ndarray

    @staticmethod
    def create(dim: int) -> ObsNorm:
        return ObsNorm(jnp.zeros(dim, jnp.float32), jnp.ones(dim, jnp.float32),
                       jnp.asarray(1e-4, jnp.float32))

    def update(self, x) -> ObsNorm:
        """The statistics with the batch ``x`` ``(..., feature_dim)`` added (no gradient
        flows into them)."""
        x = jax.lax.stop_gradient(jnp.reshape(x, (-1, self.mean.shape[0])))
        n = jnp.asarray(x.shape[0], jnp.float32)
        b_mean, b_var = jnp.mean(x, 0), jnp.var(x, 0)
        total = self.count + n
        delta = b_mean - self.mean
        mean = self.mean + delta * n / total
        m2 = self.var * self.count + b_var * n + delta**2 * self.count * n / total
        return ObsNorm(mean, m2 / total, total)

    def __call__(self, x, enabled: bool = True):
        """``x`` normalised and clipped to ±10 (``x`` itself when not ``enabled``)."""
        if not enabled:
            return x
        mean, var = jax.lax.stop_gradient(self.mean), jax.lax.stop_gradient(self.var)
        return jnp.clip((x - mean) / jnp.sqrt(var + 1e-8), -10.0, 10.0)


def deterministic_act(policy_net, normalize_obs: bool) -> Callable:
    """``act(policy, feats) -> z``: the deterministic normalised action ``tanh(mean)`` of
    the Gaussian policy network ``policy_net`` (:func:`dax_algos.nets.policy_network`) for
    a :class:`dax_algos.learner.Policy` and features ``feats``."""

    def act(policy, feats):
        mean, _ = policy_net.apply(policy.params, policy.obs_norm(feats, normalize_obs))
        return jnp.tanh(mean)

    return act
