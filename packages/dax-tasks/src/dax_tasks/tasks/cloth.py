"""The cloth tasks: Fold-Cloth-1, Fold-Cloth-3, Fold-T-shirt, Unfold-Cloth-1, Unfold-Cloth-3.

Scene (SI units, z up). One mass-spring cloth (:mod:`dax_physics.cloth`, mesh path) on a
table at z = 0 with Coulomb friction (static 1.0, dynamic 0.8) and self-collision, and one
gripper. The square cloth is 0.3 m x 0.3 m with 11 x 11 vertices (3 cm spacing,
union-jack triangulation); the T-shirt a 0.2 m wide, 0.25 m long body with 8 cm sleeves on
a 2.5 cm grid (:func:`dax_physics.cloth.tshirt_mesh`). Material (``params.physics``, a
:class:`ClothParams`, so it can be changed, batched or differentiated without
recompiling): 0.2 kg/m^2, stretch = shear 10 N/m, bend 0.5 N/m, dashpot 0.01 N s/m per
spring. Substep ``dt`` = 1e-3 s (square) and 4e-4 s (T-shirt), under the stable bounds
with self-collision (1.04e-3 s and 4.2e-4 s); checked when a task is built, and for other
params by :func:`dax_tasks.core.checks.check_params`. The canonical pose is the cloth
centred on the table centre, the origin.

Self-collision (:data:`SQUARE_CONTACT`, :data:`TSHIRT_CONTACT`), on in all five tasks:
vertex pairs closer than the thickness h repel with ``self_stiffness`` (h - d) and a
viscous ``self_friction`` on their relative velocity; pairs closer than 2 h on the rest
mesh never repel. h is the mesh spacing (3 cm, T-shirt 2.5 cm), so folded layers lie about
h apart (a thick cloth). The pairs come from the neighbour list kept in the cloth state
(``ClothScene.self_search="list"``), which finds every pair closer than h that testing all
pairs finds while its ``overflow`` is 0.

Start, drawn from the key. Fold tasks: the flat cloth; unfold tasks: the canonical folded
cloth (the scripted fold below, simulated once per scene and cached). Either is placed by a
random rigid pose: a heading uniform in ±``rotation_range`` (pi) about the vertical axis
through the table centre, then a shift uniform over all the shifts that keep the rotated
*flat* cloth inside the table region ±``table_half`` (0.35 m; for an unfold task the cloth
it unfolds into fits too), so the cloth lies anywhere on the table at any heading, inside
the gripper's reach. Vertices keep their index: they correspond across seeds and to the
goal.

Goal (fixed per task and scene; :func:`dax_tasks.make` caches it on disk), in the canonical
pose. Fold tasks: the end state of the canonical scripted fold of the flat cloth (each fold
picks one vertex and places it in the cloth's frame), followed by 0.5 s of free settling,
so the goal is at rest:

* Fold-Cloth-1: corner (-,-) onto 0.9 x the opposite corner (+,+): a triangle;
* Fold-Cloth-3: that, then corner (+,-) onto 0.9 x corner (-,+) (the triangle in half),
  then corner (-,+) onto 0.9 x corner (+,+) (in half again);
* Fold-T-shirt: each sleeve tip mirrored across its body side (sleeves in), then the
  bottom-left hem corner and the top-left shoulder onto 0.9 x their mirror across the
  vertical centre line (in half). A sleeve caught between the halves slides back out while
  the cloth settles, and the goal has it so.

Unfold tasks: the flat cloth.

Distance: the goal is a shape, not a place. ``D`` = index-correspondence mean L2 [m]
between the cloth's vertices and the goal's after the goal is moved by the rigid motion in
the table plane (rotation about the vertical, shift) that best maps it onto the cloth
(least squares, the closed-form 2-D Kabsch fit; :meth:`ClothTask.aligned_goal`). D is
differentiable while the cloth is not a point, and a rigid motion of the cloth leaves it
unchanged: moving the cloth around earns nothing, folding it does. λ = 10 /m.

Action: a pick-and-place macro ``(x, y, z, x', y', z')`` [m]: the gripper holds the
vertices within ``grasp_radius`` x spacing (0.75 cm) of the pick point, carries them along
an eased arc (cosine speed profile, height peaking at ``arc_height`` = 0.5 x the
table-plane travel) to the place point over ``substeps - settle_substeps`` substeps,
releases them, and the cloth settles for ``settle_substeps`` (400 + 300 substeps, 0.7 s;
T-shirt 900 + 225 substeps of 4e-4 s, 0.45 s). The carry is the gripper's velocity
command, which the held vertices take, so ``d reward / d action`` is non-zero whenever
something is held. Bounds: x and y within ±0.40 m of the table centre (the table region
plus 5 cm), z in [0, 0.1] m (:data:`Z_MAX`). Horizons: Fold-Cloth-1 3, Fold-Cloth-3 4,
Fold-T-shirt 5, the unfold tasks 10; every fold task has a step after its folds.

Contact adjustment (``spec.contact_adjustment``, default on): the pick point snaps to the
nearest cloth vertex (3-D distance) and the gripper holds the vertices within the grasp
radius of that vertex that are also within it on the rest mesh (one layer of a folded
cloth), so a pick always holds at least one vertex. The snap is straight-through for
gradients (``d start / d pick`` is the identity). Off, the raw pick point is used: a pick
with no vertex within the grasp radius holds nothing, the cloth only settles, and the
action gradient is exactly zero.

Expert (:meth:`ClothTask.expert`; privileged: ``state.physics``, ``state.t`` and
``params.goal``), acting in the cloth's frame. Fold tasks: at step t < the number of folds,
fold t of the canonical plan done on the cloth where it lies (the plan's vertex picked
where it is now and placed at the plan's place point moved by the cloth's rigid pose,
fitted in the table plane on all vertices against the canonical cloth after t folds).
Unfold tasks: the folds undone in reverse order in the cloth's fitted pose. Then, in both,
at each remaining step the vertex farthest from its aligned goal position is picked and
placed there, until every vertex is within :data:`CORRECTION_TOLERANCE` (3 cm) of it; then a
no-op (that vertex picked and put back where it is).

Limitations. Self-collision is vertex-vertex at the mesh spacing, so layers lie about 3 cm
apart, and in a three-fold stack a vertex can end in the plane of another layer. Layers
slide over each other with only viscous friction (nothing holds a layer still against a
steady push).
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np

import dax_physics.cloth as dc
from dax_physics.precision import mm

from ..core import rewards
from ..core.env import Env
from ..core.spec import TaskSpec
from ..viz import images
from . import _cloth
from ._cloth import DEFAULT_MATERIAL, ClothParams, ClothScene

__all__ = ["DEFAULT_MATERIAL", "FOLD_CLOTH1", "FOLD_CLOTH3", "FOLD_TSHIRT", "UNFOLD_CLOTH1",
           "UNFOLD_CLOTH3", "ClothParams", "ClothScene", "ClothTask", "replace_scene"]


#: Height range of pick and place points [m] (the table is z = 0).
Z_MAX = 0.1
#: The unfold experts stop correcting once every vertex is this close to its goal [m].
CORRECTION_TOLERANCE = 0.03


def start_vertices(spec: TaskSpec) -> np.ndarray:
    """The canonical start of an episode before the random pose (V, 3) [m]: the folded cloth
    for unfold tasks, the flat cloth otherwise."""
    scene = spec.scene
    if scene.unfold:
        return _cloth.folded_vertices(scene, spec.substeps)
    return _cloth.flat_vertices(scene)


def _fold_states(scene: ClothScene, substeps: int) -> np.ndarray:
    """(n + 1, V, 3) [m]: the canonical cloth after 0, 1, ..., n - 1 folds of the plan (each
    fold's own settling), then after all n and ``REST_TIME`` (the fold tasks' goal, the
    unfold tasks' start)."""
    n = len(_cloth.fold_plan(scene))
    return np.stack([_cloth.fold_prefix_vertices(scene, substeps, m) for m in range(n)]
                    + [_cloth.folded_vertices(scene, substeps)])


def _planar_pose(x, ref):
    """The rotation about z (2, 2) and table-plane shift (2,) that best map ``ref`` onto
    ``x`` (least squares, 2-D Kabsch)."""
    mx, mr = jnp.mean(x[:, :2], 0), jnp.mean(ref[:, :2], 0)
    a, b = ref[:, :2] - mr, x[:, :2] - mx
    cos = jnp.sum(a * b)
    sin = jnp.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])
    th = jnp.arctan2(sin, cos)
    rot = jnp.asarray([[jnp.cos(th), -jnp.sin(th)], [jnp.sin(th), jnp.cos(th)]])
    return rot, mx - mm(rot, mr)


