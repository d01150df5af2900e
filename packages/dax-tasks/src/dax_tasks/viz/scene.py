"""Pictures of an episode for people: an oblique, shaded view of the table, the object,
the colliders and the goal, rasterised with a z-buffer in NumPy on the CPU (no GPU, no
display). The top-down splats of :mod:`dax_tasks.viz` are network inputs; these are for
looking at (reports, animations, filmstrips).

* :class:`SceneView` fixes the camera of one env once (host side, like
  :meth:`dax_tasks.viz.Camera.for_env`), so every frame of every method of a task is
  seen from the same place.
* :func:`scene_frames` ``(T, H, W, 3)`` uint8: one picture per state of a stacked episode
  (an :class:`~dax_tasks.EnvState` whose leaves have a leading time axis, as
  ``jax.lax.scan`` stacks them).
* :func:`goal_frame` ``(H, W, 3)`` uint8: the goal alone, drawn as the object would be.

What a picture shows, back to front:

* the table, a plane at the task's table height with a faint checker (one square per
  :attr:`SceneView.grid` metres) fading into the background far away, and the soft shadows
  of the object and the end effector cast by a light high above the back-left: a shadow
  lies further from its point the higher the point is, the height cue a single view lacks;
* particles (MPM tasks) as spheres (discs of the sphere's depth and normal, Lambert plus
  ambient shading), each in its point's colour (``env.object_colors``: a rope's ends, a
  liquid's materials);
* a cloth (``env.object_faces``) as its triangle mesh, smoothly shaded, two-sided: the
  front (the side facing up on the flat cloth) in the cloth's texture, the back a pale
  cream tint of it, so a folded layer (its back up) stands out from the layer under it;
* a dark outline where the kind of surface changes (object / table / front / back) or the
  depth jumps, so layers and crossings read as separate;
* the end effector as a small red sphere;
* kinematic colliders other than planes (the pour tasks' bowls, the push pusher) as
  translucent shaded glass (the nearest surface in front of the opaque scene blended at
  :data:`GLASS_ALPHA`) with their rims outlined, so the water inside stays visible;
* the goal as a faint green overlay drawn over everything: dots at (up to
  :data:`GOAL_DOTS` of) its points at alpha :data:`GOAL_ALPHA`, and for a cloth the goal
  mesh's outline at :data:`GOAL_EDGE_ALPHA`.

Pure NumPy after the states' points are taken out (one jitted, vmapped call per episode).
Deterministic: the same input gives the same bytes (ties in depth keep the drawing order).
"""

from __future__ import annotations

import dataclasses
import math
import weakref

import jax
import numpy as np

from .images import point_spacing, table_region

#: Colours (RGB in [0, 1]).
BACKGROUND = np.asarray([0.93, 0.94, 0.96])
TABLE = np.asarray([0.84, 0.82, 0.78])
PARTICLE = np.asarray([0.25, 0.5, 0.9])     # particles without object_colors
CLOTH_BACK = np.asarray([0.99, 0.95, 0.86])  # mixed into a cloth's back side
GLASS = np.asarray([0.82, 0.9, 0.98])
RIM = np.asarray([0.35, 0.4, 0.48])
MARKER = np.asarray([0.86, 0.12, 0.12])
GOAL = np.asarray([0.1, 0.75, 0.2])
#: Opacity of the goal overlay, its outline and the colliders' glass.
GOAL_ALPHA, GOAL_EDGE_ALPHA, GLASS_ALPHA = 0.3, 0.55, 0.3
#: At most this many goal points are drawn as dots (every k-th), so a dense goal (a
#: liquid's) stays a sprinkle that the object shows through.
GOAL_DOTS = 160
#: Light: direction towards it (world), ambient and diffuse shares.
LIGHT = np.asarray([-0.35, 0.3, 1.0]) / np.linalg.norm([-0.35, 0.3, 1.0])
AMBIENT, DIFFUSE = 0.45, 0.55
#: Darkest shadow (fraction of light removed) and the shadow's blur [m].
SHADOW, SHADOW_BLUR = 0.35, 0.006
#: Surface kinds in the kind buffer (outlines where they change).
_TABLE, _PARTICLE, _FRONT, _BACK, _MARKER = 0, 1, 2, 3, 4
_NEAR = 1e-3  # [m] nothing nearer the camera is drawn
#: The table is drawn this far [m] below its height, so a cloth lying on it is not
#: z-fighting with it.
TABLE_SINK = 2e-3
#: The cloth tasks have no self-collision, so the layers of a fold pass through each other
#: by millimetres; a folded-over layer shows its back, so a back-facing cloth surface wins
#: over a front-facing one up to this much [m] behind it (no speckles where layers meet).
LAYER_BIAS = 4e-3


