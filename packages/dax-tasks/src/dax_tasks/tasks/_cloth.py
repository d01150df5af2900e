"""Private helpers of the cloth tasks: the scene, the physics params, the cloth meshes, the
pick-and-place macro and the canonical scripted folds (see :mod:`dax_tasks.tasks.cloth` for
the task documentation)."""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

import dax_physics.cloth as dc
from dax_physics import pytree_dataclass
from dax_physics.cloth import mesh as dmesh

from ..core.env import replace_cast

#: Default T-shirt outline [m] (see :func:`dax_physics.cloth.tshirt_outline`).
TSHIRT_OUTLINE = (("width", 0.2), ("length", 0.25), ("sleeve", 0.08),
                  ("sleeve_width", 0.08), ("neck", 0.08), ("neck_depth", 0.02))


@dataclasses.dataclass(frozen=True)
class ClothScene:
    """Static scene of a cloth task (SI units; hashable, a jit static argument).

    shape: ``"square"`` or ``"tshirt"``.
    n: square cloth vertices per side (``n * n`` vertices).
    size: square cloth side [m].
    spacing: T-shirt grid spacing [m]; outline: T-shirt outline keywords (tuple of pairs).
    dt: substep [s] (checked against the stable bound when the task is built).
    settle_substeps: substeps after the release in every action (the rest of
        ``spec.substeps`` carry the gripper).
    arc_height: the gripper path's peak height over the table-plane travel distance.
    grasp_radius: without contact adjustment the gripper holds the vertices within this
        fraction of the mesh spacing of the pick point; with it, those around the nearest
        vertex.
    folds: canonical fold sequence of the task ("" none; "diag1" one diagonal fold;
        "diag3" three; "tshirt" sleeves in, then in half).
    unfold: the episode starts folded (``folds`` applied) and the goal is the flat cloth.
    rotation_range [rad]: the start's heading is uniform in ``±rotation_range`` (default
        pi: any heading), a rotation about the vertical axis through the cloth's centre.
    table_half [m]: half-width of the square table region (centred on the table centre) that
        the whole start cloth lies in, at its flat extent (so an unfolded cloth lies in it
        too); the action box is 5 cm wider on every side.
    offset_range [m]: the largest shift of the cloth's centre per axis; the shift is drawn
        uniformly over the positions where the rotated flat cloth lies inside
        ``±table_half`` and within ``±offset_range`` (default ``table_half``: no further
        limit; 0 with ``rotation_range`` 0: the unrandomised start).
    thickness [m]: self-collision thickness h (vertex pairs closer than h repel, see
        :class:`dax_physics.cloth.ClothConfig`); 0 turns self-collision off.
    self_stiffness [N/m], self_friction [N s/m], self_search, self_skin [m],
        self_capacity, self_candidates: the self-collision's repulsion stiffness,
        tangential friction, pair search and neighbour-list sizes
        (:class:`dax_physics.cloth.ClothConfig`). The default search, ``"list"``, keeps a
        Verlet neighbour list in the cloth state (``physics.neighbours``) and finds every
        pair all-pairs finds while its ``overflow`` is 0; ``"all"`` tests every pair.
    friction_model: the table friction law, ``"coulomb"`` (default: stick-slip) or
        ``"smooth"`` (a regularised law whose rollouts are smooth in the actions, for
        gradient-based planners; see :class:`dax_physics.cloth.ClothConfig`).
    segment: substeps per checkpointed segment of a pick-and-place's two scans
        (:func:`dax_physics.checkpointed_scan`): the reverse pass keeps the state at each
        segment's start and recomputes one segment at a time, so an action gradient's
        memory grows with the segments, not the substeps.
    """

    shape: str = "square"
    n: int = 11
    size: float = 0.3
    spacing: float = 0.025
    outline: tuple = TSHIRT_OUTLINE
    dt: float = 1.0e-3
    settle_substeps: int = 300
    arc_height: float = 0.5
    grasp_radius: float = 0.25
    folds: str = "diag1"
    unfold: bool = False
    rotation_range: float = math.pi
    table_half: float = 0.35
    offset_range: float = 0.35
    friction_model: str = "coulomb"
    thickness: float = 0.0
    self_stiffness: float = 0.5
    self_damping: float = 0.0
    self_friction: float = 0.0
    self_search: str = "list"
    self_skin: float | None = None
    self_capacity: float = 4.0
    self_candidates: int = 16
    segment: int = 50

    def __post_init__(self):
        if self.shape not in ("square", "tshirt"):
            raise ValueError(f"cloth shape must be 'square' or 'tshirt', got {self.shape!r}")
        if self.folds not in FOLD_PLANS:
            raise ValueError(f"unknown fold sequence {self.folds!r}; "
                             f"valid: {', '.join(FOLD_PLANS)}")
        if self.shape == "square" and self.n < 3:
            raise ValueError(f"a square cloth needs n >= 3 vertices per side, got {self.n}")
        for name in ("size", "spacing", "dt", "grasp_radius", "table_half"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        for name in ("thickness", "self_stiffness", "self_damping", "self_friction",
                     "rotation_range",
                     "offset_range"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.self_candidates < 1:
            raise ValueError(f"self_candidates must be >= 1, got {self.self_candidates}")
        if self.segment < 1:
            raise ValueError(f"segment must be >= 1 substep, got {self.segment}")
        if self.self_search not in dc.SELF_SEARCHES:
            raise ValueError(f"unknown self_search {self.self_search!r}; valid: "
                             f"{', '.join(dc.SELF_SEARCHES)}")
        if self.settle_substeps < 0:
            raise ValueError(f"settle_substeps must be >= 0, got {self.settle_substeps}")

    @property
    def mesh_spacing(self) -> float:
        return self.size / (self.n - 1) if self.shape == "square" else self.spacing


def rest_vertices(scene: ClothScene):
    """Rest mesh ``(vertices (V, 3), faces)`` [m], flat on the table (z = 0), centred on the
    table centre (the origin)."""
    if scene.shape == "square":
        h = scene.size / 2
        return dmesh.square_mesh(scene.n, scene.n, (scene.size, scene.size), (-h, -h), 0.0)
    v, f = dmesh.tshirt_mesh(scene.spacing, 0.0, **dict(scene.outline))
    v = v.copy()
    v[:, :2] -= 0.5 * (v[:, :2].min(0) + v[:, :2].max(0))
    return v, f


@functools.lru_cache(maxsize=32)
def _cloth_np(scene: ClothScene):
    v, f = rest_vertices(scene)
    return v, f


@pytree_dataclass
class ClothParams:
    """The cloth tasks' physics numbers (``params.physics``; scalars, SI units).

    density: areal density [kg/m^2]; stretch, shear, bend: spring moduli [N/m] of the
    structural, shear and bending springs (:func:`dax_physics.cloth.make_cloth`); damping:
    dashpot modulus [N s/m]; friction_static, friction_dynamic: Coulomb coefficients [-]
    of the cloth on the table. ``replace`` casts new values to float32 (no retrace).
    """

    density: jnp.ndarray
    stretch: jnp.ndarray
    shear: jnp.ndarray
    bend: jnp.ndarray
    damping: jnp.ndarray
    friction_static: jnp.ndarray
    friction_dynamic: jnp.ndarray

    @staticmethod
    def create(**values) -> ClothParams:
        """Float32 params from :data:`DEFAULT_MATERIAL` with ``values`` replaced."""
        unknown = sorted(set(values) - set(DEFAULT_MATERIAL))
        if unknown:
            raise ValueError(f"unknown cloth parameter(s) {unknown}; valid: "
                             f"{sorted(DEFAULT_MATERIAL)}")
        merged = {**DEFAULT_MATERIAL, **values}
        return ClothParams(**{k: jnp.asarray(v, jnp.float32) for k, v in merged.items()})

    def replace(self, **changes) -> ClothParams:
        return replace_cast(self, changes)


#: The cloth tasks' default material: 0.2 kg/m^2, stretch = shear 10 N/m, bend 0.5 N/m,
#: dashpot 0.01 N s/m, friction on the table 1.0 (static) and 0.8 (dynamic).
DEFAULT_MATERIAL = {"density": 0.2, "stretch": 10.0, "shear": 10.0, "bend": 0.5,
                    "damping": 0.01, "friction_static": 1.0, "friction_dynamic": 0.8}


def make_cloth(scene: ClothScene) -> dc.Cloth:
    """The :class:`dax_physics.cloth.Cloth` of the scene with :data:`DEFAULT_MATERIAL`
    (constant arrays; the table friction is the config's)."""
    v, f = _cloth_np(scene)
    m = DEFAULT_MATERIAL
    with jax.ensure_compile_time_eval():
        return dc.make_cloth(v, f, density=m["density"], stretch=m["stretch"],
                             shear=m["shear"], bend=m["bend"], damping=m["damping"])


def cloth_with(base: dc.Cloth, params: ClothParams) -> dc.Cloth:
    """``base`` (built with :data:`DEFAULT_MATERIAL`) with the material of ``params``: the
    spring network scaled by the moduli relative to the defaults (exactly ``base`` at the
    defaults) and the table friction as data."""
    m = DEFAULT_MATERIAL
    cloth = dc.scale_moduli(base, stretch=params.stretch / m["stretch"],
                            shear=params.shear / m["shear"], bend=params.bend / m["bend"],
                            damping=params.damping / m["damping"],
                            density=params.density / m["density"])
    return cloth.replace(table_friction=jnp.stack([params.friction_static,
                                                   params.friction_dynamic]))


def cloth_config(scene: ClothScene) -> dc.ClothConfig:
    m = DEFAULT_MATERIAL
    return dc.ClothConfig(dt=scene.dt, friction_static=m["friction_static"],
                          friction_dynamic=m["friction_dynamic"], table_height=0.0,
                          friction_model=scene.friction_model, thickness=scene.thickness,
                          self_stiffness=scene.self_stiffness,
                          self_damping=scene.self_damping,
                          self_friction=scene.self_friction,
                          self_search=scene.self_search, self_skin=scene.self_skin,
                          self_capacity=scene.self_capacity,
                          self_candidates=scene.self_candidates)


@functools.lru_cache(maxsize=32)
def check_scene(scene: ClothScene) -> None:
    """Raise ``ValueError`` if ``scene.dt`` is above the stable substep of its cloth."""
    dc.check_params(cloth_config(scene), make_cloth(scene))


# ----------------------------------------------------------------------------- the macro

def grasp_set(scene: ClothScene, x, pick, contact_adjustment: bool):
    """``(grip (V,), start (3,))``: the held vertices (1/0, no gradient) and the gripper's
    start point [m]. With contact adjustment the start is the nearest vertex, with a
    straight-through gradient so that d start / d pick = identity."""
    xs = jax.lax.stop_gradient(x)
    if contact_adjustment:
        i = jnp.argmin(jnp.sum((xs - jax.lax.stop_gradient(pick)) ** 2, -1))
        centre = xs[i]
        start = centre + (pick - jax.lax.stop_gradient(pick))
    else:
        centre = jax.lax.stop_gradient(pick)
        start = pick
    r = scene.grasp_radius * scene.mesh_spacing
    # Only the layer under the fingers: the vertices near the centre in space *and* on the
    # cloth (rest positions) of the vertex nearest to it. Without that, a pick on a folded
    # cloth would also lift a layer below wherever it lies within the grasp radius (with
    # self-collision off the layers lie in one plane; with it, where a stack is squeezed).
    rest = jnp.asarray(_cloth_np(scene)[0], x.dtype)
    k = jnp.argmin(jnp.sum((xs - centre) ** 2, -1))
    near = jnp.sum((xs - centre) ** 2, -1) <= r * r
    same_layer = jnp.sum((rest - rest[k]) ** 2, -1) <= r * r
    grip = (near & same_layer).astype(x.dtype)
    return grip, start


def gripper_path(scene: ClothScene, start, place, n_move: int):
    """Gripper waypoints (n_move + 1, 3) [m]: an eased arc from ``start`` to ``place`` whose
    height peaks at ``arc_height`` x the table-plane distance."""
    u = jnp.linspace(0.0, 1.0, n_move + 1, dtype=start.dtype)
    s = 0.5 - 0.5 * jnp.cos(jnp.pi * u)
    dist = jnp.sqrt(jnp.sum((place - start)[:2] ** 2) + 1e-12)
    lift = scene.arc_height * dist * jnp.sin(jnp.pi * s)
    up = jnp.asarray([0.0, 0.0, 1.0], start.dtype)
    return start + (place - start) * s[:, None] + lift[:, None] * up


def pick_place(scene: ClothScene, substeps: int, cloth: dc.Cloth, state: dc.ClothState,
               action, contact_adjustment: bool) -> dc.ClothState:
    """One pick-and-place action ``(x, y, z, x', y', z')`` [m] as ``substeps`` substeps of
    ``cloth`` in two checkpointed rollouts (segments of ``scene.segment`` substeps): grasp
    at the pick point, carry along :func:`gripper_path` for ``substeps - settle_substeps``
    substeps, release, settle."""
    n_settle = scene.settle_substeps
    n_move = substeps - n_settle
    if n_move < 1:
        raise ValueError(f"cloth tasks need substeps > settle_substeps = {n_settle}, "
                         f"got {substeps}")
    cfg = cloth_config(scene)
    pick, place = action[:3], action[3:]
    grip, start = grasp_set(scene, state.x, pick, contact_adjustment)
    path = gripper_path(scene, start, place, n_move)
    vel = (path[1:] - path[:-1]) / scene.dt
    state = state.replace(grip=grip[None], gripper_pos=start[None],
                          gripper_vel=jnp.zeros_like(state.gripper_vel))

    # two rollouts: the grip is fixed in each, so the solver's grip arithmetic is hoisted
    # out of the loop (a per-substep grip mask would keep it inside)
    state = dc.rollout(cfg, cloth, state, n_move, segment=scene.segment,
                       gripper_vel=vel[:, None, :])
    state = state.replace(grip=jnp.zeros_like(state.grip),
                          gripper_vel=jnp.zeros_like(state.gripper_vel))
    if n_settle:
        state = dc.rollout(cfg, cloth, state, n_settle, segment=scene.segment)
    return state


# ----------------------------------------------------------------------------- fold plans

def _square_corners(scene: ClothScene):
    n = scene.n
    return {"00": 0, "01": n - 1, "10": (n - 1) * n, "11": n * n - 1}


def _nearest(v, p):
    return int(np.argmin(np.sum((v[:, :2] - np.asarray(p)[None]) ** 2, 1)))


def fold_plan(scene: ClothScene):
    """The canonical fold sequence: a tuple of ``(vertex index, place point (3,))`` in the
    canonical (target) frame."""
    v, _ = _cloth_np(scene)
    plan = []
    if scene.folds in ("diag1", "diag3"):
        if scene.shape != "square":
            raise ValueError(f"fold sequence {scene.folds!r} needs a square cloth")
        c = _square_corners(scene)
        plan.append((c["00"], 0.9 * v[c["11"]]))       # onto the opposite corner
        if scene.folds == "diag3":
            plan.append((c["10"], 0.9 * v[c["01"]]))   # triangle in half
            plan.append((c["01"], 0.9 * v[c["11"]]))   # and once more
    elif scene.folds == "tshirt":
        if scene.shape != "tshirt":
            raise ValueError("fold sequence 'tshirt' needs a T-shirt cloth")
        o = dict(scene.outline)
        hw = o["width"] / 2
        lo, hi = v[:, :2].min(0), v[:, :2].max(0)
        arm = lo[1] + o["length"] - o["sleeve_width"]
        for side in (-1.0, 1.0):  # sleeve tips folded in, mirrored across the body side
            tip = _nearest(v, (side * hi[0], arm))
            x_in = side * (2 * hw - abs(v[tip, 0]))
            plan.append((tip, np.array([x_in, v[tip, 1], 0.0])))
        hem = _nearest(v, (-hw, lo[1]))
        shoulder = _nearest(v, (-hw, lo[1] + o["length"]))
        plan.append((hem, np.array([0.9 * hw, v[hem, 1], 0.0])))
        plan.append((shoulder, np.array([0.9 * hw, v[shoulder, 1], 0.0])))
    return tuple((int(i), np.asarray(p, np.float32)) for i, p in plan)


FOLD_PLANS = ("", "diag1", "diag3", "tshirt")


def plan_action(x, index: int, place) -> jnp.ndarray:
    """The action picking vertex ``index`` (at its current position) and placing it at
    ``place``."""
    return jnp.concatenate([x[index], jnp.asarray(place, x.dtype)])


#: Time [s] of free settling after the canonical fold, so the goal of a fold task and the
#: start of an unfold task are at rest.
REST_TIME = 0.5


def settle(scene: ClothScene, state: dc.ClothState, n: int) -> dc.ClothState:
    """``n`` substeps with nothing held (one rollout)."""
    cfg, cloth = cloth_config(scene), make_cloth(scene)
    state = state.replace(grip=jnp.zeros_like(state.grip),
                          gripper_vel=jnp.zeros_like(state.gripper_vel))
    return dc.rollout(cfg, cloth, state, n)


@functools.lru_cache(maxsize=16)
def folded_vertices(scene: ClothScene, substeps: int) -> np.ndarray:
    """The canonical folded cloth (V, 3) [m]: :func:`fold_plan` run from the flat cloth at
    the target pose with contact adjustment on, then ``REST_TIME`` of free settling (NumPy;
    computed once per scene)."""
    check_scene(scene)
    plan = fold_plan(scene)
    with jax.ensure_compile_time_eval():
        state = _run_folds(scene, substeps, plan)
        if plan:
            state = jax.jit(lambda s: settle(scene, s, round(REST_TIME / scene.dt)))(state)
        return np.asarray(state.x, np.float32)


@functools.lru_cache(maxsize=16)
def fold_prefix_vertices(scene: ClothScene, substeps: int, n: int) -> np.ndarray:
    """The cloth (V, 3) [m] after the first ``n`` folds of :func:`fold_plan` from the flat
    cloth at the target pose, as an episode has it after step ``n`` (each fold's own settling
    only, no ``REST_TIME``; NumPy, computed once per scene)."""
    check_scene(scene)
    with jax.ensure_compile_time_eval():
        return np.asarray(_run_folds(scene, substeps, fold_plan(scene)[:n]).x, np.float32)


def _run_folds(scene: ClothScene, substeps: int, plan) -> dc.ClothState:
    """The flat cloth at the target pose after the pick-and-places of ``plan`` (fold index,
    place point pairs), contact adjustment on, each jitted step run eagerly in turn."""
    cloth = make_cloth(scene)
    state = dc.ClothState.create(cloth, n_grippers=1, cfg=cloth_config(scene))
    step = jax.jit(lambda s, a: pick_place(scene, substeps, cloth, s, a, True))
    for index, place in plan:
        state = step(state, plan_action(state.x, index, place))
    return state


def flat_vertices(scene: ClothScene) -> np.ndarray:
    return np.asarray(_cloth_np(scene)[0], np.float32)


def heights_over_points(x, faces, p):
    """For table points ``p`` (P, 1, 2+) and every triangle of the cloth ``x`` (faces (F, 3)):
    the height of the triangle above each point (P, F) and whether the triangle's
    table-plane projection contains the point (barycentric weights all >= 0; a triangle
    seen edge-on contains nothing)."""
    a, b, c = (x[faces[:, k]] for k in range(3))
    det = (b[:, 1] - c[:, 1]) * (a[:, 0] - c[:, 0]) + (c[:, 0] - b[:, 0]) * (a[:, 1] - c[:, 1])
    det = np.where(np.abs(det) > 1e-12, det, np.nan)
    l1 = ((b[:, 1] - c[:, 1]) * (p[..., 0] - c[:, 0])
          + (c[:, 0] - b[:, 0]) * (p[..., 1] - c[:, 1])) / det
    l2 = ((c[:, 1] - a[:, 1]) * (p[..., 0] - c[:, 0])
          + (a[:, 0] - c[:, 0]) * (p[..., 1] - c[:, 1])) / det
    l3 = 1.0 - l1 - l2
    inside = (l1 >= 0) & (l2 >= 0) & (l3 >= 0)
    return l1 * a[:, 2] + l2 * b[:, 2] + l3 * c[:, 2], inside


def layer_gaps(x, faces, rest, exclude):
    """Vertical gaps [m] between the cloth's layers: for every vertex and every triangle
    whose table-plane projection contains it (and whose corners are all farther than
    ``exclude`` from it on the rest mesh, so a crease's own neighbours do not count), the
    height of the vertex over or under the triangle at that point (NumPy, host side; used
    by the tests and the resolution study to tell layers lying apart from layers that
    pass through each other)."""
    p = x[:, None, :]
    z, inside = heights_over_points(x, faces, p)
    far = np.min(np.linalg.norm(rest[faces][None] - rest[:, None, None], axis=-1), -1) > exclude
    return np.abs(p[..., 2] - z)[inside & far]


def rigid_pose(key, scene: ClothScene, x):
    """``x`` rotated about the vertical axis through the table centre by a heading uniform
    in ``±rotation_range``, then shifted in the table plane by a uniform draw over the
    shifts that keep the rotated flat cloth inside ``±table_half`` (and within
    ``±offset_range`` per axis). ``x`` is a start in the canonical pose, so the flat cloth's
    extent bounds it (and, for an unfold task, the cloth it unfolds into)."""
    k_rot, k_off = jax.random.split(key)
    # float32 draws in either precision: a seed gives the same pose under x64
    th = jax.random.uniform(k_rot, (), jnp.float32, minval=-scene.rotation_range,
                            maxval=scene.rotation_range)
    u = jax.random.uniform(k_off, (2,), jnp.float32)
    c, s = jnp.cos(th), jnp.sin(th)

    def rotate(p):  # element-wise, not a matrix product: bit-identical under vmap
        return jnp.stack([c * p[:, 0] - s * p[:, 1], s * p[:, 0] + c * p[:, 1]], 1)

    ext = rotate(jnp.asarray(flat_vertices(scene)[:, :2]))
    lo = jnp.maximum(-scene.offset_range, -scene.table_half - jnp.min(ext, 0))
    hi = jnp.minimum(scene.offset_range, scene.table_half - jnp.max(ext, 0))
    off = lo + u * jnp.maximum(hi - lo, 0.0)
    xy = rotate(x) + off
    return jnp.concatenate([xy, x[:, 2:]], 1)


def check_fits(scene: ClothScene) -> None:
    """Raise ``ValueError`` unless the flat cloth fits inside ``±table_half`` at every
    heading (its farthest vertex from the centre is within ``table_half``)."""
    r = float(np.max(np.linalg.norm(flat_vertices(scene)[:, :2], axis=1)))
    if r > scene.table_half:
        raise ValueError(f"table_half={scene.table_half} m is too small for this cloth: it "
                         f"reaches {r:.3f} m from its centre at some heading")


#: Margin [m] of the action box around the start region.
REACH_MARGIN = 0.05


def reach(scene: ClothScene) -> float:
    """Half-width [m] of the action box in the table plane: the start region
    (``table_half``) plus :data:`REACH_MARGIN`."""
    return scene.table_half + REACH_MARGIN
