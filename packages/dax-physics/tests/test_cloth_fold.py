"""Cloth folding with self-collision, gradients, checkpointing, vmap and determinism."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import dax_physics.cloth as c

N, L = 16, 0.3
SP = L / (N - 1)
H = SP  # thickness = grid spacing: a vertex cannot slip through the other layer's holes


def _fold_setup(dtype=jnp.float32, n=N, size=L, friction=1.0, strain_limit=0.05):
    sp = size / (n - 1)
    cl = c.square_cloth(n, size=(size, size), density=0.2, stretch=50.0, bend=0.2,
                        damping=0.02, dtype=dtype)
    cfg = c.ClothConfig(dt=1.0, friction_static=friction,
                        friction_dynamic=0.8 * friction, thickness=sp, self_stiffness=50.0,
                        self_damping=0.01, self_friction=0.005, air_drag=0.5,
                        strain_limit=strain_limit)
    dt = {N: 1.5e-4, 8: 2e-4}.get(n) or c.max_stable_dt(cfg, cl)
    cfg = dataclasses.replace(cfg, dt=dt)
    return cfg, cl, c.ClothState.create(cl)


def test_fold_corner_onto_opposite_corner_gives_two_ordered_layers():
    """The corner is placed 0.15 L inside the opposite corner (at 0.1 L it lands 1 cm from
    the bottom layer's edge and slides off it after release), and the layers end a
    thickness apart (with a search that dropped vertices of the stack, a spatial hash of 8
    slots, the gap sank to 0.75 h). The neighbour list finds every contact: its overflow
    stays 0."""
    cfg, cl, st = _fold_setup()
    st = c.with_neighbours(cfg, cl, st)
    sc = c.PickPlace(approach_steps=100, lift_steps=1000, move_steps=2500, lower_steps=1000,
                     settle_steps=2500, lift_height=0.08, radius=0.5 * SP)
    place = jnp.array([0.85 * L, 0.85 * L, H])
    out = jax.jit(lambda p, q: c.pick_and_place(cfg, cl, st, p, q, sc))(
        jnp.zeros(3), place)
    x = np.asarray(out.x).reshape(N, N, 3)
    assert np.isfinite(x).all(), "expected finite positions, got NaN/inf"
    ii, jj = np.meshgrid(range(N), range(N), indexing="ij")
    top, bot = x[ii + jj < N - 1], x[ii + jj >= N - 1]  # folded half / half that stays
    d = np.linalg.norm(top[:, None, :2] - bot[None, :, :2], axis=-1)
    near = d.min(1) < 0.7 * SP
    assert near.mean() > 0.8, f"expected > 80 % of the folded half over the other half, " \
                              f"got {near.mean():.2f}"
    gap = top[near, 2] - bot[d.argmin(1)[near], 2]
    assert gap.min() >= 0.85 * H, f"expected the folded layer >= 0.85 h = {0.85 * H:.4f} m " \
                                  f"above the bottom layer, got min gap {gap.min():.4f} m"
    assert bot[:, 2].min() >= 0.0, f"expected no vertex below the table, got {bot[:, 2].min()}"
    overflow = int(out.neighbours.overflow)
    assert overflow == 0, f"expected a neighbour list that missed nothing, got {overflow}"
    assert int(out.neighbours.builds) > 1, "expected the list rebuilt as the cloth moved"


def _grad_setup():
    """Small frictionless fold in float64 (stick/slip switching makes finite differences
    of a frictional fold meaningless at any step size)."""
    n, size = 8, 0.2
    cfg, cl, st = _fold_setup(jnp.float64, n=n, size=size, friction=0.0, strain_limit=None)
    sp = size / (n - 1)
    sc = c.PickPlace(approach_steps=0, lift_steps=300, move_steps=800, lower_steps=300,
                     settle_steps=300, lift_height=0.05, radius=0.5 * sp)
    goal = np.asarray(cl.rest_pos).copy()
    goal[:, :2] = size - goal[:, 1::-1]  # a fixed target: the cloth mirrored
    return cfg, cl, st, sc, jnp.asarray(goal), jnp.array([0.9 * size, 0.9 * size, sp])


def test_fold_loss_gradient_wrt_place_matches_finite_differences():
    with jax.enable_x64(True):
        cfg, cl, st, sc, goal, p0 = _grad_setup()

        def loss(place):
            out = c.pick_and_place(cfg, cl, st, jnp.zeros(3, jnp.float64), place, sc)
            return jnp.mean(jnp.sum((out.x - goal) ** 2, -1))
        g = np.asarray(jax.jit(jax.grad(loss))(p0))
        f = jax.jit(loss)
        eps = 1e-4
        # horizontal components: the place height decides when the layers touch (contact
        # events), so its derivative is not smooth on the scale of any usable FD step
        for k in (0, 1):
            e = jnp.zeros(3, jnp.float64).at[k].set(eps)
            fd = float((f(p0 + e) - f(p0 - e)) / (2 * eps))
            assert abs(g[k] - fd) <= 0.02 * abs(fd), \
                f"d loss / d place[{k}]: expected FD {fd:.6g}, got autodiff {g[k]:.6g}"
        assert np.all(np.isfinite(g)), f"expected a finite gradient, got {g}"


def test_checkpointed_rollout_gives_identical_values_and_gradients():
    cfg, cl, st = _fold_setup(n=6, size=0.1)
    st = c.grasp(st, 0, (0.0, 0.0, 0.0), 0.01)

    def loss(v, seg):
        gv = jnp.broadcast_to(v, (300, 1, 3))
        out = c.rollout(cfg, cl, st, 300, segment=seg, gripper_vel=gv)
        return jnp.sum(out.x[:, 2] ** 2) + jnp.sum(out.x[:, 0])
    v0 = jnp.array([0.05, 0.05, 0.1])
    l1, g1 = jax.jit(jax.value_and_grad(lambda v: loss(v, None)))(v0)
    l2, g2 = jax.jit(jax.value_and_grad(lambda v: loss(v, 70)))(v0)  # 4 segments + 20
    # equal up to float rounding: XLA fuses the substep differently inside the
    # checkpointed segments (measured: 1 ulp of the loss, 1.3e-6 of the gradient after
    # 300 float32 substeps)
    np.testing.assert_allclose(float(l2), float(l1), rtol=1e-6,
                               err_msg="expected the checkpointed loss equal to the plain one")
    np.testing.assert_allclose(g2, g1, rtol=1e-5, atol=1e-9,
                               err_msg="expected checkpointed gradients equal to plain ones")


def _short_fold(place, cfg, cl, st):
    sc = c.PickPlace(approach_steps=10, lift_steps=100, move_steps=200, lower_steps=100,
                     settle_steps=100, lift_height=0.03, radius=0.01)
    return c.pick_and_place(cfg, cl, st, jnp.zeros(3), place, sc).x


def test_vmap_batch_equals_loop():
    cfg, cl, st = _fold_setup(n=6, size=0.1)
    places = jnp.array([[0.08, 0.08, 0.02], [0.05, 0.09, 0.02], [0.09, 0.03, 0.02]])
    f = jax.jit(lambda p: _short_fold(p, cfg, cl, st))
    batch = jax.jit(jax.vmap(lambda p: _short_fold(p, cfg, cl, st)))(places)
    for b in range(3):  # atol: roundoff differs with the batch size and contacts amplify it
        np.testing.assert_allclose(batch[b], f(places[b]), rtol=0, atol=1e-4,
                                   err_msg=f"expected vmap row {b} to equal the loop")
    spread = float(jnp.max(jnp.abs(batch[0] - batch[1])))
    assert spread > 1e-3, f"expected different places to give different folds, got {spread}"


def test_same_inputs_same_result():
    cfg, cl, st = _fold_setup(n=6, size=0.1)
    f = jax.jit(lambda p: _short_fold(p, cfg, cl, st))
    p = jnp.array([0.08, 0.08, 0.02])
    a, b = np.asarray(f(p)), np.asarray(f(p))
    assert np.array_equal(a, b), f"expected bitwise equal runs, max diff {np.abs(a - b).max()}"


@pytest.mark.parametrize("bad", ["pick", "place"])
def test_nan_pick_or_place_in_macro_is_a_noop_under_jit(bad):
    cfg, cl, st = _fold_setup(n=6, size=0.1)
    sc = c.PickPlace(approach_steps=10, lift_steps=20, move_steps=20, lower_steps=20,
                     settle_steps=10, radius=0.01)
    nan = jnp.array([jnp.nan, 0.0, 0.0])
    ok = jnp.array([0.05, 0.05, 0.02])
    pick, place = (nan, ok) if bad == "pick" else (jnp.zeros(3), nan)
    out = jax.jit(lambda p, q: c.pick_and_place(cfg, cl, st, p, q, sc))(pick, place)
    ref = c.rollout(cfg, cl, st, sc.n_steps)
    assert bool(jnp.all(jnp.isfinite(out.x))), "expected finite positions, got NaN"
    diff = float(jnp.max(jnp.abs(out.x - ref.x)))
    assert diff < 1e-7, f"expected an untouched cloth, got max diff {diff}"