# --------------------------------------------------------------------------- the camera
@dataclasses.dataclass(frozen=True)
class SceneView:
    """An oblique perspective camera on one env's table (hashable; all lengths in m).

    eye, target: camera position and the point it looks at (3-tuples); z is up.
    window: ``(a0, a1, b0, b1)``: the part of the image plane at unit distance (right,
    up) that the picture shows; any ``res`` fits it, centred, keeping the aspect.
    table_z: the table's height; grid: its checker's square side.
    radius: the sphere each particle is drawn as (0.65 x the points' spacing, so a liquid
    reads as a body, not a cloud); marker: the end effector's sphere.
    shadow_box: ``(x0, x1, y0, y1)`` the table region that receives shadows.

    Perspective, not orthographic: things nearer the camera look larger, which with the
    shading and the shadows tells near from far in one still picture; the field of view is
    narrow (the eye is :data:`DISTANCE` x the scene's size away) so the distortion stays
    mild and sizes stay comparable across the picture.
    """

    eye: tuple
    target: tuple
    window: tuple
    table_z: float
    grid: float
    radius: float
    marker: float
    shadow_box: tuple

    #: Camera elevation above the table [deg] and azimuth [deg] (0: looking along +y
    #: from the front; positive: from the left).
    ELEVATION = 35.0
    AZIMUTH = 30.0
    DISTANCE = 3.0
    PAD = 0.08  # fraction of the image left free around the framed points

    # ------------------------------------------------------------------ building
    @staticmethod
    def for_env(env, params=None, key=None) -> SceneView:
        """The view of ``env``'s episodes: looking from the front-left at
        :attr:`ELEVATION` degrees, framing the object at the start of the episode drawn from
        ``key`` (default ``PRNGKey(0)``), the goal (``params.goal``), the end effector, the
        kinematic colliders (the pour tasks' bowls) and the space under them on the table,
        plus the wrist's workspace where the scene has one (``wrist_low``/``wrist_high``)
        and the table region the object may start in (``render.table_region``), padded.
        Host side, once per env."""
        key = jax.random.PRNGKey(0) if key is None else key
        params = env.default_params if params is None else params
        with jax.ensure_compile_time_eval():
            _, state = jax.jit(env.reset)(key, params)
            pts = np.asarray(env.object_points(state.physics), np.float64)
            ee = np.asarray(env.end_effector(state.physics), np.float64).reshape(1, 3)
        goal = np.asarray(params.goal, np.float64).reshape(-1, 3)
        faces = env.unwrapped.object_faces
        spacing = point_spacing(pts)
        radius = 0.65 * spacing if faces is None else 0.0
        table_z = _table_height(env, pts, radius)
        parts = [pts, goal, ee]
        for shape in _collider_shapes(env, state.physics):
            parts.append(shape.outline())
        scene = getattr(env.unwrapped.spec, "scene", None)
        if hasattr(scene, "wrist_low") and hasattr(scene, "wrist_high"):
            lo, hi = np.asarray(scene.wrist_low), np.asarray(scene.wrist_high)
            parts.append(np.stack(np.meshgrid(*zip(lo, hi, strict=True)), -1).reshape(-1, 3))
        parts.append(table_region(env) + [0.0, 0.0, table_z])
        allp = np.concatenate(parts)
        allp = np.concatenate([allp, allp * [1, 1, 0] + [0, 0, table_z]])  # the floor under
        lo, hi = allp.min(0), allp.max(0)
        size = float(np.linalg.norm(hi - lo))
        target = 0.5 * (lo + hi)
        el, az = math.radians(SceneView.ELEVATION), math.radians(SceneView.AZIMUTH)
        back = np.asarray([-math.sin(az) * math.cos(el), -math.cos(az) * math.cos(el),
                           math.sin(el)])
        eye = target + SceneView.DISTANCE * size * back
        right, up, fwd = _basis(eye, target)
        rel = allp - eye
        a, b = rel @ right / (rel @ fwd), rel @ up / (rel @ fwd)
        grow = 1.0 / (1.0 - 2 * SceneView.PAD)
        ca, cb = 0.5 * (a.min() + a.max()), 0.5 * (b.min() + b.max())
        ha, hb = 0.5 * np.ptp(a) * grow, 0.5 * np.ptp(b) * grow
        window = (float(ca - ha), float(ca + ha), float(cb - hb), float(cb + hb))
        extent = float(np.max(hi[:2] - lo[:2]))
        grid = float(10 ** math.floor(math.log10(extent / 8)))  # 8 to 20 squares across
        if extent / grid > 20:
            grid *= 2.5 if extent / grid > 40 else 2
        pad = 0.5 * extent
        box = (float(lo[0] - pad), float(hi[0] + pad), float(lo[1] - pad), float(hi[1] + pad))
        return SceneView(tuple(map(float, eye)), tuple(map(float, target)), window,
                         float(table_z), grid, float(radius), float(0.012 * size), box)

    # ------------------------------------------------------------------ projection
    def intrinsics(self, res) -> tuple:
        """``(f, row0, col0)`` of a ``res = (W, H)`` picture: the focal length [px] and the
        continuous pixel coordinates of the image-plane point ``(0, 0)``."""
        w, h = _check_res(res)
        a0, a1, b0, b1 = self.window
        f = min(w / (a1 - a0), h / (b1 - b0))
        return f, (h - 1) / 2 + f * 0.5 * (b0 + b1), (w - 1) / 2 - f * 0.5 * (a0 + a1)

    def camera(self, points) -> np.ndarray:
        """Camera coordinates (..., 3) [m] of world points (..., 3): right, up, depth."""
        right, up, fwd = _basis(np.asarray(self.eye), np.asarray(self.target))
        rel = np.asarray(points, np.float64) - np.asarray(self.eye)
        return np.stack([rel @ right, rel @ up, rel @ fwd], -1)

    def project(self, points, res=(320, 240)) -> np.ndarray:
        """``(row, col, depth)`` (..., 3) of world points (..., 3) [m] in a ``res = (W, H)``
        picture: continuous pixel coordinates (pixel ``(i, j)``'s centre is ``(i, j)``, so
        rounding gives the pixel a point falls in) and the depth along the view [m]."""
        f, r0, c0 = self.intrinsics(res)
        c = self.camera(points)
        z = np.maximum(c[..., 2], _NEAR)
        return np.stack([r0 - f * c[..., 1] / z, c0 + f * c[..., 0] / z, c[..., 2]], -1)


def _basis(eye, target):
    fwd = np.asarray(target, np.float64) - np.asarray(eye, np.float64)
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    return right, np.cross(right, fwd), fwd


def _check_res(res) -> tuple:
    try:
        w, h = (int(v) for v in res)
    except (TypeError, ValueError):
        raise ValueError(f"res must be (width, height) in pixels, got {res!r}") from None
    if w <= 0 or h <= 0 or (w, h) != tuple(res):
        raise ValueError(f"res must be two positive whole numbers (width, height), got {res!r}")
    return w, h


