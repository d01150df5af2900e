"""Pictures of the tasks.

* :mod:`.images`: top-down height maps and RGB images of a task's object points, pure JAX
  (jit and vmap them); they are the image observation modes' pixels. A :class:`Camera`
  fixes one env's view window once.
* :mod:`.scene`: oblique, shaded pictures of recorded episodes for people (NumPy).
* :mod:`.animation`: GIFs, filmstrips and PNGs of those pictures, written atomically.
"""

from .animation import filmstrip, save_animation, save_png, save_video, subsample
from .images import (
    GRIPPER_RGB,
    MIN_HEIGHT,
    TABLE_RGB,
    Camera,
    height_map,
    point_spacing,
    ramp_colors,
    record_episode,
    render,
    rgb_image,
    table_region,
    top_points,
    uv_colors,
    view_window,
)
from .scene import SceneView, goal_frame, scene_frames

__all__ = [
    "GRIPPER_RGB", "MIN_HEIGHT", "TABLE_RGB", "Camera", "SceneView", "filmstrip", "goal_frame",
    "height_map", "point_spacing", "ramp_colors", "record_episode", "render", "rgb_image",
    "save_animation", "save_png", "save_video", "scene_frames", "subsample", "table_region",
    "top_points", "uv_colors", "view_window",
]
