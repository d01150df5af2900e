"""Cloth checks that pin down what works today (see issue 3 for the rest: folding with
self-collision in layers, fold gradients against finite differences, friction threshold)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dax_physics import cloth as C


@pytest.fixture(scope="module")
def small_cloth():
    cl = C.square_cloth(8, size=(0.2, 0.2), height=0.05, density=0.2, stretch=50.0,
                        damping=0.05)
    cfg = C.ClothConfig(dt=1e-4, table_height=0.0, friction_static=0.5, air_drag=0.5)
    return cfg, cl


def test_mesh_cloth_refuses_an_unstable_substep(small_cloth):
    cfg, cl = small_cloth
    bad = C.ClothConfig(dt=10 * C.max_stable_dt(cfg, cl), table_height=0.0)
    with pytest.raises(ValueError, match="largest stable dt"):
        C.check_params(bad, cl)
    C.check_params(cfg, cl)  # the stable one passes


def test_dropped_cloth_comes_to_rest_flat_on_the_table(small_cloth):
    cfg, cl = small_cloth
    state = C.ClothState.create(cl)
    out = jax.jit(lambda s: C.rollout(cfg, cl, s, 3000))(state)
    z = np.asarray(out.x[:, 2])
    speed = float(np.abs(np.asarray(out.v)).max())
    assert np.all(np.abs(z) < 1e-3), (
        f"expected all vertices on the table, z range {z.min()}..{z.max()}")
    assert speed < 0.05, f"expected the cloth at rest, max speed {speed} m/s"
    # flat: in-plane extent unchanged (no crumpling), within 2 %
    ext = np.ptp(np.asarray(out.x[:, :2]), axis=0)
    assert np.allclose(ext, 0.2, rtol=0.02), f"expected a 0.2 m square, got extent {ext}"


def test_cloth_rollout_is_deterministic_and_vmaps_like_a_loop(small_cloth):
    cfg, cl = small_cloth
    s0 = C.ClothState.create(cl)
    states = [s0.replace(x=s0.x + jnp.asarray([0.0, 0.0, dz])) for dz in (0.0, 0.01)]
    run = jax.jit(lambda s: C.rollout(cfg, cl, s, 200))
    loop = [np.asarray(run(s).x) for s in states]
    batch = jax.tree.map(lambda *a: jnp.stack(a), *states)
    vm = np.asarray(jax.jit(jax.vmap(lambda s: C.rollout(cfg, cl, s, 200)))(batch).x)
    np.testing.assert_allclose(vm, np.stack(loop), atol=1e-6)
    np.testing.assert_array_equal(np.asarray(run(states[0]).x), loop[0])


def test_nan_pick_point_is_refused(small_cloth):
    cfg, cl = small_cloth
    with pytest.raises(ValueError, match="pick point must be finite"):
        C.grasp(C.ClothState.create(cl), 0, [np.nan, 0.0, 0.0], 0.01)


def test_degenerate_triangle_is_refused():
    v = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 1, 0]], float)
    f = np.array([[0, 1, 2], [0, 1, 3]])
    with pytest.raises(C.MeshError):
        C.make_cloth(v, f)
