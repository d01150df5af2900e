"""The optimiser every gradient method uses (Optax) and the update that keeps non-finite
gradients out of the parameters."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import optax

from .checks import check_choice

OPTIMISERS = ("adam", "sgd")
#: Learning-rate schedules: ``constant``, or ``linear`` from the learning rate to 0 over
#: the run's optimiser steps (as SHAC's original code decays its rates).
LR_SCHEDULES = ("constant", "linear")


def check_lr_schedule(schedule: str) -> None:
    """Raise a ValueError naming the valid schedules when ``schedule`` is not one."""
    check_choice("lr_schedule", schedule, LR_SCHEDULES)


def make_optimiser(learning_rate: float, max_grad_norm: float | None,
                   zero_nans: bool = False, optimiser: str = "adam",
                   lr_schedule: str = "constant", steps: int | None = None
                   ) -> optax.GradientTransformation:
    """``[zero_nans] -> [clip_by_global_norm(max_grad_norm)] -> adam | sgd``, minimising;
    ``max_grad_norm=None`` clips nothing. ``lr_schedule="linear"`` decays the rate from
    ``learning_rate`` to 0 over ``steps`` optimiser steps (required then)."""
    check_choice("optimiser", optimiser, OPTIMISERS)
    check_lr_schedule(lr_schedule)
    rate = learning_rate
    if lr_schedule == "linear":
        if not steps or steps < 1:
            raise ValueError(f"lr_schedule 'linear' needs the run's optimiser steps "
                             f"(a positive int), got {steps!r}")
        rate = optax.linear_schedule(learning_rate, 0.0, steps)
    parts = [optax.zero_nans()] if zero_nans else []
    if max_grad_norm is not None:
        parts.append(optax.clip_by_global_norm(max_grad_norm))
    parts.append((optax.adam if optimiser == "adam" else optax.sgd)(rate))
    return optax.chain(*parts)


def guarded_update(opt, grads, opt_state, params, zero_nans: bool):
    """One optimiser step that never lets a non-finite gradient into the parameters.

    Returns ``(params, opt_state, raw_norm, nonfinite)``: the raw (unclipped) global norm
    and whether the gradient had a NaN/inf. With ``zero_nans`` the optimiser zeroes the
    non-finite entries and applies the rest (asked for explicitly); otherwise the whole
    update is skipped (parameters and optimiser state unchanged) and counted.
    """
    norm = optax.tree.norm(grads)
    nonfinite = ~jnp.isfinite(norm)
    updates, new_opt_state = opt.update(grads, opt_state, params)
    new_params = optax.apply_updates(params, updates)
    if zero_nans:
        return new_params, new_opt_state, norm, nonfinite
    keep = jnp.logical_not(nonfinite)
    pick = lambda new, old: jax.tree_util.tree_map(  # noqa: E731
        lambda a, b: jnp.where(keep, a, b), new, old)
    return pick(new_params, params), pick(new_opt_state, opt_state), norm, nonfinite
