"""Test helpers of dax-algos: a smooth analytic toy task (no physics) and a cheap cloth task.
(A uniquely named module, so it never clashes with another package's conftest.)"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp


class ToyState(NamedTuple):
    p: jnp.ndarray
    t: jnp.ndarray
    finite: jnp.ndarray


@dataclasses.dataclass(frozen=True)
class ToySpec:
    name: str = "toy"
    action_low: tuple = (-0.5, -0.5)
    action_high: tuple = (0.5, 0.5)
    action_kind: str = "velocity"

    @property
    def action_dim(self):
        return len(self.action_low)


class ToyTask:
    """A point moved by its action on a smooth Gaussian reward landscape:
    ``p' = p + a``, ``r = exp(-|p' - g|^2 / width)`` with ``g = (0.3, -0.2)``. Same
    interface as :class:`dax_tasks.Env` (``reset``, ``step``, ``spec``, ``horizon``,
    ``default_params``); its params are unused (``None``)."""

    def __init__(self, horizon=2, width=0.05, scale=1.0):
        self.spec = ToySpec()
        self.horizon = horizon
        self.width = width
        self.scale = scale
        self.goal = jnp.asarray([0.3, -0.2])
        self.has_expert = False
        self.default_params = None

    def reset(self, key, params=None):
        p = jax.random.uniform(key, (2,), minval=-0.2, maxval=0.2)
        return p, ToyState(p, jnp.zeros((), jnp.int32), jnp.asarray(True))

    def step(self, state, action, params=None):
        p = state.p + action
        d2 = jnp.sum((p - self.goal) ** 2)
        r = self.scale * jnp.exp(-d2 / self.width)
        finite = state.finite & jnp.all(jnp.isfinite(p))
        info = {"r_gt": r, "distance": jnp.sqrt(d2), "finite": finite}
        return p, ToyState(p, state.t + 1, finite), r, state.t + 1 >= self.horizon, info


def cheap_cloth_overrides(name="fold_cloth1", **extra):
    """A coarse cloth task: 6 x 6 vertices, 400 substeps per action (200 carrying; a
    60-substep carry flings the cloth off the table, so the goal itself is off it), without
    self-collision (it multiplies a cloth step's time by about 11; these tests are about
    the methods, not the layers)."""
    import dax_tasks

    spec = dax_tasks.get_spec(name)
    return dict(scene=dataclasses.replace(spec.scene, n=6, settle_substeps=200,
                                          thickness=0.0),
                substeps=400, **extra)


def make_nan_planner(task, config):
    """A broken planner for the runner's tests: random actions times NaN (the task's
    finite flag turns false, so its rows must be ``failed``)."""
    from dax_algos.planning import planner, reference

    rnd = reference.make_random(task, config)

    def plan(pstate, env_state, key, params):
        action, pstate, stats = rnd.plan(pstate, env_state, key, params)
        return action * jnp.nan, pstate, stats

    return planner.Planner(init=rnd.init, plan=plan)


def register_nan_planner(overwrite: bool = False) -> None:
    """Register :func:`make_nan_planner` as the method ``nan_actions`` (unregister it with
    ``registry.unregister("nan_actions")``)."""
    from dax_algos import method, registry
    from dax_algos.planning import reference

    registry.register(method.PlannerMethod(
        name="nan_actions", family="reference", config_cls=reference.RandomConfig,
        make_planner=make_nan_planner), overwrite=overwrite)
