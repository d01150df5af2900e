"""The imitation-learning methods: Transporter networks learn the right pick and place
pixels on a synthetic picture task; ILD reproduces a smooth demonstration on the toy task;
demonstration files made for something else are refused in one line; the runner makes
the demonstrations, trains, evaluates and keeps the policies."""

import dataclasses

import h5py
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from algos_helpers import cheap_cloth_overrides

import dax_data
import dax_tasks
from dax_algos import actions, mlp_policy, registry, toy
from dax_algos.bench import grid, trained
from dax_algos.il import demos, ild, transporter
from dax_algos.method import NotApplicable

# ----------------------------------------------------------------------------- Transporter


def _synthetic(key, n, size=32):
    """Pictures (one height channel) of a tall 3 x 3 block (the object: pick its centre) and
    a low 5 x 5 pad (the target: place there) at random places."""
    kp, kq = jax.random.split(key)
    pick = jax.random.randint(kp, (n, 2), 3, size - 3)
    place = jax.random.randint(kq, (n, 2), 3, size - 3)
    ij = jnp.stack(jnp.meshgrid(jnp.arange(size), jnp.arange(size), indexing="ij"), -1)

    def picture(p, q):
        block = jnp.all(jnp.abs(ij - p) <= 1, -1) * 0.05
        pad = jnp.all(jnp.abs(ij - q) <= 2, -1) * 0.01
        return jnp.maximum(block, pad)[..., None]

    obs = jax.vmap(picture)(pick, place)
    return transporter.TransporterData(obs, pick.astype(jnp.float32),
                                       place.astype(jnp.float32), jnp.zeros(n), jnp.zeros(n))


SYNTH = transporter.TransporterConfig(image_size=32, goal_image=False, width=8, features=8,
                                      crop=5, n_rotations=4, train_steps=300, batch_size=8,
                                      learning_rate=3e-3)


def test_transporter_learns_pick_and_place_pixels_on_a_synthetic_task():
    train = _synthetic(jax.random.PRNGKey(0), 48)
    test = _synthetic(jax.random.PRNGKey(1), 16)
    params, metrics = jax.jit(lambda k, d: transporter.fit(k, d, SYNTH))(
        jax.random.PRNGKey(2), train)
    loss = np.asarray(metrics.loss)
    assert np.mean(loss[-20:]) < 0.3 * np.mean(loss[:20]), (loss[:5], loss[-5:])
    net = transporter.network(None, SYNTH)
    pick, place, _, _ = jax.jit(jax.vmap(
        lambda o: transporter.predict(net, params, o, SYNTH)))(test.obs)
    want_pick = np.round(np.asarray(transporter.to_grid(test.pick)))
    want_place = np.round(np.asarray(transporter.to_grid(test.place)))
    pick_ok = np.max(np.abs(np.asarray(pick) - want_pick), 1) <= 1
    place_ok = np.max(np.abs(np.asarray(place) - want_place), 1) <= 1
    assert pick_ok.mean() >= 0.9 and place_ok.mean() >= 0.9, (
        f"held-out pictures within one output pixel: pick {pick_ok.mean():.2f}, place "
        f"{place_ok.mean():.2f}")


@pytest.mark.parametrize("stride, k", [(1, 1), (1, 3), (2, 3)])
def test_matmul_conv_equals_xla_convolution(stride, k):
    # Full float32 on both sides: at JAX's default precision a GPU rounds the products'
    # inputs to TF32 and the two formulations then differ by 4e-3 (measured on an H100).
    with jax.default_matmul_precision("highest"):
        x = jax.random.normal(jax.random.PRNGKey(0), (2, 16, 16, 5))
        w = jax.random.normal(jax.random.PRNGKey(1), (k, k, 5, 7))
        want = jax.lax.conv_general_dilated(x, w, (stride, stride), "SAME",
                                            dimension_numbers=("NHWC", "HWIO", "NHWC"))
        got = transporter.matmul_conv(x, w, (stride, stride), "SAME")
        np.testing.assert_allclose(np.asarray(got), np.asarray(want), atol=2e-5)
        correlated = transporter.correlate(x[0], w[:, :, :, :3].transpose(3, 0, 1, 2))
        if k == 3:
            np.testing.assert_allclose(  # the transport's correlation = a "SAME" convolution
                np.asarray(correlated),
                np.asarray(jax.lax.conv_general_dilated(
                    x[:1], w[:, :, :, :3], (1, 1), "SAME",
                    dimension_numbers=("NHWC", "HWIO", "NHWC"))[0].transpose(2, 0, 1)), atol=2e-5)


