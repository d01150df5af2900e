"""Image observations (height map, RGB), rendering and GIF writing."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from PIL import Image

import dax_tasks
from dax_tasks import render


def test_height_map_puts_points_where_they_are():
    window = (0.0, 1.0, 0.0, 1.0, 0.0)
    pts = jnp.asarray([[0.05, 0.95, 0.3], [0.95, 0.05, 0.1], [0.95, 0.05, 0.2],
                       [2.0, 2.0, 5.0]])  # the last is outside the window
    hm = np.asarray(render.height_map(pts, window, res=10))
    assert hm[0, 0] == pytest.approx(0.3)          # top-left: small x, large y
    assert hm[9, 9] == pytest.approx(0.2)          # bottom-right keeps the highest point
    assert np.count_nonzero(hm) == 2
    flat = np.asarray(render.height_map(jnp.asarray([[0.5, 0.5, 0.0]]), window, 10))
    assert flat.max() == pytest.approx(render.MIN_HEIGHT)  # a point on the table still shows
    disc = np.asarray(render.height_map(jnp.asarray([[0.55, 0.55, 0.1]]), window, 10, 0.2))
    assert 9 <= np.count_nonzero(disc) <= 16       # a 0.2 m disc covers about pi*2^2 pixels


@pytest.fixture(scope="module")
def batched():
    return dax_tasks.make("fold_cloth1", batch_size=2, cache_goal=False)


def test_image_obs_batched_and_jittable(batched):
    _, state = batched.reset(jax.random.PRNGKey(0))
    images = batched.image_obs(state, res=32)
    assert images["height"].shape == (2, 32, 32) and images["height"].dtype == jnp.float32
    assert images["rgb"].shape == (2, 32, 32, 3) and images["rgb"].dtype == jnp.uint8
    # the flat cloth covers a good part of the view; the goal's folded triangle is higher
    covered = float(jnp.mean(images["height"][0] > 0))
    assert 0.15 < covered < 0.9, covered
    inside = jax.jit(lambda s: batched.image_obs(s, res=32)["height"].sum())(state)
    assert np.isfinite(float(inside))
    frames = batched.render(state, res=32)
    assert frames.shape == (2, 32, 32, 3) and frames.dtype == np.uint8
    red = np.all(frames[0] == np.asarray(render.GRIPPER_RGB, np.uint8), axis=-1)
    assert red.any(), "the gripper marker is missing"


def test_record_episode_and_gif(tmp_path):
    task = dax_tasks.make("fold_cloth1", cache_goal=False)
    frames = render.record_episode(task, res=48)
    assert len(frames) == task.horizon + 1
    assert not np.array_equal(frames[0], frames[-1]), "the expert's fold changed nothing"
    path = render.save_video(frames, tmp_path / "ep.gif", fps=5)
    with Image.open(path) as gif:
        assert gif.n_frames == len(frames) and gif.size == (48, 48)
    assert not list(tmp_path.glob(".*.tmp")), "temporary file left behind"
    with pytest.raises(ValueError, match="GIF"):
        render.save_video(frames, tmp_path / "ep.mp4")
    with pytest.raises(ValueError, match="uint8"):
        render.save_video([np.zeros((4, 4, 3), np.float32)], tmp_path / "bad.gif")
