"""Mass-spring cloth for dax-physics (SI units, z up).

* General triangle meshes (:mod:`.sim`, :mod:`.mesh`): structural, shear and bending
  springs derived from the mesh, gravity, air drag, table contact with Coulomb friction,
  the shared SDF colliders, vertex-vertex self-collision (a Verlet neighbour list kept in
  the state, or every pair; :mod:`.selfcollision`), strain limiting, grippers and the
  pick-and-place macro (:mod:`.grasp`), checkpointed rollouts.
* The verbs of :mod:`dax_physics.mpm`, same argument order: ``step(cfg, cloth, state)``,
  ``rollout(cfg, cloth, state, n_substeps, *, segment=None, unroll=1, gripper_vel=None)``,
  ``check_params(cfg, cloth)``, ``max_stable_dt(cfg, cloth)``, ``check_state(state)``,
  ``grasp``, ``release``.

See ``README_cloth.md`` for the parameters, their units and the stable time step.
"""

from .grasp import PickPlace, grasp, move_gripper, nearest_vertex_point, pick_and_place, release
from .mesh import (
    MeshError,
    load_mesh,
    mesh_springs,
    polygon_mesh,
    square_mesh,
    tshirt_mesh,
    tshirt_outline,
    validate_mesh,
)
from .selfcollision import NeighbourList, neighbour_list, update_neighbours
from .sim import (
    CLASS_GROUP,
    SELF_SEARCHES,
    Cloth,
    ClothConfig,
    ClothState,
    check_params,
    check_state,
    energy,
    make_cloth,
    max_stable_dt,
    mesh_cloth,
    rollout,
    scale_moduli,
    self_collision_forces,
    self_collision_overflow,
    spring_forces,
    spring_layout,
    square_cloth,
    step,
    tshirt_cloth,
    with_neighbours,
)

__all__ = [
    "CLASS_GROUP", "SELF_SEARCHES", "Cloth", "ClothConfig", "ClothState", "MeshError",
    "NeighbourList", "PickPlace", "check_params", "check_state", "energy", "grasp",
    "load_mesh", "make_cloth", "max_stable_dt", "mesh_cloth", "mesh_springs",
    "move_gripper", "nearest_vertex_point", "neighbour_list", "pick_and_place",
    "polygon_mesh", "release", "rollout", "scale_moduli", "self_collision_forces",
    "self_collision_overflow", "spring_forces", "spring_layout", "square_cloth",
    "square_mesh", "step", "tshirt_cloth", "tshirt_mesh", "tshirt_outline",
    "update_neighbours", "validate_mesh", "with_neighbours",
]