def test_transporter_does_not_apply_to_low_level_tasks():
    with pytest.raises(NotApplicable, match="macro-action task"):
        registry.get("transporter").build(toy.point_reach(), registry.get(
            "transporter").config("quick"))


# ----------------------------------------------------------------------------- ILD


def _smooth_demo(env, key):
    """A demonstration of the toy task by a proportional controller whose actions stay
    inside the box (a policy can reproduce it exactly; a saturated one only in the limit)."""
    _, state = env.reset(key)

    def body(s, _):
        _, s2, _, _, _ = env.step(s, jnp.clip(-3.0 * s.physics, -0.5, 0.5))
        return s2, (env.object_points(s2.physics), env.end_effector(s2.physics))

    _, (pts, ee) = jax.lax.scan(body, state, None, length=env.horizon)
    first = (env.object_points(state.physics)[None], env.end_effector(state.physics)[None])
    return ild.Demonstration(jnp.concatenate([first[0], pts]),
                             jnp.concatenate([first[1], ee]), key)


def _trajectory(env, config, policy, key):
    act = ild.make_act(env, config)
    _, state = env.reset(key)

    def body(s, _):
        z = act(policy, mlp_policy.features(env.observe(s.physics), s.t, env.horizon))
        _, s2, _, _, _ = env.step(s, actions.to_action(env, z))
        return s2, env.object_points(s2.physics)

    return jax.lax.scan(body, state, None, length=env.horizon)[1]


def test_ild_reproduces_a_smooth_demonstration_on_the_toy_task():
    env = toy.point_reach(horizon=10)
    demo = _smooth_demo(env, jax.random.PRNGKey(7))
    config = ild.ILDConfig(total_env_steps=8000, num_envs=4, policy_hidden=(64, 64),
                           learning_rate=1e-2, max_grad_norm=None, starts="demo")
    train = jax.jit(ild.make_train(env, config))
    policy, metrics = train(jax.random.PRNGKey(0), env.default_params, demo)
    untrained, _ = jax.jit(ild.make_train(env, dataclasses.replace(
        config, total_env_steps=40, learning_rate=1e-9)))(
        jax.random.PRNGKey(0), env.default_params, demo)
    dev = lambda p: float(jnp.max(jnp.linalg.norm(  # noqa: E731
        _trajectory(env, config, p, demo.key) - demo.points[1:], axis=-1)))
    assert dev(untrained) > 0.05, "the untrained policy already follows the demonstration"
    assert dev(policy) < 0.005, (
        f"trained: the states deviate up to {dev(policy) * 1e3:.1f} mm from the "
        f"demonstration's (tolerance 5 mm over the 10 steps, start distance 0.3-0.6 m)")
    assert int(np.sum(metrics.nonfinite)) == 0


def test_ild_state_distance_weights_parts_as_documented():
    pts = jnp.zeros((3, 3))
    target = pts.at[:, 0].set(0.1)                      # every point 0.1 m off
    ee, target_ee = jnp.zeros(3), jnp.asarray([0.0, 0.2, 0.0])
    per_part = ild.ILDConfig(object_weight=2.0, effector_weight=0.5)
    assert float(ild.state_distance(pts, ee, target, target_ee, per_part)) == pytest.approx(
        2.0 * 0.01 + 0.5 * 0.04)
    flat = ild.ILDConfig(weighting="flat")
    # the end effector is one point of N + 1 = 4: its 0.04 m^2 counts a quarter
    assert float(ild.state_distance(pts, ee, target, target_ee, flat)) == pytest.approx(
        (3 * 0.01 + 0.04) / 4)
    with pytest.raises(ValueError, match="unknown weighting"):
        ild.ILDConfig(weighting="balanced")