class ClothTask(Env):
    """The five cloth tasks (see the module docstring). ``params.physics`` is a
    :class:`ClothParams` (density, spring moduli, dashpots, table friction)."""

    LAM = 10.0

    def __init__(self, spec: TaskSpec):
        super().__init__(spec)
        scene = spec.scene
        _cloth.check_scene(scene)
        _cloth.check_fits(scene)
        if spec.substeps <= scene.settle_substeps:
            raise ValueError(f"cloth tasks need substeps > settle_substeps = "
                             f"{scene.settle_substeps}, got {spec.substeps}")
        self.cfg = _cloth.cloth_config(scene)
        #: The cloth with the default material (constant arrays).
        self.base_cloth = _cloth.make_cloth(scene)

    @property
    def substep_dt(self) -> float:
        return self.cfg.dt

    def default_physics_params(self):
        return ClothParams.create()

    def cloth(self, params) -> dc.Cloth:
        """The :class:`dax_physics.cloth.Cloth` with the material of ``params.physics``."""
        return _cloth.cloth_with(self.base_cloth, params.physics)

    def check_physics_params(self, physics) -> None:
        super().check_physics_params(physics)
        for name in ("density", "stretch", "shear", "bend"):
            if not float(getattr(physics, name)) > 0:
                raise ValueError(f"cloth {name} must be > 0, got {float(getattr(physics, name))}")
        for name in ("damping", "friction_static", "friction_dynamic"):
            if float(getattr(physics, name)) < 0:
                raise ValueError(f"cloth {name} must be >= 0, got {float(getattr(physics, name))}")
        dc.check_params(self.cfg, _cloth.cloth_with(self.base_cloth, physics))

    def init(self, key, params):
        """The start cloth (:func:`start_vertices`) at a random rigid pose, at rest."""
        x0 = jnp.asarray(start_vertices(self.spec))
        return dc.ClothState.create(self.base_cloth,
                                    x=_cloth.rigid_pose(key, self.spec.scene, x0),
                                    n_grippers=1, cfg=self.cfg)

    def apply_action(self, physics, action, params):
        """One pick-and-place macro (``spec.substeps`` substeps: carry, then settle)."""
        return _cloth.pick_place(self.spec.scene, self.spec.substeps, self.cloth(params),
                                 physics, action, self.spec.contact_adjustment)

    def canonical_goal(self) -> np.ndarray:
        """The goal vertices (V, 3) [m]: the canonical fold (fold tasks) or the flat cloth
        at the target (unfold tasks)."""
        scene = self.spec.scene
        if scene.unfold:
            return _cloth.flat_vertices(scene)
        return _cloth.folded_vertices(scene, self.spec.substeps)

    def object_points(self, physics):
        return physics.x

    def goal_pose(self, x, goal):
        """``(rot (2, 2), shift (2,))`` [m]: the rigid motion in the table plane (a rotation
        about the vertical, then a shift) that best maps ``goal`` (V, 3) onto the cloth
        ``x`` (V, 3) (least squares, 2-D Kabsch): the pose of the cloth's own frame."""
        return _planar_pose(x, goal)

    def aligned_goal(self, x, goal):
        """``goal`` (V, 3) moved by the rigid motion in the table plane (a rotation about
        the vertical and a shift) that best maps it onto the cloth ``x`` (least squares)."""
        rot, shift = self.goal_pose(x, goal)
        return jnp.concatenate([mm(goal[:, :2], rot.T) + shift, goal[:, 2:]], 1)

    def distance(self, physics, goal):
        """``D`` [m]: the index-correspondence mean L2 between the cloth's vertices and the
        goal's after the goal is aligned to the cloth in the table plane
        (:meth:`aligned_goal`; see the module docstring)."""
        x = physics.x
        goal = jnp.asarray(goal, x.dtype)
        return rewards.l2_correspondence(x, self.aligned_goal(x, goal))

    @property
    def goal_correspondence(self) -> bool:
        """The goal's vertices correspond to the cloth's by index (after the alignment)."""
        return True

    def end_effector(self, physics):
        """The gripper position [m] (3,)."""
        return physics.gripper_pos[0]

    @property
    def object_faces(self):
        """The cloth mesh's triangles (F, 3) (NumPy)."""
        return np.asarray(self.base_cloth.faces)

    @property
    def object_colors(self):
        """The cloth's texture: each vertex coloured by its place on the flat rest mesh
        (:func:`dax_tasks.viz.uv_colors`), so the corners differ in RGB pictures."""
        rest = _cloth.flat_vertices(self.spec.scene)[:, :2]
        lo, hi = rest.min(0), rest.max(0)
        return images.uv_colors((rest - lo) / np.maximum(hi - lo, 1e-9))

    def expert(self, state, params):
        """The scripted expert's action (see the module docstring); pure and jittable."""
        scene = self.spec.scene
        x, goal_points, t = state.physics.x, params.goal, state.t
        plan = _cloth.fold_plan(scene)
        idx = jnp.asarray([i for i, _ in plan], jnp.int32)
        n = len(plan)
        # The cloth's rigid pose is fitted on every vertex against the canonical cloth with
        # as many folds done (physics on the table does not depend on the pose, so the
        # cloth is that state rotated and shifted). No vertex stays put through every fold,
        # so a fit against the flat cloth on "unmoved" vertices would not do.
        refs = jnp.asarray(_fold_states(scene, self.spec.substeps), x.dtype)
        # The correction: pick the vertex farthest from its goal position (the goal aligned
        # to the cloth, as D aligns it) and put it there, or, once every vertex is within
        # CORRECTION_TOLERANCE, pick that vertex and put it back where it is (a no-op).
        goal = self.aligned_goal(x, goal_points)
        err = jnp.sum((x - goal) ** 2, axis=1)
        i = jnp.argmax(err)
        far = err[i] > CORRECTION_TOLERANCE ** 2
        correction = jnp.concatenate([x[i], jnp.where(far, goal[i], x[i])])
        if scene.unfold:
            # Undo the folds in reverse (pick the vertex fold j placed, put it where it was
            # before fold j, in the cloth's fitted pose), then correct.
            j = jnp.clip(n - 1 - t, 0, n - 1)  # the fold to undo at step t
            rot, shift = _planar_pose(x, refs[jnp.clip(n - t, 0, n)])
            before = refs[j][idx[j]]
            place = jnp.concatenate([mm(rot, before[:2]) + shift, before[2:]])
            return jnp.where(t < n, jnp.concatenate([x[idx[j]], place]), correction)
        k = jnp.minimum(t, n - 1)
        rot, shift = _planar_pose(x, refs[k])

        def posed(p):
            return jnp.concatenate([mm(rot, p[:2]) + shift, p[2:]])

        places = jnp.asarray(np.stack([p for _, p in plan]), x.dtype)
        fold = jnp.concatenate([x[idx[k]], posed(places[k])])
        return jnp.where(t < n, fold, correction)


