"""Several processes (hosts) running one sharded batch: the library side of
``jax.distributed``.

Every process calls :func:`initialize` (:func:`jax.distributed.initialize`; on CPU the
processes talk over Gloo, JAX's default CPU collectives) before anything else touches
JAX. After it ``jax.devices()`` lists every process's devices, so
:func:`dax_tasks.core.sharding.batch_mesh` spans them all and the vectorised env splits its
batch over every host with no other change. :func:`rollout_gradient` runs a batch of
rollouts of one task with random actions forward and backward (the gradient of the summed
reward wrt every action) and gathers the result so that every process holds all of it;
:func:`digest` names such a result by its bytes. The command-line job that runs it on
several hosts is ``python -m benchmarks.distributed`` (from the repository root).

Every process must run the same program in the same order (JAX's multi-controller
model); the batch size must be a multiple of the global device count for the batch to be
split (:mod:`dax_tasks.core.sharding`), and it is refused otherwise when there is more than
one process (each would otherwise compute the whole batch).
"""

from __future__ import annotations

import hashlib

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import multihost_utils

from .sharding import is_sharded, shard_batch
from .wrappers import VmapWrapper


def _check_address(coordinator: str) -> None:
    host, sep, port = coordinator.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(f"coordinator must be HOST:PORT (a port in 1..65535), "
                         f"got {coordinator!r}")


def initialize(coordinator: str, num_processes: int, process_id: int,
               timeout_s: int = 120) -> None:
    """Join the ``num_processes``-process JAX job whose process 0 listens at
    ``coordinator`` (``HOST:PORT``) as process ``process_id``; call it first, before any
    JAX computation. ``timeout_s``: how long to wait for the others."""
    _check_address(coordinator)
    if isinstance(num_processes, bool) or not isinstance(num_processes, int) \
            or num_processes < 1:
        raise ValueError(f"num_processes must be a positive int, got {num_processes!r}")
    if isinstance(process_id, bool) or not isinstance(process_id, int) \
            or not 0 <= process_id < num_processes:
        raise ValueError(f"process_id must be an int in [0, {num_processes}), "
                         f"got {process_id!r}")
    jax.distributed.initialize(coordinator_address=coordinator, num_processes=num_processes,
                               process_id=process_id, initialization_timeout=timeout_s)


def rollout_gradient_fn(env, batch: int, steps: int):
    """The jitted job of :func:`rollout_gradient`: ``job(key) -> dict`` of global arrays
    (split over every device of every process), for benchmarks that compile and time it
    apart (``benchmarks/scaling.py``)."""
    for name, value in (("batch", batch), ("steps", steps)):
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ValueError(f"{name} must be a positive int, got {value!r}")
    if jax.process_count() > 1 and not is_sharded(batch):
        raise ValueError(f"batch {batch} is not a multiple of the {jax.device_count()} "
                         f"devices of the {jax.process_count()} processes")
    venv = VmapWrapper(env, batch_size=batch)
    low, high = jnp.asarray(env.spec.action_low), jnp.asarray(env.spec.action_high)

    def job(key):
        k_reset, k_act = jax.random.split(key)
        _, state = venv.reset(k_reset)
        actions = shard_batch(jax.random.uniform(
            k_act, (batch, steps, env.spec.action_dim), minval=low, maxval=high))

        def total(actions):
            def body(s, a):
                _, s, reward, _, info = venv.step(s, a)
                return s, (reward, info["r_gt"])

            _, (rewards, r_gt) = jax.lax.scan(body, state, jnp.swapaxes(actions, 0, 1))
            return jnp.sum(rewards), (rewards.T, r_gt[-1])

        (ret, (rewards, final_r_gt)), grad = jax.value_and_grad(total, has_aux=True)(
            actions)
        return {"return": ret, "rewards": shard_batch(rewards),
                "final_r_gt": shard_batch(final_r_gt), "grad": shard_batch(grad)}

    return jax.jit(job)


def rollout_gradient(env, batch: int, steps: int, seed: int = 0) -> dict:
    """``batch`` rollouts of ``env`` for ``steps`` steps, forward and backward, split over
    every device of every process (:func:`dax_tasks.core.sharding.shard_batch`).

    Starts and uniform random actions come from ``PRNGKey(seed)`` inside one jitted
    program (the same numbers on any number of devices). Returns NumPy arrays that every
    process holds whole: ``return`` (the summed reward of the batch), ``rewards``
    (batch, steps), ``final_r_gt`` (batch,) and ``grad`` (batch, steps, action_dim), the
    gradient of ``return`` wrt the actions."""
    out = rollout_gradient_fn(env, batch, steps)(jax.random.PRNGKey(seed))
    out = multihost_utils.process_allgather(out, tiled=True)
    return {k: np.asarray(v) for k, v in out.items()}


def digest(result: dict) -> str:
    """SHA-256 of the result's arrays (names, dtypes, shapes and bytes), in name order."""
    h = hashlib.sha256()
    for name in sorted(result):
        a = np.ascontiguousarray(result[name])
        h.update(f"{name}:{a.dtype.str}:{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()
