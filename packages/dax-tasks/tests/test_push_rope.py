"""Push-Rope behaviour: jit/vmap, rewards, determinism, gradients, scripted pushes.

Uses the small configuration from conftest (50 substeps per action) except for one test
of the default configuration."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import dax_tasks
from conftest import Jitted
from dax_tasks.tasks import push_rope

FAR = np.asarray([0.5, 0.5, 0.1, 0.5, 0.5, 0.1], np.float32)  # a zero-length push, off rope


@pytest.fixture(scope="module")
def batched(task):
    return Jitted(task.env, batch_size=2)


@pytest.fixture(scope="module")
def grad_fn(task):
    def r_gt(x, action, state):
        state = state.replace(physics=state.physics.replace(x=x))
        return task.env.step(state, action)[4]["r_gt"]

    return jax.jit(jax.grad(r_gt, argnums=(0, 1)))


def test_reset_gives_observation_in_space_and_valid_state(task, reset0):
    obs, state = reset0
    assert obs.shape == task.observation_space.shape, f"got obs shape {obs.shape}"
    assert int(state.t) == 0 and bool(state.finite)
    assert state.physics.x.shape == task.goal.shape, (
        f"particles {state.physics.x.shape} vs goal {task.goal.shape}")
    n = state.physics.x.shape[0]
    assert 300 <= n <= 800, f"expected 300-800 rope particles, got {n}"


def test_step_reward_finite_and_in_unit_interval(task, reset0, expert):
    _, state = reset0
    for action in (FAR, expert(state)):
        obs, new, reward, done, info = task.step(state, action)
        r = float(reward)
        assert np.isfinite(r) and 0.0 <= r <= 1.0, f"expected r_gt in [0, 1], got {r}"
        assert bool(info["finite"]) and not bool(info["escaped"]), info
        assert int(new.t) == 1 and not bool(done)


def test_done_when_horizon_reached(task, reset0):
    _, state = reset0
    *_, done, info = task.step(state.replace(t=jnp.asarray(task.horizon - 1, jnp.int32)), FAR)
    assert bool(done) and int(info["t"]) == task.horizon, f"got done={done}, t={info['t']}"


def test_same_seed_same_trajectory(task, expert, check_same_seed_same_trajectory):
    check_same_seed_same_trajectory(task, expert)


def test_nan_action_under_jit_marks_info_not_finite(task, reset0):
    _, state = reset0
    bad = FAR.copy()
    bad[0] = np.nan
    # the pure step under jit, where values cannot be inspected
    *_, info = task.step(state, jnp.asarray(bad))
    assert not bool(info["finite"]), f"expected info['finite'] False, got {info['finite']}"


def test_batched_reset_and_step_match_single_envs(task, batched):
    keys = jax.random.split(jax.random.PRNGKey(7), 2)
    obs, state = batched.reset(keys)
    assert obs.shape == (2, *task.observation_space.shape)
    assert batched.batch_size == 2 and batched.action_space.shape == (6,)
    acts = np.stack([FAR, np.asarray(task.expert_action(
        jax.tree_util.tree_map(lambda v: v[1], state)))])
    _, new, reward, done, info = batched.step(state, acts)
    assert reward.shape == (2,) and done.shape == (2,)
    for i in range(2):
        _, s1 = task.reset(keys[i])
        _, _, r1, _, _ = task.step(s1, acts[i])
        assert float(reward[i]) == pytest.approx(float(r1), abs=1e-5), (
            f"env {i}: batched reward {float(reward[i])} vs single {float(r1)}")
    with pytest.raises(ValueError, match=r"\(2, 6\)"):
        batched.step(state, FAR)


def test_action_gradient_finite_and_nonzero_for_touching_push(task, reset0, expert, grad_fn):
    _, state = reset0
    gx, ga = grad_fn(state.physics.x, expert(state), state)
    assert bool(jnp.all(jnp.isfinite(ga))) and bool(jnp.all(jnp.isfinite(gx))), (ga, gx)
    assert float(jnp.max(jnp.abs(ga))) > 0.0, f"expected a non-zero action gradient, got {ga}"
    assert float(jnp.max(jnp.abs(gx))) > 0.0, "expected a non-zero state gradient"


def test_scripted_push_improves_reward_over_doing_nothing(task, expert):
    for seed in range(2):
        _, s = task.reset(jax.random.PRNGKey(seed))
        r_push = float(task.step(s, expert(s))[2])
        r_idle = float(task.step(s, FAR)[2])
        assert r_push > r_idle + 1e-3, (
            f"seed {seed}: expected the scripted push to beat doing nothing, "
            f"got r_gt {r_push:.4f} vs {r_idle:.4f}")


def test_contact_adjustment_moves_push_start_onto_rope(task, reset0):
    import dataclasses

    _, state = reset0
    x = state.physics.x
    raw = jnp.asarray([0.2, 0.2, 0.08, 0.3, 0.2, 0.08])
    on = task.env.push_start(state.physics, raw)
    off = push_rope.PushRope(dataclasses.replace(task.spec, contact_adjustment=False)
                             ).push_start(state.physics, raw)
    np.testing.assert_array_equal(np.asarray(off), np.asarray(raw[:3]))
    scene = task.spec.scene
    gap = float(jnp.min(jnp.linalg.norm(x[:, :2] - on[:2], axis=1)))
    reach = scene.pusher_radius + 2 * scene.rope_radius
    assert gap <= reach + 1e-6, f"expected the adjusted start within {reach} m, got {gap}"
    assert float(jnp.linalg.norm(on - raw[:3])) > 0.01, f"start did not move: {on} vs {raw}"
    assert float(on[2]) <= float(jnp.max(x[:, 2])) + 1e-6, "tip height was not lowered"


def test_aux_weight_adds_end_effector_term(task, reset0):
    params = task.default_params.replace(aux_weight=1.0)
    _, state = reset0
    _, _, reward, _, info = task.step(state, FAR, params)
    want = float(info["r_gt"]) + float(info["r_aux"])
    assert float(reward) == pytest.approx(want, rel=1e-6), f"expected {want}, got {reward}"
    assert 0.0 < float(info["r_aux"]) <= 1.0


def test_default_configuration_steps_finite_without_escaping():
    task = Jitted(dax_tasks.make("push_rope"))
    _, state = task.reset(jax.random.PRNGKey(0))
    _, _, reward, _, info = task.step(state, task.expert_action(state))
    assert bool(info["finite"]) and not bool(info["escaped"]), info
    assert 0.0 <= float(reward) <= 1.0


def test_expert_hook_matches_expert_action_and_batches(task, reset0, expert, batched):
    _, state = reset0
    np.testing.assert_array_equal(np.asarray(task.expert_action(state)),
                                  np.asarray(expert(state)))
    _, states = batched.reset(jax.random.PRNGKey(0))
    actions = batched.expert_action(states)
    assert actions.shape == (2, 6), f"got {actions.shape}"
    assert all(batched.action_space.contains(np.asarray(a)) for a in actions)


def test_long_push_gradient_is_finite():
    """Regression: at 160+ substeps some pushes gave NaN action gradients (a grid node
    with a vanishing mass: its reverse-mode derivative overflowed). Fixed in dax-physics by
    treating nodes below a millionth of a particle's mass as empty."""
    env = dax_tasks.make("push_rope", substeps=160)
    _, state = jax.jit(env.reset)(jax.random.PRNGKey(0))
    a = jnp.asarray([0.401, 0.214, 0.089, 0.188, 0.131, 0.095])
    g = jax.jit(jax.grad(lambda a: env.step(state, a)[4]["r_gt"]))(a)
    assert bool(jnp.all(jnp.isfinite(g))), g
    assert float(jnp.max(jnp.abs(g))) > 0.0


