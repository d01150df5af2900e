"""Episode pictures written to files: looping GIFs, filmstrips and PNGs, each written
atomically (:mod:`dax_tasks.io`). Frames are ``(H, W, 3)`` uint8 images, e.g. from
:func:`dax_tasks.viz.scene_frames` or :func:`dax_tasks.viz.render`."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..io import atomic_write
from .scene import GOAL


def _check_frames(frames, who: str) -> list:
    frames = [np.asarray(f) for f in frames]
    if not frames:
        raise ValueError(f"{who} needs at least one frame")
    for f in frames:
        if f.ndim != 3 or f.shape[2] != 3 or f.dtype != np.uint8:
            raise ValueError(f"{who}: frames must be (H, W, 3) uint8 images, got {f.shape} "
                             f"{f.dtype}")
    if len({f.shape for f in frames}) > 1:
        raise ValueError(f"{who}: frames differ in size: {sorted({f.shape for f in frames})}")
    return frames


def subsample(n: int, max_frames: int | None) -> np.ndarray:
    """Indices of at most ``max_frames`` of ``n`` frames, evenly spaced, the first and the
    last included (all ``n`` when ``max_frames`` is ``None`` or at least ``n``)."""
    if max_frames is None or max_frames >= n:
        return np.arange(n)
    if max_frames < 2:
        raise ValueError(f"max_frames must be >= 2 (the first and last frames), got "
                         f"{max_frames}")
    return np.unique(np.rint(np.linspace(0, n - 1, max_frames)).astype(int))


def save_video(frames, path, fps: float = 10.0, max_frames: int | None = None,
               palette: str = "shared", colors: int = 256) -> Path:
    """Write ``frames`` (a sequence of (H, W, 3) uint8 images) to ``path`` as a looping
    animated GIF, atomically (a temporary file in the same directory, then renamed).

    ``max_frames`` keeps at most that many frames, evenly spaced with the first and last
    (:func:`subsample`; the frame time stays ``1/fps``). ``palette="shared"`` quantises
    every frame to one adaptive palette of ``colors`` (2 to 256) colours made from the
    frames together (small files, no flicker between frames); ``"per_frame"`` lets Pillow
    choose one per frame."""
    from PIL import Image

    path = Path(path)
    if path.suffix.lower() != ".gif":
        raise ValueError(f"save_video writes GIF files; got {path.name!r} (use a .gif name)")
    frames = _check_frames(frames, "save_video")
    if not fps > 0:
        raise ValueError(f"fps must be > 0, got {fps}")
    if isinstance(colors, bool) or not isinstance(colors, (int, np.integer)) or \
            not 2 <= colors <= 256:
        raise ValueError(f"colors must be a whole number from 2 to 256, got {colors!r}")
    if palette not in ("shared", "per_frame"):
        raise ValueError(f"palette must be 'shared' or 'per_frame', got {palette!r}")
    frames = [frames[i] for i in subsample(len(frames), max_frames)]
    if palette == "shared":
        # one palette from a strip of (up to 16 of) the frames, applied to all of them
        picks = [frames[i] for i in subsample(len(frames), 16)]
        ref = Image.fromarray(np.concatenate(picks, axis=0)).quantize(
            int(colors), method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE)
        images = [Image.fromarray(f).quantize(palette=ref, dither=Image.Dither.NONE)
                  for f in frames]
    else:
        images = [Image.fromarray(f) for f in frames]
    return atomic_write(path, lambda f: images[0].save(
        f, format="GIF", save_all=True, append_images=images[1:],
        duration=int(round(1000 / fps)), loop=0, optimize=False))


def save_animation(frames, path, fps: float = 8.0, max_frames: int | None = None,
                   colors: int = 64) -> Path:
    """A small looping GIF of ``frames`` ((T, H, W, 3) uint8, e.g. :func:`scene_frames`) at
    ``path``, atomically: one adaptive palette of ``colors`` colours for all frames (64:
    Pour-Water's expert episode, 40 frames at 320 x 240, takes 170 KiB against 240 KiB
    with 256, and looks the same), at most ``max_frames``
    frames (evenly spaced, first and last kept). :func:`save_video` with its GIF
    settings for episode pictures. (Like any GIF written by Pillow, identical consecutive
    frames are stored once, showing for their summed time.)"""
    return save_video(frames, path, fps=fps, max_frames=max_frames, palette="shared",
                      colors=colors)


def filmstrip(frames, k: int = 5, goal_frame=None,
              ) -> np.ndarray:
    """One (H, k W, 3) uint8 image, or (H, (k + 1) W, 3) with ``goal_frame``: ``k`` key
    frames of ``frames`` side by side (evenly spaced, the first and last included; all of
    them when there are fewer than ``k``), then ``goal_frame`` (H, W, 3) when given, framed
    in the goal overlay's green. A white line marks where each frame begins."""
    frames = _check_frames(frames, "filmstrip")
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 1:
        raise ValueError(f"k must be a whole number >= 1, got {k!r}")
    idx = subsample(len(frames), k) if k >= 2 else np.asarray([len(frames) - 1])
    h, w, _ = frames[0].shape
    parts = [frames[i].copy() for i in idx]
    if goal_frame is not None:
        g = np.asarray(goal_frame)
        if g.shape != (h, w, 3) or g.dtype != np.uint8:
            raise ValueError(f"goal_frame must be a ({h}, {w}, 3) uint8 image like the "
                             f"frames, got {g.shape} {g.dtype}")
        g = g.copy()
        b = max(1, min(h, w) // 60)
        green = np.round(255 * GOAL).astype(np.uint8)
        g[:b], g[-b:], g[:, :b], g[:, -b:] = green, green, green, green
        parts.append(g)
    for p in parts[1:]:
        p[:, 0] = 255
    return np.concatenate(parts, axis=1)


def save_png(image, path, optimize: bool = True) -> Path:
    """Write ``image`` ((H, W, 3) uint8) to ``path`` as a PNG, atomically. ``optimize``:
    Pillow's smallest (and slowest) encoding; pass ``False`` where many pictures are
    written."""
    from PIL import Image

    path = Path(path)
    if path.suffix.lower() != ".png":
        raise ValueError(f"save_png writes PNG files; got {path.name!r} (use a .png name)")
    img = _check_frames([image], "save_png")[0]
    return atomic_write(path, lambda f: Image.fromarray(img).save(f, format="PNG",
                                                                    optimize=optimize))