def _table_height(env, pts, radius: float) -> float:
    """The table's height [m]: the scene's ``table_z`` or ``floor_z`` when it has one, else
    the lowest object point less its drawn radius."""
    scene = getattr(env.unwrapped.spec, "scene", None)
    for name in ("table_z", "floor_z"):
        if isinstance(getattr(scene, name, None), (int, float)):
            return float(getattr(scene, name))
    return float(pts[:, 2].min() - radius)


# --------------------------------------------------------------------------- colliders
@dataclasses.dataclass(frozen=True)
class _Shape:
    """A kinematic collider as a triangle mesh in its local frame, and its pose."""

    tris: np.ndarray   # (F, 3, 3) local
    rims: tuple        # closed polylines (P, 3) local, outlined
    pos: np.ndarray    # (3,)
    rot: np.ndarray    # (3, 3)

    def world(self, p):
        return p @ self.rot.T + self.pos

    def outline(self):
        return self.world(self.tris.reshape(-1, 3))


def _lathe(profile, n: int = 32):
    """Triangles (F, 3, 3) of the surface swept by the ``(r, z)`` polyline ``profile``
    about the z axis (``n`` segments)."""
    prof = np.asarray(profile, np.float64)
    ang = np.linspace(0.0, 2 * math.pi, n + 1)
    ring = np.stack([np.cos(ang), np.sin(ang)], -1)                     # (n+1, 2)
    pts = np.concatenate([prof[:, None, :1] * ring[None], np.broadcast_to(
        prof[:, None, 1:], (len(prof), n + 1, 1))], -1)                 # (P, n+1, 3)
    a, b = pts[:-1, :-1], pts[:-1, 1:]
    c, d = pts[1:, :-1], pts[1:, 1:]
    return np.concatenate([np.stack([a, b, d], -2).reshape(-1, 3, 3),
                           np.stack([a, d, c], -2).reshape(-1, 3, 3)])


def _circle(r, z, n: int = 48):
    ang = np.linspace(0.0, 2 * math.pi, n + 1)
    return np.stack([r * np.cos(ang), r * np.sin(ang), np.full_like(ang, z)], -1)


def _local_mesh(spec):
    """``(tris, rims)`` of a :class:`dax_physics.ColliderSpec`, or ``None`` (a plane: the
    table is drawn anyway)."""
    d = spec.dims
    if spec.shape == "bowl":
        r, h, t = d
        prof = [(0.0, 0.0), (r, 0.0), (r, h), (r - t, h), (r - t, t), (0.0, t)]
        return _lathe(prof), (_circle(r, h), _circle(r - t, h), _circle(r, 0.0))
    if spec.shape == "cylinder":
        r, hh = d
        prof = [(0.0, -hh), (r, -hh), (r, hh), (0.0, hh)]
        return _lathe(prof), (_circle(r, hh), _circle(r, -hh))
    if spec.shape in ("capsule", "sphere"):
        r, hl = (d[0], d[1]) if spec.shape == "capsule" else (d[0], 0.0)
        a = np.linspace(0.0, 0.5 * math.pi, 6)
        prof = [(r * math.cos(x), -hl - r * math.sin(x)) for x in a[::-1]] + \
               [(r * math.cos(x), hl + r * math.sin(x)) for x in a]
        return _lathe(prof), ()
    if spec.shape == "box":
        h = np.asarray(d)
        corners = np.asarray([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1)
                              for sz in (-1, 1)], np.float64) * h
        quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4),
                 (1, 5, 7, 3)]
        tris = [corners[[q[0], q[1], q[2]]] for q in quads] + \
               [corners[[q[0], q[2], q[3]]] for q in quads]
        return np.stack(tris), ()
    return None