def test_starts_span_the_documented_ranges_inside_the_start_square(task):
    """Over 32 seeds: headings fill ±heading_range, every particle lies inside the start
    square (so the pusher can reach behind it), the rope sits at most offset_range across
    the goal line and anywhere along it."""
    scene = task.spec.scene
    keys = jax.random.split(jax.random.PRNGKey(11), 32)
    heading = np.asarray(jax.vmap(task.env.start_heading)(keys))
    x = np.asarray(jax.vmap(lambda k: task.reset(k)[1].physics.x)(keys))
    h = scene.heading_range
    assert np.all(np.abs(heading) <= h) and heading.min() < -0.7 * h and \
        heading.max() > 0.7 * h, f"headings {heading} should fill ±{h} rad"
    rel = x[..., :2] - np.asarray(scene.centre)
    assert np.all(np.abs(rel) <= scene.start_half + 1e-6), (
        f"a particle {np.abs(rel).max():.4f} m from the centre, square ±{scene.start_half}")
    centroid = rel.mean(1)
    across, along = centroid[:, 1], centroid[:, 0]
    off = scene.offset_range
    assert np.all(np.abs(across) <= off + 1e-3), f"offsets across the line {across}"
    assert across.min() < -0.5 * off and across.max() > 0.5 * off, (
        f"offsets across the line {across} should spread over ±{off} m")
    # the square leaves a straight rope along the line ±5.5 cm of room
    assert along.max() - along.min() > 0.08, f"centres along the line {along} barely move"


def test_a_start_square_the_pusher_cannot_reach_behind_is_refused():
    import dataclasses

    scene = dataclasses.replace(push_rope.PUSH_ROPE.scene, start_half=0.19)
    with pytest.raises(ValueError, match="cannot reach behind"):
        push_rope.PushRope(dataclasses.replace(push_rope.PUSH_ROPE, scene=scene))


def test_distance_ignores_a_slide_along_the_goal_line_only(task, reset0):
    """The goal slid 5 cm along its line (x) is at D = 0; moved 5 cm across it (y), at
    D = 5 cm; turned by 0.2 rad about its centre, at the mean distance the turn moves its
    particles."""
    _, state = reset0
    goal = task.default_params.goal

    def dist(x):
        return float(task.env.distance(state.physics.replace(x=x), goal))

    assert dist(goal.at[:, 0].add(0.05)) == pytest.approx(0.0, abs=1e-5)
    assert dist(goal.at[:, 1].add(0.05)) == pytest.approx(0.05, abs=1e-5)
    c, s = np.cos(0.2), np.sin(0.2)
    rel = goal[:, :2] - goal[:, :2].mean(0)
    turned = goal.at[:, :2].set(goal[:, :2].mean(0) + rel @ jnp.asarray([[c, s], [-s, c]]))
    want = float(jnp.mean(jnp.linalg.norm(turned - goal, axis=1)))
    assert dist(turned) == pytest.approx(want, rel=1e-4), f"turned: want D {want}"
