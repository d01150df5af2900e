"""Cloth self-collision: vertex pairs closer than the thickness h repel.

The force of a pair (:func:`_pair_force`) is the same whichever way the pairs are found
(``ClothConfig.self_search``):

* ``"list"`` (default): a Verlet neighbour list (:class:`NeighbourList`). A build finds
  every pair closer than the cutoff ``r = h + skin`` whose rest distance exceeds
  ``self_exclude * h`` (mesh neighbours never repel) and stores it once, ``i < j``, in a
  static number of pair slots, with the number of pairs it could not store. The list is
  rebuilt only when some vertex has moved more than ``skin / 2`` since the last build,
  relative to a displacement c common to all (the middle of the displacements' range,
  per component; :func:`update_neighbours`): until then a pair closer than h was closer
  than ``h + skin`` at the build (its separation changed by ``|(d_i - c) - (d_j - c)| <=
  skin``), so the list holds every pair all-pairs finds within h while its overflow is
  0; a cloth carried as a whole keeps its list. A substep's force costs the stored
  pairs' slots (in tiers of slots, :func:`_tier_sizes`), not V^2.
  The build is a cell search: cells of side r, so a pair within r lies in neighbouring
  cells; each vertex examines the 27 cells around its own, ``self_candidates`` vertices
  per cell at most. Where that is more work than testing all pairs (:func:`uses_cells`)
  the build tests all pairs instead; the pairs found are the same.
* ``"all"``: every vertex pair as dense (V, V) arithmetic, no list: V^2 pair tests per
  substep.

Forces are differentiable in the positions and velocities with the list held constant:
no gradient flows through a build (it only selects pairs, and a pair beyond h exerts no
force), and the listed pairs' reverse pass is written out, a gather and a scatter that
mirror the forward's. Under ``jax.vmap`` a batch rebuilds when any of its members must, and
builds only those members (gathered into the smallest of a few member counts; each member
takes a new list only where it needed one, so batched and single runs hold the same
lists), and the force's slot tier is the batch's largest: ``lax.cond`` and
``lax.switch`` then stay branches instead of becoming selects that run every branch.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
from jax.custom_batching import custom_vmap

from .._fusion import materialise
from .._pytree import pytree_dataclass

_TINY = 1e-20
#: The pair searches of ``ClothConfig.self_search``.
SELF_SEARCHES = ("list", "all")
#: The 27 cell offsets around (and including) a vertex's own cell.
_CELL_OFFSETS = np.array([(a, b, c) for a in (-1, 0, 1) for b in (-1, 0, 1)
                          for c in (-1, 0, 1)], np.int32)


@pytree_dataclass
class NeighbourList:
    """The pairs the self-collision force looks at (a Verlet list; see the module
    docstring), part of :class:`dax_physics.cloth.ClothState`.

    pairs (2, P) int32: vertex pairs ``i < j`` closer than ``h + skin`` at the last build
        whose rest distance exceeds ``self_exclude * h``, sorted by ``i``; the ``P - count``
        unused slots hold ``(0, 0)``. P is :func:`pair_capacity`.
    count () int32: pairs stored.
    x_ref (V, 3) [m]: the positions at the last build (no gradient).
    overflow () int32: the most that any build of this list could not see, summed over
        its two causes: pairs found beyond the P slots, and candidates of a crowded cell
        beyond the ``self_candidates`` examined (a bound on the pairs missed there). 0
        means every build was exact; a positive count asks for a larger
        ``self_capacity`` or ``self_candidates``.
    builds () int32: builds since the list was made (1 for a new list).
    """

    pairs: jnp.ndarray
    count: jnp.ndarray
    x_ref: jnp.ndarray
    overflow: jnp.ndarray
    builds: jnp.ndarray


def skin(cfg) -> float:
    """The list's skin [m]: ``cfg.self_skin``, or ``h / 2`` when that is ``None``."""
    return 0.5 * cfg.thickness if cfg.self_skin is None else float(cfg.self_skin)


