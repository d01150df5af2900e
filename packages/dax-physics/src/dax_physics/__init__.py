"""dax-physics: differentiable MLS-MPM and mass-spring cloth solvers in JAX (SI units, z up).

The top level holds the MPM solver (:mod:`dax_physics.mpm`) and what both solvers share
(colliders, materials, :func:`checkpointed_scan`); the cloth solver is
:mod:`dax_physics.cloth`. Both use the same verbs: ``step`` (one substep), ``rollout``
(many, one checkpointed scan), ``check_state`` (raise if a state went bad), ``grasp`` and
``release``. :mod:`dax_physics.precision` holds the full-precision and
deterministic-GPU settings.
"""

from importlib.metadata import PackageNotFoundError, version

from . import cloth, colliders, materials, mpm, precision, sampling
from ._pytree import pytree_dataclass, static_field
from .colliders import ColliderSpec, ColliderState
from .materials import Material, MaterialParams, dough, rope, tofu, water
from .mpm import (
    MPMConfig,
    MPMState,
    check_params,
    check_state,
    grasp,
    init_state,
    max_stable_dt,
    max_stable_speed,
    release,
    rollout,
    set_collider_velocity,
    step,
)
from .scan import checkpointed_scan

try:
    __version__ = version("dax-physics")
except PackageNotFoundError:  # pragma: no cover - running from a source tree
    __version__ = "0.0.0+unknown"

__all__ = [
    "ColliderSpec", "ColliderState", "MPMConfig", "MPMState", "Material", "MaterialParams",
    "check_params", "check_state", "checkpointed_scan", "cloth", "colliders", "dough",
    "grasp", "init_state", "materials", "max_stable_dt", "max_stable_speed", "mpm",
    "precision", "pytree_dataclass", "release", "rollout", "rope", "sampling",
    "set_collider_velocity", "static_field", "step", "tofu", "water",
]
