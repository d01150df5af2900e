"""Eager input checks at the boundary between a user's data and the pure core.

The pure core cannot look at values without a host sync, so it never refuses a NaN: a NaN
action or parameter propagates and turns ``state.finite`` false. Code that holds concrete
values (the Gymnasium adapter, dax-data, a user's loop) calls these first and gets a
``ValueError`` that names the problem: a wrong shape, a NaN/inf, an unknown field, a
parameter that makes the time step unstable.
"""

from __future__ import annotations

import jax
import numpy as np

from .env import EnvParams


def check_action(env, action, batch_shape: tuple = ()) -> np.ndarray:
    """``action`` as a float32 NumPy array of shape ``batch_shape + (action_dim,)``, clipped
    to the spec's bounds; ``ValueError`` naming the task and the problem if it is not real
    numbers, has another shape, or holds NaN/inf. Out-of-bound values are allowed and
    clipped as the env clips them; the check and the clip happen in float64, before the
    cast to float32, so a finite action beyond float32's range (1e39) is clipped, not
    turned into inf."""
    spec = env.spec
    try:
        raw = np.asarray(action)
        if raw.dtype.kind not in "fiu":
            raise TypeError(f"dtype {raw.dtype}")
        a = raw.astype(np.float64)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{spec.name}: action is not an array of numbers (real ones; "
                         f"{err})") from None
    shape = tuple(batch_shape) + (spec.action_dim,)
    if a.shape != shape:
        raise ValueError(f"{spec.name}: expected a {spec.action_kind} action of shape "
                         f"{shape}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{spec.name}: action contains NaN or inf: {a.tolist()}")
    low = np.asarray(spec.action_low, np.float64)
    high = np.asarray(spec.action_high, np.float64)
    return np.clip(a, low, high).astype(np.float32)


def check_key(key, batch_size: int | None = None):
    """A ``PRNGKey`` of shape (2,) (or ``(batch_size, 2)``); ``ValueError`` otherwise."""
    shape = np.shape(key)
    want = (2,) if batch_size is None else (batch_size, 2)
    if shape != want:
        raise ValueError(f"expected a PRNGKey of shape {want}, got {shape}")
    return key


def check_params(env, params: EnvParams) -> EnvParams:
    """``ValueError`` naming the problem if ``params`` cannot drive ``env``: not an
    :class:`EnvParams`, a goal of the wrong shape, a non-finite or non-positive λ, a
    negative or non-finite auxiliary weight, or physics numbers the task refuses (for the
    MPM and cloth tasks: wrong shapes, NaN, non-positive densities or moduli, and any
    value that makes the substep unstable). Returns ``params``."""
    name = env.spec.name
    if not isinstance(params, EnvParams):
        raise ValueError(f"{name}: params must be an EnvParams, got {type(params).__name__}")
    goal = np.asarray(params.goal)
    want = env.default_params.goal.shape
    if goal.shape != want:
        raise ValueError(f"{name}: params.goal must have shape {want}, got {goal.shape}")
    if not np.all(np.isfinite(goal)):
        raise ValueError(f"{name}: params.goal contains NaN or inf")
    lam = np.asarray(params.lam)
    if lam.shape != () or not (np.isfinite(lam) and lam > 0):
        raise ValueError(f"{name}: params.lam must be a positive number in 1/m, got "
                         f"{lam.tolist()}")
    aux = np.asarray(params.aux_weight)
    if aux.shape != () or not (np.isfinite(aux) and aux >= 0):
        raise ValueError(f"{name}: params.aux_weight must be a number >= 0, got "
                         f"{aux.tolist()}")
    default = jax.tree_util.tree_structure(env.default_params.physics)
    if jax.tree_util.tree_structure(params.physics) != default:
        raise ValueError(f"{name}: params.physics must have the structure of "
                         f"env.default_params.physics ({default}), got "
                         f"{jax.tree_util.tree_structure(params.physics)}")
    try:
        env.check_physics_params(params.physics)
    except ValueError as err:
        raise ValueError(f"{name}: {err}") from None
    return params
