"""Image observations and rendering: a top-down height map and a top-down RGB picture of
a task's object points and end effector, pure JAX (jit and vmap them); :func:`render` and
:func:`record_episode` give NumPy frames of an env's states (written to files by
:mod:`dax_tasks.viz.animation`).

The picture covers a fixed square *view window* of the table per task
(:func:`view_window`): the box around the goal, the start of an episode and the end
effector, padded. Pixel ``(i, j)`` covers ``x`` in column ``j`` (left to right) and ``y``
in row ``i`` (top row = largest ``y``), so the image is the scene seen from above with x to
the right and y up.

* :func:`height_map` ``(H, W)`` float32 [m]: the largest height of an object point above the
  view's base height ``z0`` in each pixel (0 where there is none); occupied pixels are at
  least ``1e-4`` m, so an object lying flat on the table still shows.
* :func:`rgb_image` ``(H, W, 3)`` uint8: a grey table, the object and the end effector as
  a red square. The object is shaded from dark blue (low) to light blue (``shade_height``
  above ``z0`` or more), or, given a colour per point (its *texture*, a task's
  ``object_colors``: a cloth's colours vary across it so its corners differ, a rope's
  along it, a liquid's by material), each pixel takes the colour of the highest point
  over it, brightened with height. A height map cannot tell a cloth's four corners or a
  rope's two ends apart; the texture can, as a printed cloth does in a camera picture.

A :class:`Camera` fixes the view window and the points' splat radius of one env (host
side, once); its ``height`` and ``rgb`` are pure and are what the ``height``, ``rgb`` and
``rgbd`` observation modes (:class:`dax_tasks.core.wrappers.ObservationMode`),
:func:`render` and the Gymnasium adapter show.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

#: Smallest height [m] an occupied pixel of the height map gets.
MIN_HEIGHT = 1e-4
TABLE_RGB = (205, 200, 190)
LOW_RGB = (25, 55, 150)
HIGH_RGB = (140, 200, 255)
GRIPPER_RGB = (220, 30, 30)


def view_window(points, extra=(), pad: float = 0.25, margin: float = 0.02):
    """``(x0, x1, y0, y1, z0)`` [m]: a square box in the table plane around ``points``
    (M, 3) and the ``extra`` points, padded by ``pad`` x its size plus ``margin``; ``z0`` is
    the lowest z of ``points`` (NumPy; computed once per task)."""
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    allp = np.concatenate([pts] + [np.asarray(e, np.float64).reshape(-1, 3) for e in extra])
    lo, hi = allp[:, :2].min(0), allp[:, :2].max(0)
    centre = 0.5 * (lo + hi)
    half = 0.5 * float(np.max(hi - lo)) * (1.0 + pad) + margin
    return (float(centre[0] - half), float(centre[0] + half), float(centre[1] - half),
            float(centre[1] + half), float(pts[:, 2].min()))


def table_region(env) -> np.ndarray:
    """The corners (4, 3) [m] of the table region where the env's object may start (the
    env's ``start_region()`` if it has one, e.g. Push-Rope's start square; a cloth task's
    ``scene.table_half``; the object lies anywhere in it), or no points (0, 3), so that
    every start is in view."""
    region = getattr(env.unwrapped, "start_region", None)
    if region is not None:
        return np.asarray(region(), np.float64).reshape(-1, 3)
    half = getattr(getattr(env.unwrapped.spec, "scene", None), "table_half", None)
    if half is None:
        return np.zeros((0, 3))
    return np.asarray([[sx * half, sy * half, 0.0] for sx in (-1, 1) for sy in (-1, 1)])


def _pixels(points, window, res: int):
    x0, x1, y0, y1, _ = window
    # one subtraction and one multiplication by a host constant: with a division XLA may
    # evaluate it differently in two programs (a reciprocal), and a point on a pixel
    # boundary (the parked gripper at the centre of a symmetric view) lands in another pixel
    u = (points[:, 0] - x0) * (res / (x1 - x0))
    v = (points[:, 1] - y0) * (res / (y1 - y0))
    inside = (u >= 0) & (u < res) & (v >= 0) & (v < res)
    col = jnp.floor(u).astype(jnp.int32)
    row = res - 1 - jnp.floor(v).astype(jnp.int32)
    return row, col, inside


def point_spacing(points) -> float:
    """The points' typical spacing [m]: the median distance to the 4th-nearest neighbour
    (a cloth vertex's grid neighbours; for randomly sampled particles it is robust to the
    close pairs that make the nearest-neighbour distance small) (NumPy)."""
    p = np.asarray(points, np.float64)[:2000]
    d = np.linalg.norm(p[:, None] - p[None], axis=-1)
    np.fill_diagonal(d, np.inf)
    k = min(3, len(p) - 2)
    return float(np.median(np.sort(d, axis=1)[:, max(k, 0)])) if len(p) > 1 else 0.0


def _splat(points, window, res: int, radius: float):
    """The pixels each point covers: ``(flat, ok, h)`` with ``flat`` (N, K) flat pixel
    indices, ``ok`` (N, K) whether the pixel is inside the image, ``h`` (N,) the point's
    height above ``window[4]`` (at least :data:`MIN_HEIGHT`)."""
    row, col, inside = _pixels(points, window, res)
    h = jnp.maximum(points[:, 2] - window[4], MIN_HEIGHT)
    pix = (window[1] - window[0]) / res
    k = int(np.ceil(radius / pix))
    di, dj = np.meshgrid(np.arange(-k, k + 1), np.arange(-k, k + 1), indexing="ij")
    keep = (di ** 2 + dj ** 2) * pix * pix <= max(radius, 0.5 * pix) ** 2
    di, dj = jnp.asarray(di[keep]), jnp.asarray(dj[keep])
    r = row[:, None] + di[None]
    c = col[:, None] + dj[None]
    ok = (r >= 0) & (r < res) & (c >= 0) & (c < res) & inside[:, None]
    flat = jnp.clip(r, 0, res - 1) * res + jnp.clip(c, 0, res - 1)
    return flat, ok, h


def _height_flat(flat, ok, h, res: int):
    val = jnp.where(ok, h[:, None], 0.0)
    return jnp.zeros(res * res, jnp.float32).at[flat.ravel()].max(val.ravel())


def height_map(points, window, res: int = 64, radius: float = 0.0):
    """``(res, res)`` float32: the highest object point above ``window[4]`` per pixel [m].
    Each point covers the pixels within ``radius`` [m] of it (a cloth's vertices or a
    liquid's particles then cover the surface between them)."""
    points = jnp.asarray(points, jnp.float32)
    flat, ok, h = _splat(points, window, res, radius)
    return _height_flat(flat, ok, h, res).reshape(res, res)


def top_points(points, window, res: int = 64, radius: float = 0.0):
    """``(height, index)``: the height map (:func:`height_map`) and, per pixel, the index of
    the highest point covering it (the largest index among equally high ones, so the
    picture does not depend on the order of a scatter), -1 where there is none."""
    points = jnp.asarray(points, jnp.float32)
    flat, ok, h = _splat(points, window, res, radius)
    top = _height_flat(flat, ok, h, res)
    idx = jnp.broadcast_to(jnp.arange(points.shape[0], dtype=jnp.int32)[:, None], flat.shape)
    wins = ok & (h[:, None] >= top[flat])
    index = jnp.full(res * res, -1, jnp.int32).at[flat.ravel()].max(
        jnp.where(wins, idx, -1).ravel())
    return top.reshape(res, res), index.reshape(res, res)


def rgb_image(points, end_effector, window, res: int = 64, radius: float = 0.0,
              shade_height: float = 0.05, marker: int | None = None, colors=None):
    """``(res, res, 3)`` uint8: table, object, end effector in red (none if
    ``end_effector`` is ``None``). Without ``colors`` the
    object is shaded by height (dark to light blue); with ``colors`` (N, 3) in [0, 1] (a
    colour per point) each pixel shows the colour of the highest point over it, scaled
    from 0.7 (on the table) to 1.0 (``shade_height`` up or more)."""
    if colors is None:
        hm = height_map(points, window, res, radius)
        s = jnp.clip(hm / shade_height, 0.0, 1.0)[..., None]
        low, high = jnp.asarray(LOW_RGB, jnp.float32), jnp.asarray(HIGH_RGB, jnp.float32)
        obj = low + s * (high - low)
    else:
        colors = jnp.asarray(colors, jnp.float32)
        if colors.shape != (jnp.shape(points)[0], 3):
            raise ValueError(f"colors must be (N, 3) for {jnp.shape(points)[0]} points, got "
                             f"{colors.shape}")
        hm, index = top_points(points, window, res, radius)
        s = jnp.clip(hm / shade_height, 0.0, 1.0)[..., None]
        obj = 255.0 * colors[jnp.maximum(index, 0)] * (0.7 + 0.3 * s)
    img = jnp.where(hm[..., None] > 0, obj, jnp.asarray(TABLE_RGB, jnp.float32))
    if end_effector is None:
        return jnp.round(img).astype(jnp.uint8)
    ee = jnp.asarray(end_effector, jnp.float32).reshape(1, 3)
    row, col, inside = _pixels(ee, window, res)
    r, c = row[0], col[0]
    k = max(1, res // 32) if marker is None else marker
    rows, cols = jnp.arange(res)[:, None], jnp.arange(res)[None, :]
    mark = (jnp.abs(rows - r) <= k) & (jnp.abs(cols - c) <= k) & inside[0]
    img = jnp.where(mark[..., None], jnp.asarray(GRIPPER_RGB, jnp.float32), img)
    return jnp.round(img).astype(jnp.uint8)


def ramp_colors(s) -> np.ndarray:
    """(N, 3) colours in [0, 1] of points at positions ``s`` (N,) along an object (a rope's
    arc length, any unit): a ramp from orange (the smallest ``s``) to purple (the
    largest) (NumPy)."""
    s = np.asarray(s, np.float64)
    t = ((s - s.min()) / max(float(np.ptp(s)), 1e-12))[:, None]
    return ((1 - t) * np.asarray([0.95, 0.6, 0.1]) + t * np.asarray([0.45, 0.1, 0.65])
            ).astype(np.float32)


def uv_colors(uv) -> np.ndarray:
    """(N, 3) colours in [0, 1] of points at texture coordinates ``uv`` (N, 2) in [0, 1]:
    red grows with u, green with v, blue falls with u, so the four corners of a square are
    blue, red, cyan and yellow (NumPy)."""
    uv = np.clip(np.asarray(uv, np.float64), 0.0, 1.0)
    u, v = uv[:, 0], uv[:, 1]
    return np.stack([0.15 + 0.7 * u, 0.25 + 0.5 * v, 0.85 - 0.6 * u], 1).astype(np.float32)


@dataclasses.dataclass(frozen=True)
class Camera:
    """A top-down view of one env: ``window`` ``(x0, x1, y0, y1, z0)`` [m] (see
    :func:`view_window`) and ``radius`` [m], the disc each object point covers."""

    window: tuple
    radius: float

    @staticmethod
    def for_env(env, key=None, params=None) -> Camera:
        """The view around the goal, the start of the episode drawn from ``key`` (default
        ``PRNGKey(0)``) and its end effector; points cover 0.75 x their median spacing."""
        key = jax.random.PRNGKey(0) if key is None else key
        params = env.default_params if params is None else params
        with jax.ensure_compile_time_eval():
            _, state = jax.jit(env.reset)(key, params)
            pts = np.asarray(env.object_points(state.physics))
            ee = np.asarray(env.end_effector(state.physics))
        return Camera(view_window(pts, extra=(np.asarray(params.goal), ee,
                                              table_region(env))),
                      0.75 * point_spacing(pts))

    def height(self, points, res: int = 64):
        """``(res, res)`` float32 height map [m] (:func:`height_map`)."""
        return height_map(points, self.window, res, self.radius)

    def to_pixel(self, xy, res: int = 64):
        """Continuous pixel coordinates ``(row, col)`` (..., 2) of table points ``xy``
        (..., 2) [m] in a ``res``-pixel picture: pixel ``(i, j)``'s centre is ``(i, j)``,
        so rounding gives the pixel a point falls in (as :func:`height_map` splats it)."""
        x0, x1, y0, y1, _ = self.window
        xy = jnp.asarray(xy, jnp.float32)
        col = (xy[..., 0] - x0) * (res / (x1 - x0)) - 0.5  # as the pictures place them
        row = (y1 - xy[..., 1]) * (res / (y1 - y0)) - 0.5
        return jnp.stack([row, col], axis=-1)

    def to_table(self, pixel, res: int = 64):
        """The table point ``(x, y)`` (..., 2) [m] at continuous pixel coordinates
        ``(row, col)`` (..., 2); the inverse of :meth:`to_pixel`."""
        x0, x1, y0, y1, _ = self.window
        pixel = jnp.asarray(pixel, jnp.float32)
        x = x0 + (pixel[..., 1] + 0.5) / res * (x1 - x0)
        y = y1 - (pixel[..., 0] + 0.5) / res * (y1 - y0)
        return jnp.stack([x, y], axis=-1)

    def rgb(self, points, end_effector, res: int = 64, colors=None):
        """``(res, res, 3)`` uint8 picture (:func:`rgb_image`; ``colors`` the object's
        texture, e.g. ``env.object_colors``)."""
        return rgb_image(points, end_effector, self.window, res, self.radius, colors=colors)


def render(env, state, res: int = 256, camera: Camera | None = None) -> np.ndarray:
    """An RGB frame ``(res, res, 3)`` uint8 (NumPy) of ``state`` seen from above; a batch of
    states (leading axis) gives one frame per state."""
    camera = Camera.for_env(env) if camera is None else camera
    colors = env.object_colors
    frame = jax.jit(lambda p: camera.rgb(env.object_points(p), env.end_effector(p), res,
                                         colors))
    batched = np.ndim(state.t) == 1  # the step counter is a scalar per env
    return np.asarray(jax.vmap(frame)(state.physics) if batched else frame(state.physics))


def record_episode(env, policy=None, key=None, res: int = 128, params=None):
    """Frames (a list of (res, res, 3) uint8) of one episode of ``env`` (unbatched): the
    start and every step. ``policy(state) -> action``; default the task's scripted expert,
    or zero actions clipped into the bounds when it has none."""
    params = env.default_params if params is None else params
    if policy is None:
        if env.has_expert:
            policy = jax.jit(lambda s: env.expert_action(s, params))
        else:
            zero = np.clip(np.zeros(env.spec.action_dim, np.float32),
                           env.spec.action_low, env.spec.action_high)
            policy = lambda state: zero  # noqa: E731
    camera = Camera.for_env(env)
    key = jax.random.PRNGKey(0) if key is None else key
    step = jax.jit(env.step)
    _, state = jax.jit(env.reset)(key, params)
    frames = [render(env, state, res, camera)]
    for _ in range(env.horizon):
        _, state, _, _, _ = step(state, policy(state), params)
        frames.append(render(env, state, res, camera))
    return frames
