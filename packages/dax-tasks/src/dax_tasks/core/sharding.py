"""Batches spread over every device: one mesh, one rule.

The vectorised env (:class:`dax_tasks.core.wrappers.VmapWrapper`, so :func:`training_env` and
every RL method), the planners' populations (dax-algos' CEM) and the RL evaluation
rollouts call :func:`shard_batch` where a batch is made or stepped. With one device it
does nothing. With ``n > 1`` devices (several GPUs, ``XLA_FLAGS=
--xla_force_host_platform_device_count=n`` on CPU, or every process's devices after
:func:`dax_tasks.core.distributed.initialize`) it constrains the leading (batch) axis of each
array to be split over the 1-D mesh :func:`batch_mesh` (``NamedSharding(mesh,
PartitionSpec("batch"))``), so XLA runs each device's share of the envs on that device.
The user changes no code: the same jitted function runs sharded when more than one device
is present.

**The divisibility rule.** A leaf is constrained only if its leading size is a multiple of
the device count; otherwise it is left to XLA as it is (on one device, or replicated),
never split unevenly and never padded. So a batch of 6 on 4 devices runs as on one device,
and the results are the same either way: choose batch sizes (``num_envs``, a planner's
``population``) that are multiples of the device count to use them all
(:func:`is_sharded` says whether a size will be).

Inside ``jit`` the constraint is :func:`jax.lax.with_sharding_constraint`; outside it the
arrays are placed with :func:`jax.device_put`. Under an outer ``vmap`` (e.g. the benchmark
runner's seeds) the vmapped axis is left unconstrained, the env axis is still split.
Element-wise work per env gives the same bits sharded or not; a reduction over the batch
(a mean over envs, a top-k over a population) is computed per device and then combined,
which may change the float summation order (the package README gives the differences).
"""

from __future__ import annotations

import functools

import jax
from jax.sharding import AxisType, Mesh, NamedSharding, PartitionSpec

#: The name of the mesh axis the batch is split over.
BATCH_AXIS = "batch"


@functools.lru_cache(maxsize=8)
def _mesh(devices: tuple) -> Mesh:
    return jax.make_mesh((len(devices),), (BATCH_AXIS,), axis_types=(AxisType.Auto,),
                         devices=list(devices))


def batch_mesh() -> Mesh:
    """The 1-D mesh over ``jax.devices()`` (every process's devices), axis ``"batch"``;
    built once per set of devices."""
    return _mesh(tuple(jax.devices()))


def device_count() -> int:
    """How many devices a batch is split over (``jax.device_count()``)."""
    return jax.device_count()


def batch_sharding() -> NamedSharding:
    """``NamedSharding(batch_mesh(), PartitionSpec("batch"))``: leading axis split."""
    return NamedSharding(batch_mesh(), PartitionSpec(BATCH_AXIS))


def is_sharded(size: int) -> bool:
    """Whether a batch of leading size ``size`` is split: more than one device and ``size``
    a multiple of the device count (the divisibility rule above)."""
    n = device_count()
    return n > 1 and size % n == 0


def _in_trace(leaves) -> bool:
    return any(isinstance(x, jax.core.Tracer) for x in leaves)


def shard_batch(tree):
    """``tree`` with the leading axis of every array split over :func:`batch_mesh`.

    Every leaf must have a leading (batch) axis, and all the same size; a leaf without one
    is a caller's bug and raises ``ValueError`` naming it. A no-op on one device and when
    the batch size is not a multiple of the device count. Works inside ``jit``, ``vmap``
    and ``grad`` (the constraint's transpose constrains the cotangent the same way) and
    outside (``device_put``)."""
    paths_leaves, treedef = jax.tree_util.tree_flatten_with_path(tree)
    if not paths_leaves:
        return tree
    sizes = {}
    for path, leaf in paths_leaves:
        shape = jax.numpy.shape(leaf)
        if len(shape) == 0:
            raise ValueError(f"shard_batch: leaf {jax.tree_util.keystr(path) or '<root>'} "
                             "is a scalar, with no batch axis to split")
        sizes.setdefault(shape[0], jax.tree_util.keystr(path) or "<root>")
    if len(sizes) > 1:
        named = ", ".join(f"{p}: {s}" for s, p in sizes.items())
        raise ValueError(f"shard_batch: leaves have different leading (batch) sizes "
                         f"({named})")
    (size,) = sizes
    if not is_sharded(size):
        return tree
    leaves = [leaf for _, leaf in paths_leaves]
    sharding = batch_sharding()
    if _in_trace(leaves):
        leaves = [jax.lax.with_sharding_constraint(x, sharding) for x in leaves]
    else:
        leaves = jax.device_put(leaves, sharding)
    return jax.tree_util.tree_unflatten(treedef, leaves)
