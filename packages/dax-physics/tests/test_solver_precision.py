"""Every matrix product in the solvers runs at full float32 precision.

Why, and how it is checked on CPU: :mod:`dax_physics.precision`. These tests lower
the forward and reverse passes of the solvers (MPM with a grasping collider, the
bounded-collider grid path, cloth with self-collision) and require HIGHEST on every dot.
"""

from __future__ import annotations

import dataclasses
import os

import jax
import jax.numpy as jnp
import numpy as np

from dax_physics import cloth as c
from dax_physics import colliders, materials, mpm, sampling
from dax_physics.precision import DETERMINISTIC_FLAG, deterministic_gpu_ops, dots


def assert_full_precision(fn, *args, least=1):
    """Every dot of ``fn`` lowered asks for HIGHEST, and there are at least ``least``."""
    found, low = dots(fn, *args)
    assert len(found) >= least, f"expected at least {least} dot products, found {len(found)}"
    assert not low, "dot products below full float32 precision:\n" + "\n".join(low[:5])


def _grasped_block():
    dx = 1.0 / 16
    gripper = colliders.ColliderSpec("sphere", (1.5 * dx,), mode="separate", friction=0.5)
    bowl = colliders.ColliderSpec("bowl", (0.15, 0.2, 0.05), mode="separate", friction=0.2)
    cfg = mpm.MPMConfig(materials=(materials.tofu(),), dx=dx, dt=2e-3, domain=(16, 16, 16),
                        colliders=(gripper, bowl), max_speed=1.0)
    floor = cfg.wall_cells * dx
    x, vol = sampling.box((6 * dx, 6 * dx, floor), (10 * dx, 10 * dx, floor + 3 * dx), dx,
                          ppc=1)
    p0 = np.array([[8 * dx, 8 * dx, floor + 3.5 * dx], [0.5, 0.5, 0.1]])
    s = mpm.init_state(cfg, x, vol=vol, colliders=colliders.ColliderState.create(p0))
    return cfg, s


def test_mpm_step_grasp_and_gradient_use_full_precision():
    cfg, s = _grasped_block()
    assert_full_precision(lambda st: mpm.grasp(cfg, st, 0, radius=0.05), s)
    s = mpm.grasp(cfg, s, 0, radius=0.05)
    assert np.any(np.asarray(s.held) == 0), "the setup should hold some particles"

    def loss(x):
        return jnp.sum(mpm.step(cfg, cfg.params, s.replace(x=x)).x ** 2)

    # forward: the materialised particle entries; reverse: the transfers' moments and the
    # materialised grid cotangent
    assert_full_precision(loss, s.x, least=2)
    assert_full_precision(jax.grad(loss), s.x, least=3)


def test_bounded_collider_grid_path_uses_full_precision():
    spec = (colliders.ColliderSpec("bowl", (0.05, 0.06, 0.02), "separate", 0.2),)
    dx, window, origin = 0.01, (30, 22, 26), jnp.asarray([3, 1, 2], jnp.int32)
    state = colliders.ColliderState.create(np.array([[0.15, 0.12, 0.14]]))
    v = jnp.ones((int(np.prod(window)), 3), jnp.float32)
    assert_full_precision(
        lambda st, u: colliders.apply_colliders_grid(spec, st, u, dx, window, origin),
        state, v)


def test_cloth_with_self_collision_its_gradient_and_energy_use_full_precision():
    """The cloth step has no dot today (spring sums are elementwise); this keeps any that
    is added at full precision."""
    cl = c.square_cloth(6, size=(0.3, 0.3), density=0.2, stretch=50.0, bend=0.2,
                        damping=0.02)
    cfg = c.ClothConfig(dt=1.0, thickness=0.06, self_stiffness=50.0, self_damping=0.01,
                        strain_limit=0.05)
    cfg = dataclasses.replace(cfg, dt=0.9 * c.max_stable_dt(cfg, cl))
    st = c.ClothState.create(cl)

    def loss(x):
        return jnp.sum(c.rollout(cfg, cl, st.replace(x=x), 3).x ** 2)

    assert_full_precision(loss, st.x, least=0)
    assert_full_precision(jax.grad(loss), st.x, least=0)
    assert_full_precision(lambda x: c.energy(cfg, cl, st.replace(x=x)), st.x, least=0)


def test_deterministic_gpu_ops_adds_the_flag_once_and_keeps_the_others(monkeypatch):
    monkeypatch.delenv("XLA_FLAGS", raising=False)
    deterministic_gpu_ops()
    assert os.environ["XLA_FLAGS"] == DETERMINISTIC_FLAG
    monkeypatch.setenv("XLA_FLAGS", "--xla_force_host_platform_device_count=4")
    deterministic_gpu_ops()
    deterministic_gpu_ops()
    assert os.environ["XLA_FLAGS"].split() == [
        "--xla_force_host_platform_device_count=4", DETERMINISTIC_FLAG]
    # a choice already made (even false) is the caller's
    monkeypatch.setenv("XLA_FLAGS", "--xla_gpu_deterministic_ops=false")
    deterministic_gpu_ops()
    assert os.environ["XLA_FLAGS"] == "--xla_gpu_deterministic_ops=false"