def _spec(name: str, horizon: int, scene: ClothScene, substeps: int) -> TaskSpec:
    r = _cloth.reach(scene)
    low = (-r, -r, 0.0)
    high = (r, r, Z_MAX)
    return TaskSpec(name=name, horizon=horizon, action_kind="pick_place",
                    action_low=low + low, action_high=high + high, substeps=substeps,
                    distance="l2", contact_adjustment=True, obs_stride=1, scene=scene)


#: Self-collision of the square cloth and of the T-shirt: thickness h = the mesh spacing,
#: repulsion stiffness [N/m] and inter-layer friction [N s/m] (see the module docstring).
SQUARE_CONTACT = dict(thickness=0.03, self_stiffness=0.5, self_friction=2.0e-3)
TSHIRT_CONTACT = dict(thickness=0.025, self_stiffness=0.2, self_friction=1.0e-3)

FOLD_CLOTH1 = _spec("fold_cloth1", 3, ClothScene(folds="diag1", **SQUARE_CONTACT), 700)
FOLD_CLOTH3 = _spec("fold_cloth3", 4, ClothScene(folds="diag3", **SQUARE_CONTACT), 700)
FOLD_TSHIRT = _spec("fold_tshirt", 5, ClothScene(shape="tshirt", folds="tshirt", dt=4.0e-4,
                                                 settle_substeps=225, **TSHIRT_CONTACT), 1125)
