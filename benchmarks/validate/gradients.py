"""Gradient checks: each solver's reverse-mode gradient of a scalar loss against float64
central finite differences at several steps h.

A central difference converges to the derivative as h^2 until round-off (~eps / h) takes
over; a solver whose loss is smooth shows the error falling with h and then flattening far
below 1 %. A loss that is not smooth at the scale h (contact switching, stick-slip,
return mapping onto the yield surface) shows errors that do not fall with h: the check
says so rather than picking the best h.

The same helpers serve the task-level checks that dax-tasks plugs in (the entry-point
group of :mod:`benchmarks.validate`).
"""

from __future__ import annotations

import math
import time

import jax
import jax.numpy as jnp
import numpy as np

from dax_physics import cloth as C
from dax_physics import colliders, mpm, sampling
from dax_physics.materials import Material, MaterialParams

from . import Point, Result, register

#: Steps of the central differences, relative to the parameter's scale.
STEPS = (1e-2, 1e-3, 1e-4, 1e-5, 1e-6, 1e-7)
#: The step whose error goes in the table (below it float64 round-off grows).
DEFAULT_STEP = 1e-4


def fd_sweep(loss, x0, direction, steps=STEPS):
    """Directional derivative of ``loss`` (a jittable scalar function of one array, run
    in float64) at ``x0`` along ``direction``: the reverse-mode value and the central
    differences ``(loss(x0 + h d) - loss(x0 - h d)) / 2h`` for each ``h`` in ``steps``.
    Returns ``(ad, {h: fd}, seconds of one gradient)``."""
    with jax.enable_x64(True):
        x0 = jnp.asarray(x0, jnp.float64)
        d = jnp.asarray(direction, jnp.float64)
        f = jax.jit(loss)
        g = jax.jit(jax.grad(loss)).lower(x0).compile()
        t0 = time.perf_counter()
        ad = float(jnp.sum(jax.block_until_ready(g(x0)) * d))
        wall = time.perf_counter() - t0
        fd = {h: (float(f(x0 + h * d)) - float(f(x0 - h * d))) / (2.0 * h) for h in steps}
    return ad, fd, wall


def gradient_points(ad, fd, wall, scale=1.0):
    """Sweep points (one per step h; ``cell_size`` is h relative to ``scale``) with the
    relative error of the autodiff value against each central difference."""
    return [Point(h / scale, h / scale, (ad - v) / v if v else math.inf, wall, measured=ad,
                  expected=v) for h, v in sorted(fd.items(), reverse=True)]


def gradient_result(name, solver, quantity, points, note="", tolerance=0.01):
    """A :class:`Result` for a gradient check: error at :data:`DEFAULT_STEP`, tolerance 1 %,
    expected order 2 (central differences) measured on the steps at and above it."""
    return Result(name=name, solver=solver, reference="float64 central finite differences",
                  quantity=quantity, resolution_label="FD step h (relative)",
                  default=DEFAULT_STEP, points=points, tolerance=tolerance, expected_order=2.0,
                  pareto_note="gradient check: the x axis is the FD step, not a resolution",
                  notes=note, error_label="|AD - FD| / |FD|", order_min_cell_size=DEFAULT_STEP)


def _mpm_scene(mat: Material, dx=1.0 / 12, n=12, steps=40, press=False):
    """A 5^3-particle-cell block (float64) with fixed random initial velocities, hit by a
    sticky sphere (or, with ``press``, pressed by a box) moving at 1 m/s; returns
    ``loss(params)`` (a smooth weighting of the final positions) and the params."""
    with jax.enable_x64(True):
        f64 = jnp.float64
        if press:
            tool = colliders.ColliderSpec("box", (0.3, 0.3, 0.05), mode="separate")
            pos, vel = [[0.5, 0.5, 0.62 + 0.05]], [[0.0, 0.0, -1.0]]
        else:
            tool = colliders.ColliderSpec("sphere", (1.5 * dx,), mode="sticky")
            pos, vel = [[0.25, 0.5, 0.5]], [[1.0, 0.0, 0.0]]
        cfg = mpm.MPMConfig(materials=(mat,), dx=dx, dt=2e-3 if mat.kind == "fluid" else 3e-3,
                            domain=(n, n, n), walls="slip", colliders=(tool,), max_speed=2.0)
        x, vol = sampling.box((0.4, 0.4, 0.4), (0.6, 0.6, 0.6), dx, ppc=8)
        rng = np.random.default_rng(0)
        v0 = rng.normal(0.0, 0.2, x.shape)
        cs = colliders.ColliderState.create(pos, lin_vel=vel, dtype=f64)
        state = mpm.init_state(cfg, x, v=v0, vol=vol, colliders=cs, dtype=f64)
        params = MaterialParams.from_materials(cfg.materials, dtype=f64)
        weights = jnp.asarray(rng.normal(size=x.shape), f64)

    def loss(p):
        out = mpm.rollout(cfg, p, state, steps)
        return jnp.mean(out.x * weights) + jnp.mean(out.x[:, 0])

    return loss, params


