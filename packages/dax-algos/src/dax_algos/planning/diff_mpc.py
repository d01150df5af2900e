"""diff-MPC: gradient ascent on the action sequence through the differentiable step.

At every environment step the planner optimises a normalised action sequence (``horizon``
steps) by ``steps`` gradient steps of an Optax optimiser on the planning objective
(:func:`dax_algos.planning.planner.make_objective`), differentiating through the task's pure step.
The first plan starts from a uniform random sequence; later plans start from the previous
solution shifted by one step, with a random last action. After each update the sequence is
projected back onto the action box. The best sequence seen (the objective is evaluated at
every iterate and once after the last update) is kept and its first action executed.

Stability: the raw global gradient norm of every step is computed (reported as
``grad_norm``), the gradient is clipped to ``max_grad_norm`` with
``optax.clip_by_global_norm`` (``None``: no clipping), and ``zero_nans=True`` chains
``optax.zero_nans()`` first (off by default: a non-finite gradient is counted and the
benchmark runner records the run as failed).

Pure core: :func:`gradient_refine` (any ``value(z_seq)``); :func:`make_planner` wraps it.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import optax

from ..actions import to_action
from ..checks import check_choice, check_fields
from ..episode import PlanStats
from ..optim import OPTIMISERS
from ..optim import make_optimiser as chain_optimiser
from .planner import Planner, check_objective, make_objective, plan_length, shift


@dataclasses.dataclass(frozen=True)
class DiffMPCConfig:
    """steps: gradient steps per replanning; horizon: planning horizon in environment steps
    (clipped to the episode length); learning_rate: in normalised action units (the box is
    [-1, 1]); optimiser: ``"adam"`` or ``"sgd"``; max_grad_norm: global-norm clip (``None``
    off); zero_nans: replace NaN gradient entries by 0; objective: ``"final"`` or
    ``"sum"``."""

    steps: int = 50
    horizon: int = 3
    learning_rate: float = 0.05
    optimiser: str = "adam"
    max_grad_norm: float | None = 1.0
    zero_nans: bool = False
    objective: str = "final"

    def __post_init__(self):
        check_fields(self, ints=("steps", "horizon"), positive=("learning_rate",),
                     optional_positive=("max_grad_norm",))
        check_choice("optimiser", self.optimiser, OPTIMISERS)
        check_objective(self.objective)


def make_optimiser(config: DiffMPCConfig) -> optax.GradientTransformation:
    """``[zero_nans] -> [clip_by_global_norm] -> adam | sgd`` (minimising) of ``config``
    (:func:`dax_algos.optim.make_optimiser`)."""
    return chain_optimiser(config.learning_rate, config.max_grad_norm, config.zero_nans,
                           config.optimiser)


def gradient_refine(value_fn, z0, config, best_z=None, best_v=None):
    """Maximise ``value_fn(z)`` over ``z`` in [-1, 1]^shape by ``config.steps`` projected
    optimiser steps from ``z0``; ``best_z``/``best_v`` seed the incumbent (e.g. CEM's
    best). Returns ``(best_z, best_value, PlanStats)``. Pure and jittable."""
    opt = make_optimiser(config)
    value_and_grad = jax.value_and_grad(value_fn)
    if best_z is None:
        best_z, best_v = z0, jnp.asarray(-jnp.inf, jnp.float32)

    def keep_best(z, v, best_z, best_v):
        better = jnp.isfinite(v) & jnp.all(jnp.isfinite(z)) & (v > best_v)
        return jnp.where(better, z, best_z), jnp.where(better, v, best_v)

    def step(carry, _):
        z, opt_state, best_z, best_v, gmax, gsum, bad = carry
        v, g = value_and_grad(z)
        best_z, best_v = keep_best(z, v, best_z, best_v)
        g = -g  # the optimiser minimises; we ascend the objective
        norm = optax.tree.norm(g)
        finite = jnp.isfinite(norm)
        gmax = jnp.where(finite, jnp.maximum(gmax, norm), jnp.inf)
        gsum = gsum + jnp.where(finite, norm, 0.0)
        bad = bad + (~finite).astype(jnp.int32)
        updates, opt_state = opt.update(g, opt_state, z)
        z = jnp.clip(optax.apply_updates(z, updates), -1.0, 1.0)
        return (z, opt_state, best_z, best_v, gmax, gsum, bad), None

    zero = jnp.zeros((), jnp.float32)
    init = (z0, opt.init(z0), best_z, best_v, zero, zero, jnp.zeros((), jnp.int32))
    (z, _, best_z, best_v, gmax, gsum, bad), _ = jax.lax.scan(step, init, None,
                                                             length=config.steps)
    best_z, best_v = keep_best(z, value_fn(z), best_z, best_v)
    stats = PlanStats(objective=best_v, grad_norm_max=gmax, grad_norm_sum=gsum,
                             grad_steps=jnp.asarray(config.steps, jnp.int32),
                             nonfinite_grads=bad)
    return best_z, best_v, stats


def make_planner(env, config: DiffMPCConfig) -> Planner:
    """diff-MPC for ``env``: pstate is the previous solution (h, d)."""
    h = plan_length(env, config.horizon)
    d = env.spec.action_dim
    value = make_objective(env, config.objective)

    def init(key):
        return jax.random.uniform(key, (h, d), jnp.float32, -1.0, 1.0)

    def plan(z0, env_state, key, params):
        best_z, _, stats = gradient_refine(lambda z: value(env_state, z, params), z0, config)
        action = to_action(env, best_z[0])
        tail = jax.random.uniform(key, (d,), jnp.float32, -1.0, 1.0)
        return action, shift(best_z, tail), stats

    return Planner(init=init, plan=plan, sim_steps_per_plan=(config.steps + 1) * h,
                          backprop_steps_per_plan=config.steps * h,
                          nan_grads_zeroed=config.zero_nans)
