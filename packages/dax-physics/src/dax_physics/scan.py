"""The one checkpointed scan every DaX rollout uses (MPM, cloth and the tasks).

A rollout of ``n`` steps differentiated in reverse mode keeps every step's intermediates
unless it is checkpointed. :func:`checkpointed_scan` runs the steps in *segments* of
``segment`` steps, each segment wrapped in ``jax.checkpoint``: the backward pass stores
only the carry at each segment boundary and recomputes one segment at a time, so memory
grows with the number of segments (plus one segment's intermediates), not with ``n``.
Forward values are those of a plain ``lax.scan`` of the same body.

**The segment rule** (the only one in DaX): ``k = ceil(n / segment)`` checkpointed
segments of equal length ``L = ceil(n / k)`` (so ``L <= segment``). When ``L`` does not
divide ``n``, the ``k L - n`` surplus steps (fewer than ``k``, so less than ``1 / L`` of
the work) come last; they are computed and discarded (a select keeps the carry, and their
outputs are dropped), which keeps the body one inlined computation: a ``lax.cond`` would
compile it as a separate one and change the float results of the real steps. Equal
segments compile one segment body, not two. With ``short_last=True`` the same ``k``
segments are run without surplus steps instead: ``k - 1`` of ``L`` steps, then the last
with the ``n - (k - 1) L`` left, as a second scan of the body (compiled twice, no select
on every step's carry). ``segment=None`` (or ``segment >= n``) is a plain scan with no
checkpointing.
Examples: 200 steps, segment 20: 10 x 20; 36 steps, segment 10: 4 x 9; 50 steps, segment
20: 3 x 17 with one skipped step.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def _scan_length(xs, length) -> int:
    """The number of steps: ``length``, checked against the leading axis of ``xs``."""
    leaves = jax.tree_util.tree_leaves(xs)
    if length is not None:
        # lax.scan runs a negative length as zero steps: refuse it instead of doing nothing
        if isinstance(length, bool) or int(length) != length or length < 0:
            raise ValueError(f"length must be an int >= 0, got {length!r}")
        n = int(length)
        if any(leaf.shape[0] != n for leaf in leaves):
            raise ValueError(f"length {n} does not match the leading axis of xs "
                             f"{[leaf.shape[0] for leaf in leaves]}")
        return n
    if not leaves:
        raise ValueError("checkpointed_scan needs xs or length")
    return int(leaves[0].shape[0])


def segment_layout(n: int, segment: int | None) -> tuple[int, int]:
    """``(k, L)``: the number of checkpointed segments and their length for ``n`` steps
    (``(1, n)`` without checkpointing); see the module docstring."""
    if segment is None or segment >= n:
        return 1, n
    if not (isinstance(segment, int) and not isinstance(segment, bool) and segment > 0):
        raise ValueError(f"segment must be a positive int or None, got {segment!r}")
    k = -(-n // segment)
    return k, -(-n // k)


def checkpointed_scan(body, carry, xs=None, *, length: int | None = None,
                      segment: int | None = None, unroll: int = 1, short_last: bool = False):
    """``jax.lax.scan(body, carry, xs, length)`` in checkpointed segments.

    body: ``body(carry, x) -> (carry, y)``, as for ``lax.scan``; it must be defined (finite)
        on the final carry, which the surplus steps feed it.
    segment: the most steps per checkpointed segment (see the module docstring for how
        the steps are split); ``None`` for a plain scan.
    unroll: passed to the inner ``lax.scan``.
    short_last: where ``L`` does not divide ``n``, run the last of the ``k`` segments with
        its ``n - (k - 1) L`` steps only, as a scan of its own, instead of computing and
        discarding surplus steps: no select on every step's carry, at the price of a
        second compiled copy of ``body`` (longer compiles; the same checkpoints). For a
        body whose carry is large next to its work (the cloth's neighbour list).
    Returns ``(carry, ys)`` with ``ys`` stacked over all ``n`` steps, as ``lax.scan`` does.
    """
    n = _scan_length(xs, length)
    k, seg_len = segment_layout(n, segment)
    if k == 1:
        return jax.lax.scan(body, carry, xs, length=n, unroll=unroll)
    total = k * seg_len
    if total > n and short_last:
        head_n = (k - 1) * seg_len

        @jax.checkpoint
        def run_head(c, seg_xs):
            return jax.lax.scan(body, c, seg_xs, length=seg_len, unroll=unroll)

        @jax.checkpoint
        def run_last(c, last_xs):
            return jax.lax.scan(body, c, last_xs, length=n - head_n, unroll=unroll)

        head = jax.tree_util.tree_map(
            lambda a: a[:head_n].reshape(k - 1, seg_len, *a.shape[1:]), xs)
        carry, ys = jax.lax.scan(run_head, carry, head, length=k - 1)
        carry, ys_last = run_last(carry, jax.tree_util.tree_map(lambda a: a[head_n:], xs))
        ys = jax.tree_util.tree_map(
            lambda a, b: jnp.concatenate([a.reshape(head_n, *a.shape[2:]), b]), ys, ys_last)
        return carry, ys
    step = body
    if total > n:  # the surplus steps at the end leave the carry as it is
        def step(c, inp):
            i, x = inp
            new, y = body(c, x)
            keep = i < n
            return jax.tree_util.tree_map(lambda a, b: jnp.where(keep, a, b), new, c), y

        def pad(a):
            return jnp.concatenate([a, jnp.broadcast_to(a[-1:], (total - n, *a.shape[1:]))])

        xs = (jnp.arange(total, dtype=jnp.int32), jax.tree_util.tree_map(pad, xs))

    @jax.checkpoint
    def run_segment(c, seg_xs):
        return jax.lax.scan(step, c, seg_xs, length=seg_len, unroll=unroll)

    seg_xs = jax.tree_util.tree_map(lambda a: a.reshape(k, seg_len, *a.shape[1:]), xs)
    carry, ys = jax.lax.scan(run_segment, carry, seg_xs, length=k)
    ys = jax.tree_util.tree_map(lambda a: a.reshape(total, *a.shape[2:])[:n], ys)
    return carry, ys