def pair_capacity(cfg, n_vertices: int) -> int:
    """Pair slots P of a neighbour list of ``n_vertices`` vertices:
    ``self_capacity * n_vertices`` rounded up to a multiple of 8 (at least 8)."""
    return max(8, 8 * math.ceil(cfg.self_capacity * n_vertices / 8))


#: Tiers of at least this many slots are spaced by sqrt(2), smaller ones by 2: where a
#: slot tier is large its unused slots cost the most, and each tier is one more branch to
#: compile (twice, with its gradient).
_FINE_TIERS = 256


def _tier_sizes(capacity: int) -> tuple:
    """Slot counts the force is evaluated over: the smallest tier holding all stored pairs
    is used (multiples of 8: P, P / 2, P / 4, ... down to 8, and between them P / sqrt(2),
    P / (2 sqrt(2)), ... while those are at least ``_FINE_TIERS``)."""
    sizes, k = set(), 1
    while capacity / 2 ** (k / 2) >= 8:
        size = 8 * math.ceil(capacity / (8 * 2 ** (k / 2)))
        if k % 2 == 0 or size >= _FINE_TIERS:
            sizes.add(size)
        k += 1
    return tuple(sorted(s for s in sizes if s < capacity)) + (capacity,)


# ----------------------------------------------------------------------------- batching

@custom_vmap
def _batch_any(flag):
    """``flag`` (bool scalar); under ``vmap``, whether any member's flag is set, unbatched."""
    return flag


@_batch_any.def_vmap
def _batch_any_rule(axis_size, in_batched, flag):
    del axis_size, in_batched
    return _batch_any(jnp.any(flag, axis=0)), False


@custom_vmap
def _batch_max(value):
    """``value`` (int scalar); under ``vmap``, the largest member's value, unbatched."""
    return value


@_batch_max.def_vmap
def _batch_max_rule(axis_size, in_batched, value):
    del axis_size, in_batched
    return _batch_max(jnp.max(value, axis=0)), False


# ----------------------------------------------------------------------------- build

def _cell_keys(cells, n_buckets: int):
    """Bucket of each integer cell (..., 3): a spatial hash modulo ``n_buckets`` (a power
    of two)."""
    h = (cells[..., 0] * jnp.int32(73856093)) ^ (cells[..., 1] * jnp.int32(19349663)) ^ (
        cells[..., 2] * jnp.int32(83492791))
    return h & jnp.int32(n_buckets - 1)


def _keep(cfg, xi, xj, ri, rj, r: float):
    """Which candidate pairs belong in the list: closer than ``r`` now (positions ``xi``,
    ``xj``: three component arrays each, broadcasting), farther than ``self_exclude * h``
    at rest (``ri``, ``rj``)."""
    d2 = sum((xi[c] - xj[c]) ** 2 for c in range(3))
    r2 = sum((ri[c] - rj[c]) ** 2 for c in range(3))
    return (d2 < r * r) & (r2 > (cfg.self_exclude * cfg.thickness) ** 2)


def _pack(bits):
    """32 boolean arrays of one shape as one uint32 array (bit b from ``bits[b]``; missing
    trailing ones are 0): the candidates of a build are tested 32 to a word, so that no
    boolean array of all of them is written."""
    word = jnp.zeros(bits[0].shape, jnp.uint32)
    for b, bit in enumerate(bits):
        word = word | (bit.astype(jnp.uint32) << b)
    return word


