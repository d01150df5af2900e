"""Image observations (height map, RGB), rendering and GIF writing."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from PIL import Image

import dax_tasks
from dax_tasks import viz
from dax_tasks.core.wrappers import ObservationMode, VmapWrapper


def test_height_map_puts_points_where_they_are():
    window = (0.0, 1.0, 0.0, 1.0, 0.0)
    pts = jnp.asarray([[0.05, 0.95, 0.3], [0.95, 0.05, 0.1], [0.95, 0.05, 0.2],
                       [2.0, 2.0, 5.0]])  # the last is outside the window
    hm = np.asarray(viz.height_map(pts, window, res=10))
    assert hm[0, 0] == pytest.approx(0.3)          # top-left: small x, large y
    assert hm[9, 9] == pytest.approx(0.2)          # bottom-right keeps the highest point
    assert np.count_nonzero(hm) == 2
    flat = np.asarray(viz.height_map(jnp.asarray([[0.5, 0.5, 0.0]]), window, 10))
    assert flat.max() == pytest.approx(viz.MIN_HEIGHT)  # a point on the table still shows
    disc = np.asarray(viz.height_map(jnp.asarray([[0.55, 0.55, 0.1]]), window, 10, 0.2))
    assert 9 <= np.count_nonzero(disc) <= 16       # a 0.2 m disc covers about pi*2^2 pixels


@pytest.fixture(scope="module")
def fold():
    return dax_tasks.make("fold_cloth1", cache_goal=False)


@pytest.mark.parametrize("mode, shape, dtype", [
    ("height", (32, 32, 1), np.float32), ("rgb", (32, 32, 3), np.uint8),
    ("rgbd", (32, 32, 4), np.float32), ("particles", (122, 3), np.float32)])
def test_observation_modes_batched_under_jit(fold, mode, shape, dtype):
    env = ObservationMode(fold, mode, image_size=32)
    assert env.observation_space.shape == shape and env.observation_space.dtype == dtype
    obs, state = jax.jit(VmapWrapper(env, batch_size=2).reset)(jax.random.PRNGKey(0))
    assert obs.shape == (2, *shape) and obs.dtype == dtype, (obs.shape, obs.dtype)
    assert env.observation_space.contains(np.asarray(obs[0])), f"{mode} obs outside its space"
    if mode == "height":
        # the view frames the whole table region the cloth may start in (0.7 m square,
        # padded to 0.92 m), so the flat 0.3 m cloth covers about a tenth of it
        covered = float(jnp.mean(obs[0] > 0))
        assert 0.08 < covered < 0.5, covered
    if mode == "particles":
        np.testing.assert_array_equal(np.asarray(obs[0, :-1]), np.asarray(
            state.physics.x[0]))
    _, _, reward, _, _ = jax.jit(VmapWrapper(env, batch_size=2).step)(
        state, jnp.zeros((2, 6)) + jnp.asarray(fold.spec.action_low))
    assert reward.shape == (2,)


def test_render_gives_frames_with_the_gripper(fold):
    _, state = jax.jit(VmapWrapper(fold, batch_size=2).reset)(jax.random.PRNGKey(0))
    frames = viz.render(fold, state, res=32)
    assert frames.shape == (2, 32, 32, 3) and frames.dtype == np.uint8
    red = np.all(frames[0] == np.asarray(viz.GRIPPER_RGB, np.uint8), axis=-1)
    assert red.any(), "the gripper marker is missing"


def test_unknown_observation_mode_is_refused(fold):
    with pytest.raises(ValueError, match="unknown observation mode 'depth'"):
        ObservationMode(fold, "depth")
    with pytest.raises(ValueError, match="unknown observation mode"):
        dax_tasks.make("fold_cloth1", obs_mode="rgba")


def test_record_episode_and_gif(tmp_path):
    env = dax_tasks.make("fold_cloth1", cache_goal=False)
    frames = viz.record_episode(env, res=48)
    assert len(frames) == env.horizon + 1
    assert not np.array_equal(frames[0], frames[-1]), "the expert's fold changed nothing"
    path = viz.save_video(frames, tmp_path / "ep.gif", fps=5)
    with Image.open(path) as gif:
        assert gif.n_frames == len(frames) and gif.size == (48, 48)
    assert not list(tmp_path.glob(".*.tmp")), "temporary file left behind"
    with pytest.raises(ValueError, match="GIF"):
        viz.save_video(frames, tmp_path / "ep.mp4")
    with pytest.raises(ValueError, match="uint8"):
        viz.save_video([np.zeros((4, 4, 3), np.float32)], tmp_path / "bad.gif")


def test_textured_picture_shows_each_pixels_highest_point_in_its_colour():
    window = (0.0, 1.0, 0.0, 1.0, 0.0)
    pts = jnp.asarray([[0.05, 0.95, 0.01], [0.05, 0.95, 0.02], [0.95, 0.05, 0.0]])
    colors = np.asarray([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], np.float32)
    img = np.asarray(viz.rgb_image(pts, None, window, res=10, colors=colors))
    # top-left: the higher (green) point wins, brightened by its height (0.02 of 0.05)
    assert tuple(img[0, 0]) == (0, round(255 * (0.7 + 0.3 * 0.4)), 0), img[0, 0]
    assert tuple(img[9, 9]) == (0, 0, round(255 * (0.7 + 0.3 * viz.MIN_HEIGHT / 0.05)))
    assert tuple(img[5, 5]) == viz.TABLE_RGB  # no gripper marker without an effector
    with pytest.raises(ValueError, match=r"colors must be \(N, 3\) for 3 points"):
        viz.rgb_image(pts, None, window, res=10, colors=colors[:2])


def test_cloth_and_rope_textures_tell_their_ends_apart(fold):
    colors = fold.object_colors
    assert colors.shape == (121, 3) and colors.min() >= 0 and colors.max() <= 1
    corners = colors[[0, 10, 110, 120]]  # the four corners of the 11 x 11 mesh
    gaps = np.linalg.norm(corners[:, None] - corners[None], axis=-1)
    assert np.all(gaps + np.eye(4) > 0.3), f"two corners look alike: {gaps}"
    ramp = viz.ramp_colors(np.linspace(0.0, 0.24, 5))
    assert np.linalg.norm(ramp[0] - ramp[-1]) > 0.5


def test_goal_image_appends_the_goal_picture_and_pixels_map_to_the_table(fold):
    env = ObservationMode(fold, "rgbd", image_size=32, goal_image=True)
    obs, _ = jax.jit(env.reset)(jax.random.PRNGKey(0))
    assert obs.shape == (32, 32, 8) and env.observation_space.shape == (32, 32, 8)
    goal = np.asarray(env.goal_observation())
    # equal bits on CPU; on a GPU the jitted reset rounds the colours 1 ulp apart from the
    # eager call (2e-7)
    np.testing.assert_allclose(np.asarray(obs[..., 4:]), goal, rtol=0, atol=1e-6)
    changed = env.goal_observation(fold.default_params.replace(
        goal=fold.default_params.goal + jnp.asarray([0.05, 0.0, 0.0])))
    assert not np.array_equal(np.asarray(changed), goal), "the goal picture ignores params"
    with pytest.raises(ValueError, match="goal_image needs an image mode"):
        ObservationMode(fold, "state", goal_image=True)
    camera = env.camera
    xy = jnp.asarray([[0.1, -0.05], [-0.2, 0.2]])
    px = camera.to_pixel(xy, 32)
    np.testing.assert_allclose(np.asarray(camera.to_table(px, 32)), np.asarray(xy), atol=1e-6)
    # a point lands in the pixel the height map splats it into
    hm = np.asarray(viz.height_map(jnp.asarray([[0.1, -0.05, 0.03]]), camera.window, 32))
    row, col = np.round(np.asarray(px[0])).astype(int)
    assert hm[row, col] == pytest.approx(0.03 - camera.window[4])


def test_an_aligned_goal_picture_follows_the_cloth_pose(fold):
    """With ``align_goal`` the goal is pictured where the distance compares it (moved onto
    the cloth's pose): two starts at different poses show two goal pictures, each the
    picture of the goal aligned to that start's cloth; without it both show the same."""
    plain = ObservationMode(fold, "height", image_size=32, goal_image=True)
    aligned = ObservationMode(fold, "height", image_size=32, goal_image=True,
                              align_goal=True)
    pics = []
    for seed in (0, 1):
        obs, state = jax.jit(aligned.reset)(jax.random.PRNGKey(seed))
        x = fold.object_points(state.physics)
        want = plain.image(fold.aligned_goal(x, fold.default_params.goal))
        np.testing.assert_allclose(np.asarray(obs[..., 1]), np.asarray(want[..., 0]),
                                   rtol=0, atol=1e-6)
        pics.append(np.asarray(obs[..., 1]))
        np.testing.assert_array_equal(np.asarray(jax.jit(plain.reset)(
            jax.random.PRNGKey(seed))[0][..., 1]), np.asarray(plain.goal_observation())[..., 0])
    assert not np.array_equal(pics[0], pics[1]), "the aligned goal ignores the cloth's pose"
    with pytest.raises(ValueError, match="needs goal_image"):
        ObservationMode(fold, "height", goal_image=False, align_goal=True)
    with pytest.raises(ValueError, match="aligned_goal"):
        ObservationMode(dax_tasks.make("whip_rope", cache_goal=False), "height",
                        goal_image=True, align_goal=True)
    with pytest.raises(ValueError, match="object's points"):
        aligned.goal_observation()
