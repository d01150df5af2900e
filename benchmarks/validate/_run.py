"""Running a scene for a check: a jitted scan of substep chunks with a probe after each,
timed with the compilation excluded."""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import numpy as np

from dax_physics import mpm


def trace(cfg, params, state, n_chunks: int, every: int, probe, step=None):
    """Run ``n_chunks * every`` substeps of ``step`` (default :func:`dax_physics.mpm.step`
    with ``cfg`` and ``params``); return ``(final state, probes (n_chunks, ...) as float64
    NumPy, wall seconds)`` where ``probe(state)`` is evaluated after each chunk. The wall
    time excludes compilation (the program is compiled ahead of time)."""
    if step is None:
        def step(s):
            return mpm.step(cfg, params, s)

    def run(s):
        def body(s, _):
            s = jax.lax.fori_loop(0, every, lambda i, s: step(s), s)
            return s, probe(s)

        return jax.lax.scan(body, s, None, length=n_chunks)

    compiled = jax.jit(run).lower(state).compile()
    t0 = time.perf_counter()
    final, probes = jax.block_until_ready(compiled(state))
    wall = time.perf_counter() - t0
    return final, np.asarray(probes, np.float64), wall


def zero_crossings(t, a):
    """Times where ``a(t)`` changes sign, linearly interpolated."""
    t, a = np.asarray(t, np.float64), np.asarray(a, np.float64)
    i = np.nonzero(np.sign(a[1:]) != np.sign(a[:-1]))[0]
    return t[i] - a[i] * (t[i + 1] - t[i]) / (a[i + 1] - a[i])


def masked_mean(mask, values):
    """Mean of ``values`` over ``mask`` (jittable)."""
    return jnp.sum(jnp.where(mask, values, 0.0)) / jnp.maximum(jnp.sum(mask), 1)