def _mpm_check(name, solver, mat, field, press=False, level="default"):
    """Gradient of the MPM loss with respect to material ``field`` (e.g. ``lam``)."""
    loss, params = _mpm_scene(mat, press=press, steps=20 if level == "quick" else 40)
    value = float(getattr(params, field)[0])

    def of(x):
        return loss(params.replace(**{field: jnp.reshape(x, (1,))}))

    ad, fd, wall = fd_sweep(of, value, 1.0, steps=tuple(h * value for h in STEPS))
    points = gradient_points(ad, fd, wall, scale=value)
    return gradient_result(name, solver, f"d loss / d {field} (40 substeps)", points)


@register
def check_gradient_mpm_fluid(level="default"):
    """Water (bulk modulus 2e4 Pa) hit by a sticky sphere: d loss / d K (the params'
    ``lam`` of a fluid) against float64 central differences."""
    return _mpm_check("gradient_mpm_fluid", "MPM fluid", Material(
        "fluid", 1000.0, bulk_modulus=2.0e4, viscosity=1e-3), "lam", level=level)


@register
def check_gradient_mpm_elastic(level="default"):
    """Tofu (fixed-corotated, E = 5e4 Pa) hit by a sticky sphere: d loss / d mu against
    float64 central differences."""
    return _mpm_check("gradient_mpm_elastic", "MPM elastic", Material(
        "elastic", 1050.0, youngs_modulus=5.0e4, poisson_ratio=0.3), "mu", level=level)


@register
def check_gradient_mpm_plastic(level="default"):
    """Dough (von Mises, yield stress 1 kPa) pressed by a plate until it flows: d loss / d
    yield stress against float64 central differences."""
    return _mpm_check("gradient_mpm_plastic", "MPM plastic", Material(
        "plastic", 1200.0, youngs_modulus=5.0e4, poisson_ratio=0.3, yield_stress=1.0e3),
        "yield_stress", press=True, level=level)


@register
def check_gradient_cloth(level="default"):
    """A 9 x 9 cloth pinned at two corners swinging down for 0.2 s (no table): d loss / d
    stretch factor (:func:`dax_physics.cloth.scale_moduli`) against float64 central
    differences."""
    with jax.enable_x64(True):
        cl = C.square_cloth(9, size=(0.2, 0.2), height=0.3, density=0.2, stretch=50.0,
                            damping=0.01, dtype=jnp.float64)
        cfg = C.ClothConfig(dt=2e-4, table_height=None, air_drag=0.5)
        st = C.ClothState.create(cl, n_grippers=2)
        st = C.grasp(st, 0, [0.0, 0.0, 0.3], 1e-3)
        st = C.grasp(st, 1, [0.2, 0.0, 0.3], 1e-3)
        w = jnp.asarray(np.random.default_rng(1).normal(size=(81, 3)), jnp.float64)
    n = 500 if level == "quick" else 1000

    def loss(k):
        out = C.rollout(cfg, C.scale_moduli(cl, stretch=k), st, n)
        return jnp.mean(out.x * w) + jnp.mean(out.x[:, 2])

    ad, fd, wall = fd_sweep(loss, 1.0, 1.0)
    return gradient_result("gradient_cloth", "cloth", "d loss / d stretch factor "
                           f"({n} substeps)", gradient_points(ad, fd, wall))
