"""dax-physics: differentiable MLS-MPM and mass-spring cloth solvers in JAX (SI units, z up)."""

from importlib.metadata import PackageNotFoundError, version

from . import cloth, colliders, materials, mpm, sampling
from ._pytree import pytree_dataclass, static_field
from .colliders import ColliderSpec, ColliderState
from .materials import Material, MaterialParams, dough, rope, tofu, water
from .mpm import (
    MPMConfig,
    MPMState,
    check_state,
    grasp,
    init_state,
    max_stable_dt,
    release,
    rollout,
    set_collider_velocity,
    substep,
)

try:
    __version__ = version("dax-physics")
except PackageNotFoundError:  # pragma: no cover - running from a source tree
    __version__ = "0.0.0+unknown"

__all__ = [
    "ColliderSpec", "ColliderState", "MPMConfig", "MPMState", "Material", "MaterialParams",
    "check_state", "cloth", "colliders", "dough", "grasp", "init_state", "materials",
    "max_stable_dt", "mpm", "pytree_dataclass", "release", "rollout", "rope", "sampling",
    "set_collider_velocity", "static_field", "substep", "tofu", "water",
]
