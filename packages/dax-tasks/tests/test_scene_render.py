"""The oblique scene pictures for people (dax_tasks.viz.scene, re-exported by dax_tasks.viz):
projection, depth order, a folded cloth's two sides, the goal overlay, determinism, the
GIF/PNG/filmstrip writers and bad input. Tiny synthetic scenes, so the whole file runs in
seconds; the real tasks' pictures are made by ``python -m benchmarks.scene_demo``."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from PIL import Image

from dax_tasks import Env, TaskSpec, viz
from dax_tasks.core.env import EnvState
from dax_tasks.viz import SceneView, filmstrip, goal_frame, save_animation, scene_frames

RES = (320, 240)
RED, BLUE, GREEN = (0.9, 0.1, 0.1), (0.1, 0.1, 0.9), (0.1, 0.7, 0.1)


class Still(Env):
    """Points (or a mesh) that do not move: physics = {"x": (N, 3), "ee": (3,)}."""

    substep_dt = 0.01

    def __init__(self, points, colors=None, faces=None, ee=(5.0, 5.0, 0.0)):
        super().__init__(TaskSpec(name="still", horizon=1, action_kind="velocity",
                                  substeps=1, action_low=(-1.0,), action_high=(1.0,)))
        self._x = np.asarray(points, np.float32)
        self._colors = None if colors is None else np.asarray(colors, np.float32)
        self._faces = faces
        self._ee = np.asarray(ee, np.float32)

    def default_physics_params(self):
        return {}

    def init(self, key, params):
        return {"x": jnp.asarray(self._x), "ee": jnp.asarray(self._ee)}

    def apply_action(self, physics, action, params):
        return physics

    def object_points(self, physics):
        return physics["x"]

    def end_effector(self, physics):
        return physics["ee"]

    def canonical_goal(self):
        return self._x

    @property
    def object_faces(self):
        return self._faces

    @property
    def object_colors(self):
        return self._colors


def stacked(*point_sets, ee=(5.0, 5.0, 0.0)):
    """An EnvState with a leading time axis, one step per point set."""
    x = jnp.asarray(np.stack(point_sets), jnp.float32)
    t = len(point_sets)
    return EnvState(physics={"x": x, "ee": jnp.tile(jnp.asarray(ee, jnp.float32), (t, 1))},
                    t=jnp.arange(t, dtype=jnp.int32), finite=jnp.ones(t, bool))


# A camera 2 m in front of the origin (-y), looking along +y: x is right, z is up, and the
# image plane at unit distance spans 1 x 0.75, so f = 320 px for a 320 x 240 picture.
FRONT = SceneView(eye=(0.0, -2.0, 0.0), target=(0.0, 0.0, 0.0),
                  window=(-0.5, 0.5, -0.375, 0.375), table_z=-1.0, grid=0.1, radius=0.02,
                  marker=0.01, shadow_box=(-1.0, 1.0, -1.0, 1.0))


def test_projection_puts_a_known_point_at_the_expected_pixel():
    # col = 159.5 + 320 x / 2, row = 119.5 - 320 z / 2
    p = np.asarray([0.253125, 0.0, 0.121875])
    row, col, depth = FRONT.project(p, RES)
    assert (row, col, depth) == pytest.approx((100.0, 200.0, 2.0))
    f, r0, c0 = FRONT.intrinsics(RES)
    assert (f, r0, c0) == pytest.approx((320.0, 119.5, 159.5))
    env = Still([p], colors=[RED]).with_goal([p])
    img = scene_frames(env, stacked([p]), view=FRONT, res=RES, goal=False)[0]
    assert img.shape == (240, 320, 3) and img.dtype == np.uint8
    r, g, b = (int(c) for c in img[100, 200])
    assert r > 80 and r > 3 * max(g, b), img[100, 200]           # the red sphere
    r, g, b = (int(c) for c in img[100, 230])
    assert not r > 3 * max(g, b)                                  # 30 px away: not red


def test_the_nearer_sphere_hides_the_farther_one():
    d = np.asarray([0.1, 1.0, 0.05])
    d /= np.linalg.norm(d)
    eye = np.asarray(FRONT.eye)
    near, far = eye + 1.6 * d, eye + 2.4 * d  # on one ray: the same pixel
    (r1, c1, _), (r2, c2, _) = FRONT.project(near, RES), FRONT.project(far, RES)
    assert (r1, c1) == pytest.approx((r2, c2))
    pix = int(round(r1)), int(round(c1))
    for order in ([near, far], [far, near]):  # the drawing order does not matter
        colors = [RED, BLUE] if order[0] is near else [BLUE, RED]
        env = Still(order, colors=colors).with_goal(order)
        img = scene_frames(env, stacked(order), view=FRONT, res=RES, goal=False)[0]
        r, _, b = (int(c) for c in img[pix])
        assert r > 2 * b, (order, img[pix])


def strip_mesh(nx=9, ny=3, length=0.4, width=0.1):
    """A flat strip along x on the table (z = 0) as a triangle mesh (V, 3), faces (F, 3)."""
    x, y = np.meshgrid(np.linspace(0, length, nx), np.linspace(0, width, ny), indexing="ij")
    v = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], 1)
    faces = []
    for i in range(nx - 1):
        for j in range(ny - 1):
            a, b, c, d = i * ny + j, (i + 1) * ny + j, (i + 1) * ny + j + 1, i * ny + j + 1
            faces += [(a, b, c), (a, c, d)]
    return v, np.asarray(faces, np.int64)


def test_a_folded_cloth_shows_its_front_and_its_back():
    v, faces = strip_mesh()
    folded = v.copy()
    flap = v[:, 0] > 0.25                       # the last 15 cm folded back over the strip
    folded[flap, 0] = 0.5 - v[flap, 0]
    folded[flap, 2] = 0.01
    env = Still(v, colors=np.broadcast_to(GREEN, v.shape), faces=faces).with_goal(v)
    view = SceneView.for_env(env)
    img = scene_frames(env, stacked(v, folded), view=view, res=RES, goal=False)
    on_front = view.project([0.05, 0.05, 0.0], RES)[:2].round().astype(int)
    on_flap = view.project([0.2, 0.05, 0.01], RES)[:2].round().astype(int)
    front_px = img[1][tuple(on_front)].astype(int)
    back_px = img[1][tuple(on_flap)].astype(int)
    assert front_px[1] > 100 and front_px[0] < 60, front_px   # green: the front
    assert back_px[0] > 120 and back_px[2] < 175, back_px     # pale cream-green: the back
    flat_px = img[0][tuple(on_flap)].astype(int)              # unfolded: the front there
    assert flat_px[0] < 60, flat_px


def test_goal_overlay_is_faint_where_nothing_else_is():
    pts = np.asarray([[0.0, 0.0, 0.02], [0.02, 0.0, 0.02]])
    goal = pts + [0.2, 0.1, 0.0]
    env = Still(pts).with_goal(goal)
    view = SceneView.for_env(env)
    state = stacked(pts)
    with_goal = scene_frames(env, state, view=view, res=RES, goal=True)[0].astype(int)
    without = scene_frames(env, state, view=view, res=RES, goal=False)[0].astype(int)
    diff = np.abs(with_goal - without).max(-1)
    assert diff.max() > 10                                 # the goal is drawn
    assert diff.max() <= round(0.35 * 255)                 # but faintly (alpha 0.3)
    r, c = view.project(goal[0], RES)[:2].round().astype(int)
    assert diff[r, c] > 10                                 # where the goal is
    far_from_goal = np.ones_like(diff, bool)
    for g in goal:
        r, c = view.project(g, RES)[:2]
        rows, cols = np.ogrid[:RES[1], :RES[0]]
        far_from_goal &= (rows - r) ** 2 + (cols - c) ** 2 > 10 ** 2
    assert diff[far_from_goal].max() == 0                  # and nowhere else


def test_same_input_same_bytes_and_goal_frame():
    v, faces = strip_mesh()
    ee = (0.2, 0.05, 0.03)
    env = Still(v, colors=np.broadcast_to(GREEN, v.shape), faces=faces, ee=ee).with_goal(v)
    view = SceneView.for_env(env)
    a = scene_frames(env, stacked(v, v + [0, 0, 0.02], ee=ee), view=view, res=(64, 48))
    b = scene_frames(env, stacked(v, v + [0, 0, 0.02], ee=ee), view=view, res=(64, 48))
    assert a.shape == (2, 48, 64, 3) and a.tobytes() == b.tobytes()
    assert not np.array_equal(a[0], a[1])                  # the lifted strip looks different
    _, s0 = env.reset(jax.random.PRNGKey(0))
    g = goal_frame(env, s0, view, res=(64, 48))
    assert g.shape == (48, 64, 3) and g.dtype == np.uint8
    # the goal is the start here: the goal picture is the start without the overlay and
    # without the end effector's marker (and its shadow)
    c = scene_frames(env, stacked(v, ee=ee), view=view, res=(64, 48), goal=False)[0]
    rows, cols = np.nonzero(np.any(g != c, axis=-1))
    assert len(rows) > 0
    r, col = view.project(np.asarray(ee), (64, 48))[:2]
    assert np.all(np.hypot(rows - r, cols - col) < 10), (rows, cols, r, col)


def test_gif_round_trip_is_small_and_keeps_first_and_last(tmp_path):
    pts = np.asarray([[0.0, 0.0, 0.02], [0.03, 0.0, 0.02]])
    ee = (0.05, 0.0, 0.05)
    env = Still(pts, colors=[RED, BLUE], ee=ee).with_goal(pts + [0.09, 0.0, 0.0])
    states = stacked(*[pts + [0.01 * i, 0.0, 0.0] for i in range(10)], ee=ee)
    frames = scene_frames(env, states, res=(80, 60))
    path = save_animation(frames, tmp_path / "ep.gif", fps=8, max_frames=6)
    with Image.open(path) as im:
        assert im.size == (80, 60) and im.n_frames == 6 and im.info.get("loop") == 0
        im.seek(0)
        first = np.asarray(im.convert("RGB"), int)
        im.seek(5)
        last = np.asarray(im.convert("RGB"), int)
    assert np.abs(first - frames[0]).mean() < 4 and np.abs(last - frames[-1]).mean() < 4
    assert path.stat().st_size < 40_000
    assert list(viz.subsample(10, 4)) == [0, 3, 6, 9]
    strip = filmstrip(frames, k=4, goal_frame=frames[0])
    assert strip.shape == (60, 5 * 80, 3) and strip.dtype == np.uint8
    assert filmstrip(frames, k=3).shape == (60, 3 * 80, 3)
    png = viz.save_png(strip, tmp_path / "strip.png")
    with Image.open(png) as im:
        assert np.array_equal(np.asarray(im.convert("RGB")), strip)


def test_bad_input_raises_one_line_errors(tmp_path):
    pts = np.asarray([[0.0, 0.0, 0.02]])
    env = Still(pts).with_goal(pts)
    _, single = env.reset(jax.random.PRNGKey(0))
    cases = [
        (lambda: scene_frames(env, single), "time axis"),
        (lambda: scene_frames(env, stacked(pts), res=(0, 10)), "res"),
        (lambda: scene_frames(env, stacked(pts), res=(10.5, 10)), "res"),
        (lambda: scene_frames(env, stacked(pts), view="front"), "SceneView"),
        (lambda: scene_frames(env, single.replace(t=jnp.arange(3))), "leading time axis"),
        (lambda: scene_frames(env, np.zeros((3, 1, 3))), "EnvState"),
        (lambda: save_animation(np.zeros((2, 8, 8)), tmp_path / "a.gif"), r"\(H, W, 3\)"),
        (lambda: save_animation(np.zeros((2, 8, 8, 3), np.uint8), tmp_path / "a.png"),
         "GIF"),
        (lambda: save_animation(np.zeros((4, 8, 8, 3), np.uint8), tmp_path / "a.gif",
                                max_frames=1), "max_frames"),
        (lambda: filmstrip(np.zeros((3, 8, 8, 3), np.uint8), k=0), "k must"),
        (lambda: filmstrip(np.zeros((3, 8, 8, 3), np.uint8),
                           goal_frame=np.zeros((4, 8, 3), np.uint8)), "goal_frame"),
        (lambda: viz.save_png(np.zeros((8, 8, 3), np.uint8), tmp_path / "a.jpg"), "PNG"),
    ]
    for call, match in cases:
        with pytest.raises(ValueError, match=match) as err:
            call()
        assert "\n" not in str(err.value)
    assert not list(tmp_path.iterdir())  # nothing half-written