def test_planar_fit_recovers_a_rigid_motion_and_moves_the_whole_demonstration():
    pts = jax.random.uniform(jax.random.PRNGKey(0), (30, 3), minval=-0.2, maxval=0.2)
    angle, shift = 0.7, jnp.asarray([0.11, -0.05])
    rot = jnp.asarray([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]],
                      jnp.float32)
    moved = pts.at[:, :2].set(pts[:, :2] @ rot.T + shift)
    fit_rot, fit_shift = ild.planar_fit(pts, moved)
    np.testing.assert_allclose(np.asarray(fit_rot), np.asarray(rot), atol=1e-5)
    np.testing.assert_allclose(np.asarray(fit_shift), np.asarray(shift), atol=1e-5)
    # every step and the end effector move alike; heights stay
    demo = ild.Demonstration(jnp.stack([pts, pts + 0.01]), jnp.zeros((2, 3)),
                             jax.random.PRNGKey(0))
    out = ild.move_demonstration(demo, fit_rot, fit_shift)
    np.testing.assert_allclose(np.asarray(out.points[0]), np.asarray(moved), atol=1e-5)
    np.testing.assert_allclose(np.asarray(out.points[:, :, 2]), np.asarray(demo.points[:, :, 2]))
    np.testing.assert_allclose(np.asarray(out.effector[0, :2]), np.asarray(shift), atol=1e-5)


def test_ild_targets_are_the_demonstration_or_it_moved_onto_each_start():
    env = toy.point_reach(horizon=4)
    demo = _smooth_demo(env, jax.random.PRNGKey(7))
    keys = jax.random.split(jax.random.PRNGKey(1), 3)
    _, state = dax_tasks.VmapWrapper(env, 3).reset(keys, env.default_params)
    none = ild.episode_targets(env, demo, state.physics, env.default_params, ild.ILDConfig())
    np.testing.assert_array_equal(np.asarray(none.points),
                                  np.broadcast_to(np.asarray(demo.points), (3, 5, 1, 3)))
    start = ild.episode_targets(env, demo, state.physics, env.default_params,
                                ild.ILDConfig(align="start"))
    # one point: the fit is the shift in the table plane that puts the demonstration's
    # start over each start (heights are not moved)
    starts = np.asarray(jax.vmap(env.object_points)(state.physics))
    np.testing.assert_allclose(np.asarray(start.points[:, 0, :, :2]), starts[..., :2],
                               atol=1e-6)
    offset = starts[:, 0, :2] - np.asarray(demo.points[0, 0, :2])
    np.testing.assert_allclose(np.asarray(start.points[:, :, 0, :2]),
                               np.asarray(demo.points[:, 0, :2])[None] + offset[:, None],
                               atol=1e-6)
    with pytest.raises(ValueError, match="unknown align"):
        ild.ILDConfig(align="object")
    # the toy task's distance does not align its goal: align="goal" is refused, by name
    with pytest.raises(ValueError, match="goal_pose.*point_reach has none"):
        ild.make_train(env, ild.ILDConfig(align="goal"))


class _SlidingReach(toy.PointReach):
    """The toy task with a goal that slides along x onto the object (Push-Rope's
    alignment: no rotation, the mean x offset)."""

    def goal_pose(self, x, goal):
        dx = jnp.mean(x[:, 0] - goal[:, 0])
        return jnp.eye(2, dtype=x.dtype), jnp.stack([dx, jnp.zeros_like(dx)])


def test_ild_goal_alignment_moves_the_demonstration_as_the_task_aligns_its_goal():
    base = toy.point_reach(horizon=4)
    env = _SlidingReach(base.spec).with_goal(base.canonical_goal())
    demo = _smooth_demo(base, jax.random.PRNGKey(7))
    keys = jax.random.split(jax.random.PRNGKey(1), 3)
    _, state = dax_tasks.VmapWrapper(env, 3).reset(keys, env.default_params)
    out = ild.episode_targets(env, demo, state.physics, env.default_params,
                              ild.ILDConfig(align="goal"))
    starts = np.asarray(jax.vmap(env.object_points)(state.physics))
    # slid along x only, by the starts' x offset from the demonstration's start; y and z kept
    dx = starts[:, 0, 0] - np.asarray(demo.points[0, 0, 0])
    np.testing.assert_allclose(np.asarray(out.points[..., 0]),
                               np.asarray(demo.points[..., 0])[None] + dx[:, None, None],
                               atol=1e-6)
    np.testing.assert_allclose(np.asarray(out.points[..., 1:]),
                               np.broadcast_to(np.asarray(demo.points[..., 1:]),
                                               out.points[..., 1:].shape), atol=1e-7)
    np.testing.assert_allclose(np.asarray(out.effector[..., 0]),
                               np.asarray(demo.effector[..., 0])[None] + dx[:, None],
                               atol=1e-6)