def _quat_matrix(q):
    w, x, y, z = (float(v) for v in q)
    return np.asarray([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def _collider_specs(env):
    cfg = getattr(env.unwrapped, "cfg", None)
    return tuple(getattr(cfg, "colliders", ()) or ())


def _collider_shapes(env, physics, t=None) -> list:
    """The drawable colliders of ``physics`` (at time index ``t`` of a stacked episode)."""
    specs = _collider_specs(env)
    cs = getattr(physics, "colliders", None)
    if not specs or cs is None:
        return []
    pos, quat = np.asarray(cs.pos, np.float64), np.asarray(cs.quat, np.float64)
    if t is not None:
        pos, quat = pos[t], quat[t]
    out = []
    for k, spec in enumerate(specs):
        mesh = _local_mesh(spec)
        if mesh is not None and k < len(pos):
            out.append(_Shape(mesh[0], mesh[1], pos[k], _quat_matrix(quat[k])))
    return out


# --------------------------------------------------------------------------- rasterising
class _Canvas:
    """Colour, depth and kind buffers of one picture (flat, row-major)."""

    def __init__(self, view: SceneView, res, table):
        self.w, self.h = _check_res(res)
        self.view = view
        self.f, self.r0, self.c0 = view.intrinsics(res)
        self.rgb = table.rgb.copy()
        self.depth = table.depth.copy()
        self.kind = np.zeros(self.w * self.h, np.int8)

    # screen coordinates ---------------------------------------------------------------
    def screen(self, cam):
        z = np.maximum(cam[..., 2], _NEAR)
        return self.r0 - self.f * cam[..., 1] / z, self.c0 + self.f * cam[..., 0] / z

    def _flat(self, row, col):
        ok = (row >= 0) & (row < self.h) & (col >= 0) & (col < self.w)
        return np.where(ok, row * self.w + col, 0), ok

    # fragments ------------------------------------------------------------------------
    def spheres(self, centres, radius, colors, kind, light_cam):
        """Fragments of spheres of ``radius`` [m] at ``centres`` (N, 3) world."""
        cam = self.view.camera(centres)
        keep = cam[:, 2] > radius + _NEAR
        cam, colors = cam[keep], colors[keep]
        if not len(cam):
            return None
        row, col = self.screen(cam)
        rpx = self.f * radius / cam[:, 2]
        k = int(np.ceil(min(rpx.max(), 0.25 * max(self.w, self.h))))
        di, dj = np.meshgrid(np.arange(-k, k + 1), np.arange(-k, k + 1), indexing="ij")
        di, dj = di.ravel(), dj.ravel()
        ri, ci = np.rint(row).astype(np.int64), np.rint(col).astype(np.int64)
        pr, pc = ri[:, None] + di, ci[:, None] + dj                        # (N, K)
        u = (pc - col[:, None]) / rpx[:, None]
        v = (row[:, None] - pr) / rpx[:, None]
        rr = u * u + v * v
        inside = rr <= 1.0
        # a sphere smaller than a pixel still covers its centre pixel
        inside |= (di == 0)[None] & (dj == 0)[None]
        t = np.sqrt(np.clip(1.0 - rr, 0.0, 1.0))
        flat, ok = self._flat(pr, pc)
        ok &= inside
        depth = cam[:, 2:3] - radius * t
        normal = np.stack([u, v, -t], -1)
        lam = np.clip(normal @ light_cam, 0.0, 1.0)
        shade = AMBIENT + DIFFUSE * lam
        rgb = colors[:, None, :] * shade[..., None]
        return flat[ok], depth[ok], rgb[ok], np.full(int(ok.sum()), kind, np.int8)

    def triangles(self, tris_world, colors, kinds=None, two_sided_kinds=None,
                  vertex_colors=None, vertex_shade=None, cull_back: bool = False):
        """Fragments of triangles (F, 3, 3) world. ``colors`` (F, 3) a colour per face,
        or ``vertex_colors`` (F, 3, 3) per corner (interpolated, perspective-correct); faces
        are shaded with Lambert of their normal turned towards the camera. ``kinds`` (F,)
        int or, with ``two_sided_kinds = (sign (F,), back_tint)``, the front/back kinds
        are chosen by which side faces the camera (``sign`` +1 where the face's winding
        normal is its front) and the back's colours are mixed with ``back_tint``.
        ``vertex_shade`` (F, 3) replaces the per-face Lambert by a shade per corner,
        interpolated (smooth shading). ``cull_back`` drops faces whose winding normal
        looks away from the camera (the far side of a closed, outward-wound mesh)."""
        faces = self._shaded_faces(tris_world, colors, kinds, two_sided_kinds, vertex_colors,
                                   vertex_shade, cull_back)
        if faces is None:
            return None
        return self._rasterise(*faces, smooth=vertex_colors is not None
                               or vertex_shade is not None)

    def _shaded_faces(self, tris_world, colors, kinds, two_sided_kinds, vertex_colors,
                      vertex_shade, cull_back):
        """The faces :meth:`triangles` draws (in front of the near plane, not culled) as
        ``(cam (F, 3, 3), row (F, 3), col (F, 3), corner colours (F, 3, 3), shade (F,),
        kind (F,), depth bias (F,))``, or ``None`` if none is left."""
        tris_world = np.asarray(tris_world, np.float64)
        cam = self.view.camera(tris_world)                                 # (F, 3, 3)
        n = np.cross(tris_world[:, 1] - tris_world[:, 0],
                     tris_world[:, 2] - tris_world[:, 0])                   # world
        n /= np.linalg.norm(n, axis=1, keepdims=True) + 1e-30
        toward = np.sum(n * (np.asarray(self.view.eye) - tris_world[:, 0]), axis=1) > 0
        good = np.all(cam[..., 2] > _NEAR, axis=1) & (toward | (not cull_back))
        if not np.any(good):
            return None
        idx = np.nonzero(good)[0]
        cam, n, toward = cam[idx], n[idx], toward[idx]
        row, col = self.screen(cam)                                        # (F, 3)
        shade = AMBIENT + DIFFUSE * np.abs(n @ LIGHT)
        if two_sided_kinds is not None:
            sign, tint = two_sided_kinds
            front = toward == (sign[idx] > 0)
            kind = np.where(front, _FRONT, _BACK).astype(np.int8)
            bias = np.where(front, 0.0, -LAYER_BIAS)
        else:
            front = np.ones(len(idx), bool)
            kind = np.asarray(kinds, np.int8)[idx]
            bias = np.zeros(len(idx))
        if vertex_colors is not None:
            vc = np.asarray(vertex_colors, np.float64)[idx]
        else:
            vc = np.repeat(np.asarray(colors, np.float64)[idx][:, None, :], 3, axis=1)
        if two_sided_kinds is not None:
            vc = np.where(front[:, None, None], vc, 0.3 * vc + 0.7 * tint)
        if vertex_shade is not None:
            vc = vc * np.asarray(vertex_shade, np.float64)[idx][..., None]
            shade = np.ones(len(idx))
        return cam, row, col, vc, shade, kind, bias

    def _rasterise(self, cam, row, col, vc, shade, kind, bias, smooth: bool):
        """Fragments ``(flat, depth, rgb, kind)`` of the faces :meth:`_shaded_faces` gives:
        every pixel centre inside a face, its depth interpolated perspective-correctly (plus
        the face's bias) and its colour the face's (``smooth``: the corners' interpolated),
        times the face's shade; ``None`` if no pixel is covered."""
        lo_c = np.clip(np.ceil(col.min(1)), 0, self.w).astype(np.int64)
        hi_c = np.clip(np.floor(col.max(1)), -1, self.w - 1).astype(np.int64)
        lo_r = np.clip(np.ceil(row.min(1)), 0, self.h).astype(np.int64)
        hi_r = np.clip(np.floor(row.max(1)), -1, self.h - 1).astype(np.int64)
        wc, wr = hi_c - lo_c + 1, hi_r - lo_r + 1
        area = ((col[:, 1] - col[:, 0]) * (row[:, 2] - row[:, 0])
                - (col[:, 2] - col[:, 0]) * (row[:, 1] - row[:, 0]))
        live = (wc > 0) & (wr > 0) & (np.abs(area) > 1e-12)
        # triangles grouped by their bounding box rounded up to powers of two per axis
        bc = np.ceil(np.log2(np.maximum(wc, 1))).astype(int)
        br = np.ceil(np.log2(np.maximum(wr, 1))).astype(int)
        bucket = np.where(live, bc * 64 + br, -1)
        out = []
        for key in np.unique(bucket[bucket >= 0]):
            sel = np.nonzero(bucket == key)[0]
            oi, oj = np.meshgrid(np.arange(2 ** (key % 64)), np.arange(2 ** (key // 64)),
                                 indexing="ij")
            pr = lo_r[sel, None] + oi.ravel()[None]                      # (S, K)
            pc = lo_c[sel, None] + oj.ravel()[None]
            r_, c_ = row[sel], col[sel]
            w = [((c_[:, b_, None] - c_[:, a_, None]) * (pr - r_[:, a_, None])
                  - (pc - c_[:, a_, None]) * (r_[:, b_, None] - r_[:, a_, None]))
                 / area[sel, None] for a_, b_ in ((1, 2), (2, 0), (0, 1))]
            ok = ((w[0] >= -1e-9) & (w[1] >= -1e-9) & (w[2] >= -1e-9)
                  & (pr <= hi_r[sel, None]) & (pc <= hi_c[sel, None]))
            si, ki = np.nonzero(ok)
            if not len(si):
                continue
            face = sel[si]
            inv = np.stack([wk[si, ki] for wk in w], -1) / cam[face, :, 2]    # (M, 3)
            inv_z = inv.sum(-1)
            if smooth:
                rgb = np.einsum("mv,mvc->mc", inv / inv_z[:, None], vc[face])
            else:
                rgb = vc[face, 0]
            out.append((pr[si, ki] * self.w + pc[si, ki], 1.0 / inv_z + bias[face],
                        rgb * shade[face, None], kind[face]))
        if not out:
            return None
        return tuple(np.concatenate(parts) for parts in zip(*out, strict=True))

    def lines(self, polylines_world, step_px: float = 0.7):
        """Fragments ``(flat, depth)`` of world polylines, about ``step_px`` apart."""
        flats, depths = [np.zeros(0, np.int64)], [np.zeros(0)]
        for pl in polylines_world:
            cam = self.view.camera(pl)
            if np.any(cam[:, 2] <= _NEAR):
                continue
            row, col = self.screen(cam)
            m = max(int(np.ceil(np.hypot(np.diff(row), np.diff(col)).max() / step_px)), 1)
            s = (np.arange(m) / m)[None]                                   # (1, m)
            z0, z1 = cam[:-1, 2, None], cam[1:, 2, None]
            z = 1.0 / ((1 - s) / z0 + s / z1)
            r = np.rint(row[:-1, None] + s * np.diff(row)[:, None]).astype(np.int64)
            c = np.rint(col[:-1, None] + s * np.diff(col)[:, None]).astype(np.int64)
            flat, ok = self._flat(r, c)
            flats.append(flat[ok])
            depths.append(z[ok])
        return np.concatenate(flats), np.concatenate(depths)

    def dots(self, points, px: float) -> np.ndarray:
        """The pixels (flat, unique) within ``px`` pixels of the points (N, 3) world."""
        cam = self.view.camera(points)
        cam = cam[cam[:, 2] > _NEAR]
        row, col = self.screen(cam)
        k = int(np.ceil(px))
        di, dj = np.meshgrid(np.arange(-k, k + 1), np.arange(-k, k + 1), indexing="ij")
        keep = di ** 2 + dj ** 2 <= px * px
        pr = np.rint(row).astype(np.int64)[:, None] + di[keep]
        pc = np.rint(col).astype(np.int64)[:, None] + dj[keep]
        flat, ok = self._flat(pr, pc)
        return np.unique(flat[ok])

    # compositing ----------------------------------------------------------------------
    @staticmethod
    def nearest(flat, depth):
        """Indices of the nearest fragment per pixel (the first drawn among equals)."""
        order = np.lexsort((depth, flat))
        fs = flat[order]
        first = np.ones(len(fs), bool)
        first[1:] = fs[1:] != fs[:-1]
        return order[first]

    def draw(self, frags):
        """Z-buffer opaque fragments ``(flat, depth, rgb, kind)``."""
        if frags is None or not len(frags[0]):
            return
        flat, depth, rgb, kind = frags
        sel = self.nearest(flat, depth)
        f = flat[sel]
        win = depth[sel] < self.depth[f]
        f, sel = f[win], sel[win]
        self.depth[f] = depth[sel]
        self.rgb[f] = rgb[sel]
        self.kind[f] = kind[sel]

    def outline(self, jump: float, darken: float = 0.55):
        """Darken the farther pixel of each neighbour pair whose kinds differ or, off the
        table, whose depths differ by more than ``jump`` [m] plus three pixels' footprint
        (a surface seen at a grazing angle is not an edge)."""
        d = np.minimum(self.depth, 1e9).reshape(self.h, self.w)  # the sky is far, not inf
        k = self.kind.reshape(self.h, self.w)
        tol = jump + 3.0 * d / self.f
        edge = np.zeros((self.h, self.w), bool)
        for ax in (0, 1):
            for sh in (1, -1):
                dn = np.roll(d, sh, axis=ax)
                kn = np.roll(k, sh, axis=ax)
                jumps = (k != _TABLE) & (kn != _TABLE) & (np.abs(dn - d) > tol)
                e = ((kn != k) | jumps) & (dn < d)
                if sh == 1:
                    (e[0, :] if ax == 0 else e[:, 0])[...] = False
                else:
                    (e[-1, :] if ax == 0 else e[:, -1])[...] = False
                edge |= e
        self.rgb[edge.ravel()] *= darken

    def blend(self, flat, rgb, alpha):
        """Blend colours ``rgb`` (M, 3) (one per pixel) over pixels ``flat`` at ``alpha``."""
        self.rgb[flat] = (1 - alpha) * self.rgb[flat] + alpha * rgb

    def glass(self, frags, alpha):
        """The nearest translucent fragment in front of the opaque scene, blended."""
        if frags is None or not len(frags[0]):
            return
        flat, depth, rgb, _ = frags
        front = depth < self.depth[flat]
        flat, depth, rgb = flat[front], depth[front], rgb[front]
        sel = self.nearest(flat, depth)
        self.blend(flat[sel], rgb[sel], alpha)

    def overlay(self, mask, rgb, alpha, edge_alpha):
        """Tint the pixels of ``mask`` (H*W,) bool with ``rgb`` at ``alpha``, its border at
        ``edge_alpha``."""
        m = mask.reshape(self.h, self.w)
        inner = m.copy()
        inner[1:, :] &= m[:-1, :]
        inner[:-1, :] &= m[1:, :]
        inner[:, 1:] &= m[:, :-1]
        inner[:, :-1] &= m[:, 1:]
        border = (m & ~inner).ravel()
        inner = inner.ravel()
        self.blend(np.nonzero(inner)[0], rgb, alpha)
        self.blend(np.nonzero(border)[0], rgb, edge_alpha)

    def image(self) -> np.ndarray:
        img = np.clip(np.rint(self.rgb * 255.0), 0, 255).astype(np.uint8)
        return img.reshape(self.h, self.w, 3)


@dataclasses.dataclass(frozen=True)
class _Table:
    """The table layer of a view at a resolution: colour, depth, and where each table pixel
    looks up the shadow grid."""

    rgb: np.ndarray      # (H*W, 3)
    depth: np.ndarray    # (H*W,)
    on_table: np.ndarray  # (H*W,) bool
    cell: np.ndarray     # (M, 4) flat shadow-grid cells around each table pixel
    weight: np.ndarray   # (M, 4) their bilinear weights


_SHADOW_GRID = 160
_TABLE_CACHE: dict = {}


def _table(view: SceneView, res) -> _Table:
    key = (view, tuple(res))
    if key in _TABLE_CACHE:
        return _TABLE_CACHE[key]
    w, h = _check_res(res)
    f, r0, c0 = view.intrinsics(res)
    right, up, fwd = _basis(view.eye, view.target)
    rows, cols = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    ray = (fwd[None, None] + ((cols - c0) / f)[..., None] * right
           + ((r0 - rows) / f)[..., None] * up).reshape(-1, 3)
    eye = np.asarray(view.eye)
    s = (view.table_z - TABLE_SINK - eye[2]) / np.where(ray[:, 2] < 0, ray[:, 2], -1e-30)
    hit = (ray[:, 2] < 0) & (s > 0)
    p = eye + s[:, None] * ray
    depth = np.where(hit, s, np.inf)  # ray's fwd component is 1: s is the depth
    checker = (np.floor(p[:, 0] / view.grid) + np.floor(p[:, 1] / view.grid)) % 2
    base = TABLE * (1.0 + 0.035 * (2 * checker - 1))[:, None]
    far = np.asarray(view.target)
    dist = np.hypot(p[:, 0] - far[0], p[:, 1] - far[1])
    x0, x1, y0, y1 = view.shadow_box
    fade = np.clip((dist - 0.5 * (x1 - x0)) / (0.5 * (x1 - x0)), 0.0, 1.0)[:, None]
    rgb = np.where(hit[:, None], (1 - fade) * base + fade * BACKGROUND, BACKGROUND)
    g = _SHADOW_GRID
    u = (p[hit, 0] - x0) / (x1 - x0) * g - 0.5
    v = (p[hit, 1] - y0) / (y1 - y0) * g - 0.5
    cell = np.stack([np.floor(u), np.floor(v)], -1)
    weight = np.stack([u, v], -1) - cell
    inside = np.all((cell >= 0) & (cell < g - 1), axis=1)
    idx = np.nonzero(hit)[0][inside]
    on = np.zeros(w * h, bool)
    on[idx] = True
    c, f = cell[inside].astype(np.int64), weight[inside]
    corners = np.stack([c[:, 0] * g + c[:, 1], (c[:, 0] + 1) * g + c[:, 1],
                        c[:, 0] * g + c[:, 1] + 1, (c[:, 0] + 1) * g + c[:, 1] + 1], -1)
    weights = np.stack([(1 - f[:, 0]) * (1 - f[:, 1]), f[:, 0] * (1 - f[:, 1]),
                        (1 - f[:, 0]) * f[:, 1], f[:, 0] * f[:, 1]], -1)
    table = _Table(rgb, np.where(hit, depth, np.inf), on, corners, weights)
    if len(_TABLE_CACHE) > 16:
        _TABLE_CACHE.clear()
    _TABLE_CACHE[key] = table
    return table


def _blur(a, sigma_x: float, sigma_y: float) -> np.ndarray:
    """``a`` (X, Y) blurred by a Gaussian of ``sigma`` cells per axis (separable shifted
    sums, not a BLAS product: OpenBLAS threads fight XLA's for the cores)."""
    for axis, sigma in ((0, sigma_x), (1, sigma_y)):
        k = max(int(np.ceil(3 * sigma)), 1)
        taps = np.exp(-0.5 * (np.arange(-k, k + 1) / max(sigma, 1e-6)) ** 2)
        taps /= taps.sum()
        pad = [(0, 0), (0, 0)]
        pad[axis] = (k, k)
        p = np.pad(a, pad)
        n = a.shape[axis]
        a = sum(t * (p[i:i + n] if axis == 0 else p[:, i:i + n]) for i, t in enumerate(taps))
    return a


def _shadow(view: SceneView, table: _Table, points, radius: float) -> np.ndarray:
    """Fraction of light (M,) the table pixels lose to the shadow of ``points`` (N, 3),
    each a disc of ``radius`` [m] seen from the light."""
    g = _SHADOW_GRID
    x0, x1, y0, y1 = view.shadow_box
    h = np.maximum(points[:, 2] - view.table_z, 0.0)
    q = points[:, :2] - h[:, None] * LIGHT[None, :2] / LIGHT[2]
    cx, cy = (x1 - x0) / g, (y1 - y0) / g
    k = max(int(np.ceil(radius / min(cx, cy))), 0)
    di, dj = np.meshgrid(np.arange(-k, k + 1), np.arange(-k, k + 1), indexing="ij")
    disc = (di * cx) ** 2 + (dj * cy) ** 2 <= max(radius, 0.5 * min(cx, cy)) ** 2
    iu = np.floor((q[:, 0] - x0) / cx).astype(np.int64)[:, None] + di[disc][None]
    iv = np.floor((q[:, 1] - y0) / cy).astype(np.int64)[:, None] + dj[disc][None]
    ok = (iu >= 0) & (iu < g) & (iv >= 0) & (iv < g)
    occ = np.zeros((g, g))
    occ[iu[ok], iv[ok]] = 1.0
    occ = _blur(occ, SHADOW_BLUR / cx, SHADOW_BLUR / cy)
    val = np.sum(occ.ravel()[table.cell] * table.weight, axis=1)
    return SHADOW * np.clip(val, 0.0, 1.0)


# --------------------------------------------------------------------------- one picture
def _face_sign(faces, candidates) -> np.ndarray:
    """+1 per face whose winding normal is its front (points up on the flattest of the
    ``candidates`` vertex sets), else -1."""
    flat = min(candidates, key=lambda p: float(np.ptp(p[:, 2])))
    t = flat[faces]
    nz = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])[:, 2]
    return np.where(nz >= 0, 1.0, -1.0)


def _boundary_edges(faces) -> np.ndarray:
    """The edges (E, 2) of a triangle mesh that belong to one face only (its outline)."""
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), 1)
    uniq, count = np.unique(e, axis=0, return_counts=True)
    return uniq[count == 1]


