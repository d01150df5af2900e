"""Fusion barriers: values computed once, into buffers of their own, in both solvers.

XLA:CPU fuses a cheap elementwise producer into each of its consumers and recomputes it
there. Where the consumers are many (a stencil's 27 reads per particle, a dozen loops
reading one moment sum, the rows of a stack, each output of a cloth substep reading the
spring force), the producer is then computed many times over. :func:`materialise` stops
that: its result is the output of a while loop, and XLA fuses nothing across a loop
boundary. :func:`materialise_cotangent` does the same for a value's cotangent in reverse
mode. Both are the identity on values, tangents and cotangents (bit for bit).

Neither ``lax.optimization_barrier`` (fused through on CPU), an identity matmul nor a sum
over a zero pad (each lowered to a library call on XLA:CPU, with a fixed cost per call)
serves here; the zero-trip loop costs one buffer write.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp


def _barrier(a):
    """``a`` (an array or a tuple of arrays) itself, as the result of a while loop that runs
    zero times. Its trip count (``bits == bits + 1``, false for every int32) is not known to
    the compiler, so the loop stays. (The bits are read from the first leaf's real part, so
    complex leaves pass too.)"""
    first = jax.tree.leaves(a)[0]
    bits = jax.lax.bitcast_convert_type(jnp.real(first.reshape(-1)[:1]).astype(jnp.float32),
                                        jnp.int32)[0]
    trips = (bits == bits + 1).astype(jnp.int32)
    bump = functools.partial(jax.tree.map, lambda x: x + jnp.ones((), x.dtype))
    return jax.lax.while_loop(lambda c: c[0] < trips, lambda c: (c[0] + 1, bump(c[1])),
                              (jnp.int32(0), a))[1]


@jax.custom_jvp
def materialise(a):
    """``a`` (an array, or a tuple of arrays computed together) in buffers of its own, so
    that its consumers read it instead of recomputing it.

    A tuple keeps its members apart: XLA may compute them in one multi-output loop that
    shares their common work, but need not (XLA:CPU gives each output a loop of its own).
    Tangents and cotangents pass straight through (a while loop has no transpose)."""
    return _barrier(a)


@materialise.defjvp
def _materialise_jvp(primals, tangents):
    return materialise(primals[0]), tangents[0]


@jax.custom_vjp
def materialise_cotangent(a):
    """``a`` (an array or a tuple of arrays) itself; in reverse mode its cotangent is
    materialised (:func:`materialise`) before it flows on to ``a``'s producers: for a value
    whose cotangent sums many consumers' adjoints and is read by many producers' adjoints."""
    return a


def _materialise_cotangent_fwd(a):
    return a, None


def _materialise_cotangent_bwd(_, ct):
    return (materialise(ct),)


materialise_cotangent.defvjp(_materialise_cotangent_fwd, _materialise_cotangent_bwd)
