"""3D MLS-MPM (APIC transfers, quadratic B-splines) as pure JAX functions.

The split follows the rest of dax-physics:

* :class:`MPMConfig` is static and hashable (grid, time step, material kinds, colliders,
  walls). It is a ``static_argnums`` argument; changing it recompiles. It refuses, when
  built, a ``dt`` above the largest stable substep of its material table.
* :class:`MaterialParams` (see :mod:`dax_physics.materials`) holds the differentiable
  material numbers; :func:`check_params` checks them against a config once, eagerly
  (shapes, values, the stable ``dt`` of these numbers, named in its message).
* :class:`MPMState` is the dynamic pytree: particles, collider poses and bookkeeping.

The verbs, shared with :mod:`dax_physics.cloth`: :func:`step` (one substep),
:func:`rollout` (many, one optionally checkpointed scan; neither is jitted: the caller
jits), :func:`check_params`, :func:`max_stable_dt`, :func:`check_state` (after a rollout),
:func:`grasp` and :func:`release`. All but the checks work under ``jax.jit``,
``jax.vmap`` (a batch of scenes) and ``jax.grad``. Units are SI, z is up.

Layout: :mod:`.config` (configuration, stability bounds), :mod:`.state` (state, its
checks, grasping), :mod:`.substep` (the substep as named stages: stencil, p2g,
grid_update, boundaries, g2p, deformation with plasticity, held, stability),
:mod:`.constitutive` (stresses, polar rotation, return map, stored energy),
:mod:`.algebra` (3x3 matrices as component lists), :mod:`.diagnostics`.

**Active region.** The simulation domain is ``domain`` cells of size ``dx`` starting at the
world origin. The grid that is actually allocated is a *window* of static shape ``window``
cells whose integer origin is recentred on the particles' bounding box at every substep, so
a rope on a large table is simulated on a grid the size of the rope. With
``window == domain`` (the default) the window is the whole domain. A particle whose
B-spline stencil does not fit in the window (or in the domain) is never dropped silently:
its stencil is clamped into the window and the state's ``escaped`` flag is raised, which
:func:`check_state` turns into an error. Results of a windowed run equal the full-grid run
to float32 rounding whenever the flag stays down.

**Walls.** The domain boundary carries walls ``wall_cells`` thick: their surfaces are the
planes ``wall_cells * dx`` and ``(domain - wall_cells) * dx`` of each axis, and the grid
nodes on or beyond a surface (global index ``<= wall_cells`` or ``>= domain -
wall_cells``) are constrained: ``"slip"`` removes the velocity component into the wall,
``"sticky"`` zeroes it, ``"none"`` disables them. Material comes to rest *on* the surface,
and :func:`init_state` accepts particles between the surfaces. The Taichi and Warp
reference scenes' band of ``b`` cells is ``wall_cells = b - 1`` here.

**Deformation in float32.** The state stores the displacement gradient ``H = F - I``
(``b_e - I`` for plastic particles), not ``F``, and updates it as ``H <- H + dt C (I +
H)``. A substep changes F by about 1e-5: added to O(1) entries of ``F`` in float32 the
increments would keep two digits, and the rounding of ``1 + d`` is biased (the spacing of
float32 numbers halves below 1), so a solid under a steady load would creep. Stored as
``H`` the increments keep their precision; ``MPMState.F`` returns ``I + H``.

**Fluids carry no tension.** A fluid particle's volume ratio is capped at ``J <= 1``: a
weakly compressible liquid pushes but does not pull, and liquid that spreads or separates
is a free surface at zero pressure (``MPMConfig(fluid_tension=True)`` lifts the cap, as
in the Taichi and Warp reference scenes). Without the cap the stretched particles'
negative pressure holds a collapsing water column together (the validation suite's
``dam_break`` check against Martin & Moyce's measurements).
"""

from ..materials import Material, MaterialParams
from .config import CFL, WALL_MODES, MPMConfig, check_params, max_stable_dt, max_stable_speed
from .constitutive import KIND_CODE, POLAR_ITERS, polar_rotation, strain_energy_density
from .diagnostics import kinetic_energy, momentum, potential_energy, total_mass
from .state import (
    MPMState,
    check_state,
    grasp,
    init_state,
    release,
    set_collider_velocity,
)
from .substep import DRIVE_FRACTION, REVERSE_SAVED, rollout, step

__all__ = [
    "CFL", "DRIVE_FRACTION", "KIND_CODE", "POLAR_ITERS", "REVERSE_SAVED", "WALL_MODES",
    "MPMConfig", "MPMState", "Material", "MaterialParams", "check_params", "check_state",
    "grasp", "init_state", "kinetic_energy", "max_stable_dt", "max_stable_speed",
    "momentum", "polar_rotation", "potential_energy", "release", "rollout",
    "set_collider_velocity", "step", "strain_energy_density", "total_mass",
]