def _draw(view, res, table, *, points, colors, faces, sign, ee, shapes, shadow_radius,
          goal=None, goal_edges=None):
    """One picture (H, W, 3) uint8 of object ``points`` (N, 3) [m] (a mesh when ``faces``
    is given), the end effector ``ee`` (3,) or ``None``, collider ``shapes`` and, when
    ``goal`` (M, 3) is given, its overlay (dots, and the lines ``goal_edges`` (E, 2))."""
    cv = _Canvas(view, res, table)
    right, up, fwd = _basis(view.eye, view.target)
    light_cam = np.asarray([LIGHT @ right, LIGHT @ up, LIGHT @ fwd])
    mesh = faces is not None
    # the table's shadows
    casters = _mesh_samples(points, faces) if mesh else points
    if ee is not None:
        casters = np.concatenate([casters, ee[None]])
    dark = _shadow(view, table, casters, shadow_radius)
    cv.rgb[np.nonzero(table.on_table)[0]] *= (1.0 - dark)[:, None]
    # opaque things
    frags = []
    if mesh:
        frags.append(cv.triangles(points[faces], None,
                                  two_sided_kinds=(sign, CLOTH_BACK),
                                  vertex_colors=colors[faces],
                                  vertex_shade=_vertex_shade(points, faces)[faces]))
    else:
        frags.append(cv.spheres(points, view.radius, colors, _PARTICLE, light_cam))
    if ee is not None:
        frags.append(cv.spheres(ee[None], view.marker, MARKER[None], _MARKER, light_cam))
    frags = [f for f in frags if f is not None]
    if frags:
        cv.draw(tuple(np.concatenate(parts) for parts in zip(*frags, strict=True)))
    cv.outline(jump=2.0 * view.radius)
    # translucent colliders, then their rims over them
    if shapes:
        tris = np.concatenate([s.world(s.tris.reshape(-1, 3)).reshape(-1, 3, 3)
                               for s in shapes])
        glass = cv.triangles(tris, np.broadcast_to(GLASS, (len(tris), 3)),
                             kinds=np.zeros(len(tris), np.int8), cull_back=True)
        cv.glass(glass, GLASS_ALPHA)
        flat, depth = cv.lines([s.world(r) for s in shapes for r in s.rims])
        vis = depth <= cv.depth[flat] + 0.5 * view.marker
        cv.blend(np.unique(flat[vis]), RIM, 0.8)
    # the goal, over everything
    if goal is not None:
        dots = goal[::max(1, -(-len(goal) // GOAL_DOTS))]
        cv.blend(cv.dots(dots, max(1.0, 0.005 * max(cv.w, cv.h))), GOAL, GOAL_ALPHA)
        if goal_edges is not None:
            flat, _ = cv.lines(list(goal[goal_edges]))
            cv.blend(np.unique(flat), GOAL, GOAL_EDGE_ALPHA)
    return cv.image()


def _vertex_shade(points, faces) -> np.ndarray:
    """Lambert plus ambient (V,) of a mesh's vertices with smooth normals (the faces'
    area-weighted normals summed per vertex), lit from either side."""
    tri = points[faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    vn = np.zeros_like(points)
    for k in range(3):
        np.add.at(vn, faces[:, k], n)
    vn /= np.linalg.norm(vn, axis=1, keepdims=True) + 1e-30
    return AMBIENT + DIFFUSE * np.abs(vn @ LIGHT)


def _mesh_samples(points, faces):
    """Vertices, edge midpoints and face centroids of a mesh (denser shadow casters)."""
    tri = points[faces]
    return np.concatenate([points, tri.mean(1), 0.5 * (tri + np.roll(tri, 1, axis=1))
                           .reshape(-1, 3)])


def _shadow_radius(view: SceneView, points, faces) -> float:
    """The disc [m] each shadow caster covers: a particle's sphere, or for a mesh half its
    median edge (its casters are vertices, edge midpoints and centroids)."""
    if faces is None:
        return view.radius
    tri = points[faces]
    edge = np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=-1)
    return 0.5 * float(np.median(edge))


# --------------------------------------------------------------------------- public
#: The jitted (object points, end effector) of a stacked episode, per env (compiled once).
_POINTS_FNS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _episode(env, states):
    """Host arrays of a stacked episode: points (T, N, 3), end effector (T, 3), T."""
    t = getattr(states, "t", None)
    physics = getattr(states, "physics", None)
    if t is None or physics is None:
        raise ValueError(f"states must be an EnvState with a leading time axis, got "
                         f"{type(states).__name__}")
    t = np.asarray(t)
    if t.ndim != 1:
        raise ValueError(f"states must have one leading time axis (state.t of shape (T,)), "
                         f"got state.t of shape {t.shape}"
                         + (" (a single state: stack it, e.g. with jax.tree.map(lambda x: "
                            "x[None], state))" if t.ndim == 0 else ""))
    n = t.shape[0]
    if n == 0:
        raise ValueError("states has no time steps (T = 0)")
    for path, leaf in jax.tree_util.tree_flatten_with_path(physics)[0]:
        shape = np.shape(leaf)
        if not shape or shape[0] != n:
            raise ValueError(f"states.physics{jax.tree_util.keystr(path)} has shape {shape}, "
                             f"not a leading time axis of {n} like state.t")
    fn = _POINTS_FNS.get(env)
    if fn is None:
        fn = jax.jit(jax.vmap(lambda p: (env.object_points(p), env.end_effector(p))))
        _POINTS_FNS[env] = fn
    pts, ee = fn(physics)
    return np.asarray(pts, np.float64), np.asarray(ee, np.float64), n


def _object_colors(env, n: int) -> np.ndarray:
    colors = env.unwrapped.object_colors
    if colors is None:
        return np.broadcast_to(PARTICLE, (n, 3)).astype(np.float64)
    colors = np.asarray(colors, np.float64)
    if colors.shape != (n, 3):
        raise ValueError(f"env.object_colors has shape {colors.shape}, not ({n}, 3) for its "
                         f"{n} object points")
    return colors


def scene_frames(env, states, *, view: SceneView | None = None, res=(320, 240),
                 goal: bool = True) -> np.ndarray:
    """``(T, H, W, 3)`` uint8 pictures (``res = (W, H)``) of the stacked states ``states``
    (an :class:`~dax_tasks.EnvState` whose leaves have a leading time axis T) seen by
    ``view`` (default :meth:`SceneView.for_env`); ``goal`` draws ``env.goal`` as a faint
    overlay. See the module docstring for what is drawn."""
    w, h = _check_res(res)
    if view is None:
        view = SceneView.for_env(env)
    elif not isinstance(view, SceneView):
        raise ValueError(f"view must be a SceneView, got {type(view).__name__}")
    pts, ee, n = _episode(env, states)
    colors = _object_colors(env, pts.shape[1])
    faces = env.unwrapped.object_faces
    goal_pts = np.asarray(env.goal, np.float64) if goal else None
    sign = goal_edges = None
    if faces is not None:
        faces = np.asarray(faces, np.int64)
        cands = [pts[0]] + ([np.asarray(env.goal, np.float64)]
                            if np.shape(env.goal) == pts.shape[1:] else [])
        sign = _face_sign(faces, cands)
        if goal_pts is not None and goal_pts.shape == pts.shape[1:]:
            goal_edges = _boundary_edges(faces)
    table = _table(view, (w, h))
    shadow_radius = _shadow_radius(view, pts[0], faces)
    out = np.empty((n, h, w, 3), np.uint8)
    for i in range(n):
        out[i] = _draw(view, (w, h), table, points=pts[i], colors=colors, faces=faces,
                       sign=sign, ee=ee[i], shapes=_collider_shapes(env, states.physics, i),
                       shadow_radius=shadow_radius, goal=goal_pts, goal_edges=goal_edges)
    return out


def goal_frame(env, state=None, view: SceneView | None = None, res=(320, 240)) -> np.ndarray:
    """``(H, W, 3)`` uint8: the goal alone, drawn opaque as the object would be (in the
    object's colours when the goal has a point per object point, else green), with the
    colliders of ``state`` (one unstacked state, default the start from ``PRNGKey(0)``)
    and no end effector."""
    w, h = _check_res(res)
    view = SceneView.for_env(env) if view is None else view
    if state is None:
        _, state = jax.jit(env.reset)(jax.random.PRNGKey(0), env.default_params)
    if np.ndim(state.t) != 0:
        raise ValueError(f"goal_frame takes one state (state.t a scalar), got state.t of "
                         f"shape {np.shape(state.t)}")
    goal = np.asarray(env.goal, np.float64)
    n = env.unwrapped.n_object_points
    same = goal.shape[0] == n
    colors = _object_colors(env, n) if same else np.broadcast_to(GOAL, (len(goal), 3))
    faces = env.unwrapped.object_faces
    sign = None
    if faces is not None and same:
        faces = np.asarray(faces, np.int64)
        start = np.asarray(env.object_points(state.physics), np.float64)
        sign = _face_sign(faces, [start, goal])
    else:
        faces = None
    table = _table(view, (w, h))
    return _draw(view, (w, h), table, points=goal, colors=np.asarray(colors, np.float64),
                 faces=faces, sign=sign, ee=None, shapes=_collider_shapes(env, state.physics),
                 shadow_radius=_shadow_radius(view, goal, faces))
