"""CEM-MPC: the cross-entropy method over action sequences, replanned every step.

At every environment step the planner samples ``population`` normalised action sequences
(``horizon`` steps each) from a diagonal Gaussian, simulates all of them from the current
state with the task's pure step (``vmap`` over the population), keeps the ``elites`` best
by the planning objective (:func:`dax_algos.planning.planner.make_objective`), refits the Gaussian
(with ``momentum`` towards the old one and a floor ``min_std``) and repeats ``iterations``
times. The current mean is always evaluated as member 0 (so an iteration never forgets
it), the best sequence seen is kept, and its first action is executed. The next step's
search starts from the best sequence shifted by one step (warm start) with the standard
deviation reset to ``init_std``.

Pure core: :func:`cem_optimise` (any ``value(z_seq)`` function); :func:`make_planner`
turns it into a :class:`dax_algos.planning.planner.Planner`.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from dax_tasks import shard_batch

from ..checks import check_positive, check_positive_int
from ..episode import no_grad_stats
from .planner import Planner, check_objective, plan_length, warm_started_planner


@dataclasses.dataclass(frozen=True)
class CEMConfig:
    """population: sequences sampled per iteration; elites: how many refit the Gaussian;
    iterations: CEM iterations per replanning; horizon: planning horizon in environment
    steps (clipped to the episode length); init_std / min_std: standard deviation at the
    start of each replanning and its floor, in normalised action units (the action box is
    [-1, 1]); momentum: weight of the old mean / std in the refit; objective: ``"final"``
    or ``"sum"`` (see :func:`dax_algos.planning.planner.make_objective`)."""

    population: int = 64
    elites: int = 8
    iterations: int = 5
    horizon: int = 3
    init_std: float = 0.5
    min_std: float = 0.05
    momentum: float = 0.1
    objective: str = "final"

    def __post_init__(self):
        for name in ("population", "elites", "iterations", "horizon"):
            check_positive_int(name, getattr(self, name))
        if self.elites > self.population:
            raise ValueError(f"elites ({self.elites}) must be <= population "
                             f"({self.population})")
        check_positive("init_std", self.init_std)
        check_positive("min_std", self.min_std, allow_zero=True)
        if not 0.0 <= self.momentum < 1.0:
            raise ValueError(f"momentum must be in [0, 1), got {self.momentum!r}")
        check_objective(self.objective)


def cem_optimise(value_fn, mean, key, config: CEMConfig):
    """Maximise ``value_fn(z)`` over ``z`` in [-1, 1]^shape by CEM from ``mean``.

    Returns ``(best_z, best_value)``. ``value_fn`` is vmapped over the population; a
    non-finite value ranks last. With several devices the population (the samples and
    their values) is split over them (:func:`dax_tasks.shard_batch`; a
    population that is a multiple of the device count). Pure and jittable."""
    pop, n_elite = config.population, config.elites
    batched = jax.vmap(value_fn)
    std0 = jnp.full_like(mean, config.init_std)

    def iteration(carry, k):
        mean, std, best_z, best_v = carry
        eps = jax.random.normal(k, (pop, *mean.shape), mean.dtype)
        z = shard_batch(jnp.clip(mean + std * eps, -1.0, 1.0).at[0].set(mean))
        v = shard_batch(batched(z))
        v = jnp.where(jnp.isfinite(v), v, -jnp.inf)
        top_v, idx = jax.lax.top_k(v, n_elite)
        elite = z[idx]
        a = config.momentum
        mean = (1 - a) * jnp.mean(elite, 0) + a * mean
        std = jnp.maximum((1 - a) * jnp.std(elite, 0) + a * std, config.min_std)
        better = top_v[0] > best_v
        best_z = jnp.where(better, elite[0], best_z)
        best_v = jnp.where(better, top_v[0], best_v)
        return (mean, std, best_z, best_v), None

    init = (mean, std0, mean, jnp.asarray(-jnp.inf, jnp.float32))
    keys = jax.random.split(key, config.iterations)
    (_, _, best_z, best_v), _ = jax.lax.scan(iteration, init, keys)
    return best_z, best_v


def make_planner(env, config: CEMConfig) -> Planner:
    """CEM-MPC for ``env``: pstate is the warm-start mean (h, d)."""
    h = plan_length(env, config.horizon)

    def search(value_fn, mean, key):
        best_z, best_v = cem_optimise(value_fn, mean, key, config)
        return best_z, no_grad_stats(best_v)

    return warm_started_planner(env, config.horizon, config.objective, search,
                                sim_steps_per_plan=config.iterations * config.population * h)