def _words_all(cfg, xt, rt, r: float):
    """Every pair ``i < j`` as a candidate: ``(words (Wj, V) uint32, decode, missed)``;
    bit b of word ``(w, i)`` is the pair ``(i, b Wj + w)`` (columns padded to ``32 Wj``;
    i runs along the words' minor axis, which XLA vectorises)."""
    V = xt.shape[1]
    Wj = -(-V // 32)
    pad = ((0, 0), (0, 32 * Wj - V))
    xp, rp = jnp.pad(xt, pad), jnp.pad(rt, pad)
    i = jnp.arange(V, dtype=jnp.int32)[None, :]
    w = jnp.arange(Wj, dtype=jnp.int32)[:, None]
    xi, ri = [a[None, :] for a in xt], [a[None, :] for a in rt]
    bits = []
    for b in range(32):
        j = b * Wj + w
        rows = slice(b * Wj, (b + 1) * Wj)
        xj, rj = [a[rows, None] for a in xp], [a[rows, None] for a in rp]
        bits.append((i < j) & (j < V) & _keep(cfg, xi, xj, ri, rj, r))

    def decode(word, bit):
        return word % V, bit * Wj + word // V

    return _pack(bits), decode, jnp.zeros((), jnp.int32)


def _words_cells(cfg, xt, rt, r: float):
    """The cell search: ``(words (V, 27, K) uint32, decode, missed)``.

    Vertices are sorted by the bucket of their cell (side r); a bucket's vertices are one
    run of that order, found from its first position and size (two scatters). Vertex i
    examines the first ``self_candidates`` vertices (32 to a word, K words) of each of the
    distinct buckets of the 27 cells around its own (a pair within r lies in neighbouring
    cells); ``missed`` counts the candidates of fuller buckets it did not examine."""
    V = xt.shape[1]
    C = cfg.self_candidates
    K = -(-C // 32)
    n_buckets = 1 << max(int(2 * V - 1).bit_length(), 4)
    cells = jnp.floor(xt.T / r).astype(jnp.int32)
    key = _cell_keys(cells, n_buckets)
    order = jnp.argsort(key).astype(jnp.int32)
    first = jnp.full((n_buckets,), V, jnp.int32).at[key[order]].min(
        jnp.arange(V, dtype=jnp.int32))
    size = jnp.zeros((n_buckets,), jnp.int32).at[key].add(1)
    near = _cell_keys(cells[:, None, :] + jnp.asarray(_CELL_OFFSETS)[None], n_buckets)
    # two of the 27 cells in one bucket: examine it once
    seen = jnp.any(jnp.tril(near[:, :, None] == near[:, None, :], -1), axis=2)
    n_in = jnp.where(seen, 0, size[near])[..., None]  # (V, 27, 1)
    start = first[near][..., None]
    i = jnp.arange(V, dtype=jnp.int32)[:, None, None]
    k = jnp.arange(K, dtype=jnp.int32)[None, None, :]
    xi, ri = [a[:, None, None] for a in xt], [a[:, None, None] for a in rt]
    bits = []
    for b in range(32):
        slot = 32 * k + b
        j = order[jnp.minimum(start + slot, V - 1)]
        bits.append((slot < jnp.minimum(n_in, C)) & (i < j) & _keep(
            cfg, xi, [a[j] for a in xt], ri, [a[j] for a in rt], r))

    def decode(word, bit):
        cell = (word // K) % 27
        slot = 32 * (word % K) + bit
        vertex = word // (27 * K)
        return vertex, order[jnp.minimum(start[vertex, cell, 0] + slot, V - 1)]

    missed = jnp.sum(jnp.maximum(n_in - C, 0), dtype=jnp.int32)
    return _pack(bits), decode, missed


def _select_bits(words, capacity: int):
    """The first ``capacity`` set bits of ``words`` (W,) uint32, in word order, then bit
    order: ``(word (P,), bit (P,), valid (P,), n)`` with n the number of set bits.

    Slot s lies in the word where the running bit count first exceeds s: marking each
    word's end (a scatter-add of the running counts) and summing the marks over the slots
    finds it for all slots at once; within the word, a binary search on popcounts finds
    the bit. The result is materialised (:func:`dax_physics._fusion.materialise`): its
    readers would otherwise each redo the search."""
    cnt = jax.lax.population_count(words).astype(jnp.int32)
    ends = jnp.cumsum(cnt)
    marks = jnp.zeros((capacity,), jnp.int32).at[ends].add(1, mode="drop")
    word = jnp.minimum(jnp.cumsum(marks), words.shape[0] - 1)
    s = jnp.arange(capacity, dtype=jnp.int32)
    bits = words[word]
    rank = (s - ends[word] + cnt[word]).astype(jnp.uint32)
    bit = jnp.zeros((capacity,), jnp.uint32)  # the largest b with rank set bits below b
    for step in (16, 8, 4, 2, 1):
        mid = bit + step
        below = jax.lax.population_count(bits & ((jnp.uint32(1) << mid) - 1))
        bit = jnp.where(below <= rank, mid, bit)
    n = ends[-1]
    word, bit = materialise((word, bit.astype(jnp.int32)))
    return word, bit, s < n, n


#: A cell-search candidate costs about this many all-pairs tests (its gathers against
#: the all-pairs test's broadcast reads, on XLA:CPU).
_CANDIDATE_COST = 10


def uses_cells(cfg, n_vertices: int) -> bool:
    """Whether a build on ``n_vertices`` vertices is the cell search: when its ``27 *
    self_candidates`` candidates per vertex cost less than testing all V pairs."""
    return n_vertices > _CANDIDATE_COST * 27 * cfg.self_candidates


def _build(cfg, cloth, x, cells: bool):
    """``(pairs (2, P), count, overflow)`` of a list built at ``x`` (no gradient)."""
    xt = jax.lax.stop_gradient(x).T
    rt = jax.lax.stop_gradient(cloth.rest_pos).T
    r = cfg.thickness + skin(cfg)
    capacity = pair_capacity(cfg, xt.shape[1])
    words, decode, missed = (_words_cells if cells else _words_all)(cfg, xt, rt, r)
    # in a buffer of its own: fused into the running count's padded input, the 32 tests
    # per word are not vectorised
    word, bit, valid, n = _select_bits(materialise(words).reshape(-1), capacity)
    i, j = decode(word, bit)
    pairs = jnp.stack([jnp.where(valid, i, 0), jnp.where(valid, j, 0)]).astype(jnp.int32)
    return pairs, jnp.minimum(n, capacity), jnp.maximum(n - capacity, 0) + missed


def neighbour_list(cfg, cloth, x) -> NeighbourList:
    """A new :class:`NeighbourList` of ``cloth`` at positions ``x`` (V, 3) [m]."""
    x = jax.lax.stop_gradient(x)
    with jax.named_scope("self_collision/build"):
        pairs, count, overflow = _build(cfg, cloth, x, uses_cells(cfg, x.shape[0]))
    return NeighbourList(pairs=pairs, count=count, x_ref=x, overflow=overflow,
                         builds=jnp.ones((), jnp.int32))


def update_neighbours(cfg, cloth, nbrs: NeighbourList, x) -> NeighbourList:
    """``nbrs`` if no vertex has moved more than ``skin / 2`` from ``nbrs.x_ref`` relative
    to the middle of all vertices' displacements (per component, the midpoint of their
    smallest and largest), else a new list at ``x`` (its ``overflow`` the larger of the
    old and the new, ``builds`` one more). Under ``vmap`` the batch rebuilds if any member
    must (a ``lax.cond``), and builds only the members that must (:func:`_rebuild_moved`)."""
    x = jax.lax.stop_gradient(x)
    half = 0.5 * skin(cfg)
    dt = x.T - nbrs.x_ref.T  # (3, V): displacements since the build
    hi = jnp.max(jnp.concatenate([dt, -dt]), axis=1, keepdims=True)
    d = dt - 0.5 * (hi[:3] - hi[3:])  # less the middle of their range
    moved = jnp.any(jnp.sum(d * d, axis=0) > half * half)

    def rebuild(old):
        return _rebuild_moved(cfg, moved, cloth, x, old)

    with jax.named_scope("self_collision/update"):
        return jax.lax.cond(_batch_any(moved), rebuild, lambda old: old, nbrs)


def _with_record(new: NeighbourList, old: NeighbourList, built) -> NeighbourList:
    """``new`` with ``overflow`` the larger of ``old``'s and its own, and ``builds`` that of
    ``old`` plus ``built`` (1 or 0)."""
    return new.replace(overflow=jnp.maximum(old.overflow, new.overflow),
                       builds=old.builds + built)


#: Batches smaller than this build every member on a rebuild (:func:`_member_tiers`).
_GATHER_FROM = 16


def _member_tiers(batch: int) -> tuple:
    """Numbers of members a batched rebuild builds: the smallest of these holding all the
    members that moved. A quarter, a half and all of a batch of at least
    :data:`_GATHER_FROM`; a smaller batch, all of it (each tier is one more build to
    compile, twice in a checkpointed gradient, and a small batch's build costs little more
    than one member's)."""
    if batch < _GATHER_FROM:
        return (batch,)
    return (batch // 4, batch // 2, batch)


def _rebuild_moved(cfg, moved, cloth, x, old: NeighbourList) -> NeighbourList:
    """``old``, or where ``moved`` a new list at ``x`` (its record kept,
    :func:`_with_record`).

    Under ``vmap`` only the members that moved are built: the smallest member tier
    (:func:`_member_tiers`) holding the n that moved is chosen (a ``lax.switch``), their
    positions are gathered into it, built, and their lists scattered back; the batch's own
    size builds every member and keeps the lists of those that moved, as before (the only
    tier of a small batch). A batch whose members rebuild at different substeps (64
    members of Fold-Cloth-1 rebuild at about 370 substeps of 700, 14 members at a time) no
    longer builds all of them each time one must. Each member's list is the one its own
    build gives, as without ``vmap``: the lists, and so the forces, are unchanged to the
    bit."""
    @custom_vmap
    def select(moved, cloth, x, old):
        new = _with_record(neighbour_list(cfg, cloth, x), old, 1)
        return jax.tree.map(lambda a, b: jnp.where(moved, a, b), new, old)

    @select.def_vmap
    def select_rule(axis_size, in_batched, moved, cloth, x, old):
        b_moved, b_cloth, b_x, b_old = in_batched
        moved = moved if b_moved else jnp.broadcast_to(moved, (axis_size,))
        x = x if b_x else jnp.broadcast_to(x, (axis_size,) + x.shape)
        old = jax.tree.map(lambda a, b: a if b else jnp.broadcast_to(a, (axis_size,) + a.shape),
                           old, b_old)
        cloth_axes = jax.tree.map(lambda b: 0 if b else None, b_cloth)
        build = jax.vmap(functools.partial(neighbour_list, cfg), in_axes=(cloth_axes, 0))
        sizes = _member_tiers(axis_size)
        record = moved.astype(old.builds.dtype)

        def everyone(order, cloth, x, old):
            del order
            new = build(cloth, x)
            return jax.tree.map(lambda a, b: jnp.where(
                moved.reshape(moved.shape + (1,) * (a.ndim - 1)), a, b), new, old)

        out_batched = jax.tree.map(lambda _: True, old)
        if len(sizes) == 1:
            return _with_record(everyone(None, cloth, x, old), old, record), out_batched
        n = jnp.sum(moved, dtype=jnp.int32)
        # the members that moved first, in member order (a stable sort of the flags); past
        # the n that moved, an index no member has (its writes are dropped)
        order = jnp.argsort(~moved, stable=True).astype(jnp.int32)
        order = jnp.where(jnp.arange(axis_size) < n, order, axis_size)

        def gathered(size):
            def run(order, cloth, x, old):
                idx = order[:size]
                safe = jnp.minimum(idx, axis_size - 1)
                new = build(jax.tree.map(lambda a, b: a[safe] if b else a, cloth, b_cloth),
                            x[safe])
                return jax.tree.map(lambda a, p: a.at[idx].set(p, mode="drop"), old, new)
            return run

        tier = jnp.sum(n > jnp.asarray(sizes[:-1], jnp.int32), dtype=jnp.int32)
        lists = jax.lax.switch(tier, [gathered(k) for k in sizes[:-1]] + [everyone],
                               order, cloth, x, old)
        return _with_record(lists, old, record), out_batched

    return select(moved, cloth, x, old)


# ----------------------------------------------------------------------------- forces

def _pair_force(cfg, d, dv, active):
    """The force [N] on the first vertex of each pair, as three component arrays: ``d``
    and ``dv`` (three arrays of any one shape) are its position and velocity relative to
    the second; ``active`` marks the pairs that may touch (closer than h is checked
    here). Repulsion ``self_stiffness (h - |d|)`` along d, ``self_damping`` on the
    approaching normal speed, ``self_friction`` on the relative velocity."""
    h = cfg.thickness
    dist = jnp.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2] + _TINY)
    active = active & (dist < h)
    inv = 1.0 / dist
    s = jnp.where(active, cfg.self_stiffness * (h - dist), 0.0) * inv
    if cfg.self_damping > 0 or cfg.self_friction > 0:
        vn = (dv[0] * d[0] + dv[1] * d[1] + dv[2] * d[2]) * inv
        s = s - jnp.where(active, (cfg.self_damping * jnp.minimum(vn, 0.0)
                                   - cfg.self_friction * vn) * inv, 0.0)
        if cfg.self_friction > 0:  # tangential part: -self_friction * (dv - vn n)
            fr = jnp.where(active, cfg.self_friction, 0.0)
            return [s * d[c] - fr * dv[c] for c in range(3)]
    return [s * d[c] for c in range(3)]


def _all_pairs_forces(cfg, cloth, xt, vt):
    """Forces (3, V) from every vertex pair (dense (V, V) arrays)."""
    V = xt.shape[1]
    rt = cloth.rest_pos.T
    d = [xt[c][:, None] - xt[c][None, :] for c in range(3)]  # from neighbour to me
    dv = [vt[c][:, None] - vt[c][None, :] for c in range(3)]
    r2 = sum((rt[c][:, None] - rt[c][None, :]) ** 2 for c in range(3))
    active = ~jnp.eye(V, dtype=bool) & (r2 > (cfg.self_exclude * cfg.thickness) ** 2)
    return jnp.stack([jnp.sum(f, axis=1) for f in _pair_force(cfg, d, dv, active)])


def _pair_rows(pairs, xt, vt):
    """``(i, j, g)``: the pairs' ends (n,) and ``g`` (n, 8), end i's position and velocity
    less end j's, read as one row of a (V, 8) array per end (x, v, padding)."""
    i, j = pairs[0], pairs[1]
    xv = jnp.concatenate([xt, vt, jnp.zeros_like(xt[:2])]).T  # (V, 8): x, v, padding
    return i, j, xv[i] - xv[j]


def _row_forces(cfg, g, i, j):
    """The forces of the pairs ``(i, j)`` as (n, 4) rows (x, y, z, 0) from their row
    differences ``g`` (n, 8); ``(0, 0)`` slots exert none."""
    f = _pair_force(cfg, [g[:, c] for c in range(3)], [g[:, 3 + c] for c in range(3)],
                    i != j)
    return jnp.stack(f + [jnp.zeros_like(f[0])], axis=1)


def _listed_pairs_forces(cfg, pairs, xt, vt):
    """Forces (3, V) of the pairs ``(2, n)``: each pair's force is computed once and added
    to i and subtracted from j (one scatter of rows); ``(0, 0)`` slots exert none. Both
    ends read their position and velocity as one row of a (V, 8) array."""
    V = xt.shape[1]
    i, j, g = _pair_rows(pairs, xt, vt)
    f = _row_forces(cfg, g, i, j)  # (n, 4)
    out = jnp.zeros((V, 4), xt.dtype).at[jnp.concatenate([i, j])].add(
        jnp.concatenate([f, -f]))
    return out[:, :3].T


def _listed_pairs_vjp(cfg, pairs, xt, vt, ct):
    """The cotangents ``(x̄, v̄)`` (3, V) of :func:`_listed_pairs_forces` for the forces'
    cotangent ``ct`` (3, V): a pair's force cotangent is ``ct_i - ct_j`` (one gather of
    (V, 4) rows), pulled back through the pair's contact law (elementwise), and its row
    cotangent is added to i and subtracted from j (one scatter of (V, 8) rows), the mirror
    of the forward pass."""
    V = xt.shape[1]
    i, j, g = _pair_rows(pairs, xt, vt)
    rows = jnp.concatenate([ct, jnp.zeros_like(ct[:1])]).T  # (V, 4)
    f_bar = rows[i] - rows[j]
    cols = [g[:, c] for c in range(6)]  # d, dv by component
    _, pull = jax.vjp(lambda *cols: _pair_force(cfg, cols[:3], cols[3:], i != j), *cols)
    # the six column cotangents stacked once, into a buffer of their own: as the
    # cotangent of g's slices (pads summed) or fused into the scatter's concatenation,
    # XLA:CPU recomputed the contact law's reverse pass for every column it wrote
    bars = pull([f_bar[:, c] for c in range(3)])
    g_bar = materialise(jnp.stack([*bars, *[jnp.zeros_like(bars[0])] * 2], axis=1))  # (n, 8)
    out = jnp.zeros((V, 8), xt.dtype).at[jnp.concatenate([i, j])].add(
        jnp.concatenate([g_bar, -g_bar]))
    return out[:, :3].T, out[:, 3:6].T


def _tier(nbrs_count, sizes):
    """Index into ``[none] + sizes`` of the smallest slot tier holding ``nbrs_count``
    pairs (0: none stored), the batch's largest under ``vmap``."""
    # one comparison against a constant array: a stack of scalar comparisons is a loop
    # per tier on XLA:CPU, run every substep
    tier = jnp.sum(nbrs_count > jnp.asarray(sizes[:-1] + (0,), jnp.int32), dtype=jnp.int32)
    return _batch_max(tier)


def _list_forces(cfg, nbrs: NeighbourList, xt, vt):
    """Forces (3, V) of the pairs of ``nbrs``, over the smallest slot tier that holds them
    (none when the list is empty); differentiable in ``xt`` and ``vt`` with the list held
    (:func:`_tiered_forces`)."""
    return _tiered_forces(cfg, nbrs.pairs, nbrs.count, xt, vt)


@functools.partial(jax.custom_vjp, nondiff_argnums=(0,))
def _tiered_forces(cfg, pairs, count, xt, vt):
    """:func:`_listed_pairs_forces` over the first slots of ``pairs`` (2, P) in the
    smallest tier holding ``count`` pairs (a ``lax.switch``).

    Its reverse pass is written out (:func:`_listed_pairs_vjp`, in the same tier): the
    autodiff of the switch keeps every tier's residuals and runs a linearised copy of the
    forward branch, which made the force's reverse pass the larger part of what
    self-collision adds to a cloth step's action gradient. Forward values are those of
    the plain switch."""
    sizes = _tier_sizes(pairs.shape[1])
    branches = [lambda p, xt, vt: jnp.zeros_like(xt)] + [
        lambda p, xt, vt, n=n: _listed_pairs_forces(cfg, p[:, :n], xt, vt) for n in sizes]
    return jax.lax.switch(_tier(count, sizes), branches, pairs, xt, vt)


def _tiered_forces_fwd(cfg, pairs, count, xt, vt):
    return _tiered_forces(cfg, pairs, count, xt, vt), (pairs, count, xt, vt)


def _tiered_forces_bwd(cfg, res, ct):
    pairs, count, xt, vt = res
    sizes = _tier_sizes(pairs.shape[1])
    branches = [lambda p, xt, vt, ct: (jnp.zeros_like(xt), jnp.zeros_like(vt))] + [
        lambda p, xt, vt, ct, n=n: _listed_pairs_vjp(cfg, p[:, :n], xt, vt, ct)
        for n in sizes]
    x_bar, v_bar = jax.lax.switch(_tier(count, sizes), branches, pairs, xt, vt, ct)
    return None, None, x_bar, v_bar


_tiered_forces.defvjp(_tiered_forces_fwd, _tiered_forces_bwd)


def forces_cm(cfg, cloth, xt, vt, nbrs: NeighbourList | None):
    """Self-collision forces (3, V) [N] on component-major positions and velocities
    (3, V): every pair with ``self_search="all"``, else the pairs of ``nbrs`` (a list
    built at ``xt`` when ``None``)."""
    with jax.named_scope("self_collision/forces"):
        if cfg.self_search == "all":
            return _all_pairs_forces(cfg, cloth, xt, vt)
        if nbrs is None:
            nbrs = neighbour_list(cfg, cloth, xt.T)
        return _list_forces(cfg, nbrs, xt, vt)