def test_goal_motion_composes_the_tasks_goal_poses():
    # a task whose goal pose is the rigid fit of the goal onto the object (the cloth's):
    # between two starts that differ by a rigid motion, the goal motion is that motion
    class Fit:
        def goal_pose(self, x, goal):
            return ild.planar_fit(goal, x)

    pts = jax.random.uniform(jax.random.PRNGKey(2), (20, 3), minval=-0.1, maxval=0.1)
    goal = pts.at[:, :2].set(pts[:, :2] @ jnp.asarray([[0.0, -1.0], [1.0, 0.0]]).T + 0.3)
    angle, shift = -0.4, jnp.asarray([0.02, 0.07])
    rot = jnp.asarray([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]],
                      jnp.float32)
    moved = pts.at[:, :2].set(pts[:, :2] @ rot.T + shift)
    got_rot, got_shift = ild.goal_motion(Fit(), pts, moved, goal)
    np.testing.assert_allclose(np.asarray(got_rot), np.asarray(rot), atol=1e-5)
    np.testing.assert_allclose(np.asarray(got_shift), np.asarray(shift), atol=1e-5)


# ----------------------------------------------------------------------------- files

SMALL = cheap_cloth_overrides(horizon=2)


@pytest.fixture(scope="module")
def demo_file(tmp_path_factory):
    """Two expert episodes of a coarse fold_cloth1 with height maps (64 px)."""
    path = tmp_path_factory.mktemp("demos") / "fold.h5"
    dax_data.generate("fold_cloth1", 2, 100, path, overrides=SMALL, progress=False,
                      obs=("state", "height"))
    return path


@pytest.fixture(scope="module")
def small_env():
    return dax_tasks.make("fold_cloth1", cache_goal=False, **SMALL)


def _one_line(err) -> str:
    text = str(err.value)
    assert "\n" not in text, text
    return text


def test_demonstrations_are_loaded_for_the_env_they_were_recorded_for(demo_file, small_env):
    config = transporter.TransporterConfig(demos=2, align_goal=False)
    data = transporter.load_data(small_env, config, demo_file)
    assert data.obs.shape == (2 * small_env.horizon, 64, 64, 2)
    # the pictures are what the policy sees: the observation wrapper at the same start
    obs, _ = jax.jit(transporter.observation_env(small_env, config).reset)(
        jax.random.PRNGKey(100))
    np.testing.assert_array_equal(np.asarray(data.obs[0]), np.asarray(obs))
    # with the goal pictured on the cloth's pose: every step's goal channel is the goal
    # aligned to that step's recorded cloth, the start's as the policy sees it
    aligned = transporter.TransporterConfig(demos=2)  # align_goal: the default
    data_a = transporter.load_data(small_env, aligned, demo_file)
    obs_a, _ = jax.jit(transporter.observation_env(small_env, aligned).reset)(
        jax.random.PRNGKey(100))
    np.testing.assert_allclose(np.asarray(data_a.obs[0]), np.asarray(obs_a), rtol=0,
                               atol=1e-6)
    assert not np.array_equal(np.asarray(data_a.obs[0, ..., 1]),
                              np.asarray(data_a.obs[1, ..., 1])), "one goal for every step"
    np.testing.assert_array_equal(np.asarray(data_a.obs[..., 0]), np.asarray(data.obs[..., 0]))


