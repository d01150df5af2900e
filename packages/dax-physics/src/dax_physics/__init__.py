"""dax-physics: differentiable MLS-MPM and mass-spring cloth solvers in JAX (SI units, z up).

The top level holds the MPM solver (:mod:`dax_physics.mpm`, whose public names are
re-exported here) and what both solvers share (colliders, materials, samplers,
:func:`checkpointed_scan`); the cloth solver is :mod:`dax_physics.cloth`. Both expose the
same verbs with the same argument order, ``(cfg, data, state, ...)`` where ``data`` is the
solver's differentiable numbers (:class:`MaterialParams` or a ``cloth.Cloth``):

* ``step(cfg, data, state)``: one substep of ``cfg.dt`` seconds;
* ``rollout(cfg, data, state, n_substeps, *, segment=None, unroll=1)``: many, as one
  optionally checkpointed scan;
* ``check_params(cfg, data)``: eager, once: refuses data that does not fit ``cfg`` or
  makes ``cfg.dt`` unstable, naming the largest stable dt; ``max_stable_dt`` returns it;
* ``check_state(state)``: after a rollout, raises if the state went bad;
* ``grasp`` and ``release``: attach and detach particles or vertices.

Everything but the checks is pure and works under ``jax.jit``, ``jax.vmap`` and
``jax.grad``; nothing is jitted at definition (the caller jits, with ``cfg`` and the step
counts static). :mod:`dax_physics.precision` holds the full-precision matrix product and
the deterministic-GPU setting.
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
