"""The kinematic drive of :func:`dax_physics.mpm.step` (``drive=(weight, velocity)``): the
grid nodes that carry driven mass move at the drive's velocity, so a held part of an
object pulls the rest through the velocity field (the grip of a rope task).

Tiny float64 scenes (16^3 cells, an elastic block of 512 particles), each compiled once.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dax_physics import materials, mpm, sampling

N = 40


@functools.partial(jax.jit, static_argnums=(0, 3))
def _run(cfg, params, state, n, weight, velocity):
    def body(s, _):
        return mpm.step(cfg, params, s, drive=(weight, velocity)), None

    return jax.lax.scan(body, state, None, length=n)[0]


@functools.partial(jax.jit, static_argnums=(0, 3))
def _run_plain(cfg, params, state, n):
    return jax.lax.scan(lambda s, _: (mpm.step(cfg, params, s), None), state, None,
                        length=n)[0]


@pytest.fixture(scope="module")
def scene():
    with jax.enable_x64(True):
        dx = 1.0 / 16
        cfg = mpm.MPMConfig(materials=(materials.tofu(),), dx=dx, dt=1e-3,
                            domain=(16, 16, 16), walls="none", gravity=(0.0, 0.0, -9.81),
                            max_speed=1.0)
        x, vol = sampling.box((4 * dx, 6 * dx, 6 * dx), (12 * dx, 10 * dx, 10 * dx), dx,
                              ppc=8, seed=3)
        params = mpm.MaterialParams.from_materials(cfg.materials, dtype=jnp.float64)
        s0 = mpm.init_state(cfg, x, vol=vol, dtype=jnp.float64)
    return cfg, params, s0, np.asarray(s0.x)


def _np(tree):
    return jax.tree.map(np.asarray, tree)


def test_a_drive_with_no_driven_particle_is_the_plain_substep(scene):
    cfg, params, s0, x0 = scene
    with jax.enable_x64(True):
        plain = _np(_run_plain(cfg, params, s0, N))
        zero = _np(_run(cfg, params, s0, N, jnp.zeros(s0.x.shape[0]),
                        jnp.array([1.0, 0.0, 0.0])))
    assert np.abs(plain.x - x0).max() > 1e-3, "the block did not fall: vacuous"
    for name in ("x", "v", "C", "H"):  # H = F - I, as stored
        np.testing.assert_allclose(getattr(zero, name), getattr(plain, name), rtol=0,
                                   atol=1e-12, err_msg=name)


def test_a_fully_driven_block_moves_rigidly_at_the_drive_velocity(scene):
    """Every node the block touches is driven: each particle gathers the drive's velocity
    exactly (gravity overridden), C stays zero and F the identity: a rigid translation."""
    cfg, params, s0, x0 = scene
    v = np.array([0.4, -0.3, 0.2])
    with jax.enable_x64(True):
        s = _np(_run(cfg, params, s0, N, jnp.ones(s0.x.shape[0]), jnp.asarray(v)))
    np.testing.assert_allclose(s.v, np.broadcast_to(v, s.v.shape), rtol=0, atol=1e-12)
    np.testing.assert_allclose(s.C, 0.0, atol=1e-12)
    np.testing.assert_allclose(s.H, 0.0, atol=1e-12)  # F - I: F stays the identity
    np.testing.assert_allclose(s.x, x0 + N * cfg.dt * v, rtol=0, atol=1e-12)


def test_a_driven_end_drags_the_free_part_along(scene):
    """The left quarter of the block is driven at 0.5 m/s along +x (no gravity); the free
    part must follow through the elastic stress: after 0.1 s its centroid has moved with
    the held part (the gap between the two centroids changed by under a tenth of a
    cell), not stayed behind."""
    cfg, params, s0, x0 = scene
    cfg = dataclasses.replace(cfg, gravity=(0.0, 0.0, 0.0))
    held = x0[:, 0] < x0[:, 0].min() + 2 * cfg.dx
    v = np.array([0.5, 0.0, 0.0])
    n = 100
    with jax.enable_x64(True):
        s = _np(_run(cfg, params, s0, n, jnp.asarray(held, jnp.float64), jnp.asarray(v)))
    moved_held = s.x[held, 0].mean() - x0[held, 0].mean()
    moved_free = s.x[~held, 0].mean() - x0[~held, 0].mean()
    assert moved_held == pytest.approx(n * cfg.dt * 0.5, rel=1e-4)  # (edge nodes)
    assert abs(moved_free - moved_held) < 0.1 * cfg.dx, (moved_held, moved_free)
    assert np.all(np.isfinite(s.x))