def test_demonstrations_of_another_task_spec_or_a_broken_file_are_refused(
        demo_file, small_env, tmp_path):
    config = transporter.TransporterConfig(demos=2)
    other_task = dax_tasks.make("unfold_cloth1", cache_goal=False,
                                **cheap_cloth_overrides("unfold_cloth1", horizon=2))
    with pytest.raises(ValueError) as err:
        transporter.load_data(other_task, config, demo_file)
    assert "demonstrations of task 'fold_cloth1', not 'unfold_cloth1'" in _one_line(err)
    other_spec = dax_tasks.make("fold_cloth1", cache_goal=False,
                                **{**SMALL, "substeps": 420})
    with pytest.raises(ValueError) as err:
        transporter.load_data(other_spec, config, demo_file)
    assert "recorded for another task spec" in _one_line(err)
    with pytest.raises(ValueError) as err:
        transporter.load_data(small_env, dataclasses.replace(config, rgb=True), demo_file)
    assert "holds no rgb pictures" in _one_line(err)
    with pytest.raises(ValueError) as err:
        transporter.load_data(small_env, dataclasses.replace(config, demos=3), demo_file)
    assert "holds 2 episodes, 3 needed" in _one_line(err)
    truncated = tmp_path / "truncated.h5"
    truncated.write_bytes(demo_file.read_bytes()[: demo_file.stat().st_size // 2])
    with pytest.raises(ValueError) as err:
        ild.load_data(small_env, truncated)
    assert str(truncated) in _one_line(err) and "truncated or corrupted" in str(err.value)
    flipped = tmp_path / "flipped.h5"
    flipped.write_bytes(demo_file.read_bytes())
    with h5py.File(flipped, "r") as f:
        ds = f["episodes/000000/height"]
        offset = ds.id.get_chunk_info(0).byte_offset
    raw = bytearray(flipped.read_bytes())
    raw[offset + 20] ^= 0x10
    flipped.write_bytes(bytes(raw))
    with pytest.raises(ValueError) as err:
        transporter.load_data(small_env, config, flipped)
    assert "corrupted" in _one_line(err)


# ----------------------------------------------------------------------------- runner


def test_runner_makes_demonstrations_trains_evaluates_and_keeps_policies(tmp_path,
                                                                          monkeypatch):
    monkeypatch.setenv("DAX_CACHE_DIR", str(tmp_path / "cache"))
    demo_dir = tmp_path / "demos"
    kw = dict(seeds=1, out=tmp_path / "out", quick=True, task_overrides={"fold_cloth1": SMALL},
              method_overrides={"transporter": dict(train_steps=20, n_eval=2, width=4,
                                                    features=4, crop=3, n_rotations=2),
                                "ild": dict(total_env_steps=16, num_envs=2, n_eval=2,
                                            policy_hidden=(16,))},
              cache_goal=False, progress=False, demo_dir=demo_dir)
    rows = grid.run_grid("fold_cloth1", "transporter,ild", **kw)
    assert [(r["method"], r["status"]) for r in rows] == [("transporter", "ok"),
                                                           ("ild", "ok")], rows
    files = sorted(p.name for p in demo_dir.glob("*.h5"))
    assert [f.split("-")[1] for f in files] == ["ild", "transporter"], files
    with dax_data.open_file(next(demo_dir.glob("*transporter*.h5"))) as f:
        assert len(f) == 10 and f.meta["generator"]["seed"] == 10_000
        assert f.image_modes == ("height", "rgb")
    stamps = {p: p.stat().st_mtime_ns for p in demo_dir.glob("*.h5")}
    env = dax_tasks.make("fold_cloth1", cache_goal=False, **SMALL)
    for method in ("transporter", "ild"):  # what the runner does again for another --out
        runnable = registry.get(method).build(env, registry.get(method).config(
            "quick", "fold_cloth1", **kw["method_overrides"][method]))
        assert demos.locate(env, runnable.demos, demo_dir, SMALL) in stamps
    assert {p: p.stat().st_mtime_ns for p in demo_dir.glob("*.h5")} == stamps, \
        "the demonstrations were recorded again instead of reused"
    for method in ("transporter", "ild"):
        path = tmp_path / "out" / "policies" / "fold_cloth1" / method / "seed0.msgpack"
        config = registry.get(method).config("quick", "fold_cloth1",
                                             **kw["method_overrides"][method])
        act, policy = trained.load_trained(path, env, method, config)
        assert policy.params is not None
        # replaying the saved policy rollout by rollout gives the row's score back
        rec = trained.evaluate_trained(path, env, method, 0)
        row = next(r for r in rows if r["method"] == method)
        assert rec["n_rollouts"] == 2 and abs(rec["mean"] - float(row["score"])) < 1e-5, (
            rec, row["score"])
    assert not (tmp_path / "out" / "learning_fold_cloth1.csv").read_text().count(
        "transporter"), "Transporter trains on demonstrations: no learning-curve rows"