UNFOLD_CLOTH1 = _spec("unfold_cloth1", 10, ClothScene(folds="diag1", unfold=True,
                                                      **SQUARE_CONTACT), 700)
UNFOLD_CLOTH3 = _spec("unfold_cloth3", 10, ClothScene(folds="diag3", unfold=True,
                                                      **SQUARE_CONTACT), 700)


#: Substeps per env step of the original benchmark's cloth tasks (40 sub-actions x 50).
REFERENCE_SUBSTEPS = 2000


def _reference(spec: TaskSpec, **scene) -> TaskSpec:
    """``spec`` at the original benchmark's resolution (``make(name,
    resolution="reference")``): :data:`REFERENCE_SUBSTEPS` substeps per step with the
    default's share of settling, and the scene changes ``scene`` (vertex count, dt)."""
    settle = round(REFERENCE_SUBSTEPS * spec.scene.settle_substeps / spec.substeps)
    return dataclasses.replace(spec, substeps=REFERENCE_SUBSTEPS, scene=dataclasses.replace(
        spec.scene, settle_substeps=settle, **scene))


# Reference resolution. Square cloths: the original's 512 vertices (a 16 x 32 mask) are
# matched by 23 x 23 = 529 (the nearest square), at dt = 2.5e-4 s (stable bound 3.2e-4 s),
# so a step simulates 0.5 s instead of 0.7 s. T-shirt: 3584 vertices (2.5 cm -> 4.34 mm
# grid; the original has 3573); the fine outline has sliver triangles whose light
# vertices bound the stable substep at 1.2e-5 s, so its 2000 substeps of 1e-5 s cover
# only 0.02 s: the same work per step as the original, not the same motion (a timing
# reference, not a task to solve). The finer meshes put more vertices within a contact
# distance of each other (the square cloths' 4.8 times, the T-shirt's 33 times per unit
# area), so their neighbour lists get more pair slots per vertex (``self_capacity``).
FOLD_CLOTH1_REFERENCE = _reference(FOLD_CLOTH1, n=23, dt=2.5e-4, self_capacity=16.0)
FOLD_CLOTH3_REFERENCE = _reference(FOLD_CLOTH3, n=23, dt=2.5e-4, self_capacity=16.0)
FOLD_TSHIRT_REFERENCE = _reference(FOLD_TSHIRT, spacing=0.00434, dt=1.0e-5,
                                   self_capacity=32.0)
UNFOLD_CLOTH1_REFERENCE = _reference(UNFOLD_CLOTH1, n=23, dt=2.5e-4, self_capacity=16.0)
UNFOLD_CLOTH3_REFERENCE = _reference(UNFOLD_CLOTH3, n=23, dt=2.5e-4, self_capacity=16.0)


def replace_scene(spec: TaskSpec, **changes) -> TaskSpec:
    """``spec`` with scene fields replaced (e.g. a coarser cloth for tests)."""
    return dataclasses.replace(spec, scene=dataclasses.replace(spec.scene, **changes))
