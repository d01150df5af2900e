"""Cloth self-collision: the neighbour list finds the pairs all-pairs finds, counts what it
cannot hold, is rebuilt when (and only when) a vertex has moved half the skin, batches
like single runs, and gives the forces and gradients of the contact law."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import dax_physics.cloth as c
from dax_physics.cloth import selfcollision as sc

H = 0.03


def _layer_stack(h=H, layers=8):
    """``layers`` layers of a 4x4 grid of spacing h / 3, h * 7 / 30 apart: 16 * layers
    vertices within about one h of each other (jittered by 1e-3 h, so that no distance
    ties with a cutoff)."""
    g = np.stack(np.meshgrid(np.arange(4), np.arange(4), indexing="ij"), -1).reshape(-1, 2)
    x = np.concatenate([np.c_[0.001 + h / 3 * g, np.full(16, 0.001 + 0.007 / 0.03 * h * k)]
                        for k in range(layers)])
    return x + 1e-3 * h * np.random.default_rng(7).uniform(-1, 1, x.shape)


def _stack_cloth(h=H, layers=8):
    """A cloth of 16 * layers vertices whose rest mesh puts every pair of the stack farther
    apart than ``self_exclude * h``, so that every close pair of the stack may touch."""
    n = 16 * layers
    return c.square_cloth(n // 8, 8, size=(n // 8 * 2.5 * h, 8 * 2.5 * h))


def _pairs_within(x, rest, r, h, exclude=2.0):
    """float64 brute force: the pairs ``i < j`` closer than r whose rest distance exceeds
    ``exclude * h``."""
    x, rest = np.asarray(x, np.float64), np.asarray(rest, np.float64)
    d = np.linalg.norm(x[:, None] - x[None], axis=-1)
    far = np.linalg.norm(rest[:, None] - rest[None], axis=-1) > exclude * h
    return {(int(i), int(j)) for i, j in zip(*np.nonzero(np.triu((d < r) & far, 1)),
                                             strict=True)}


def _listed(nbrs):
    p = np.asarray(nbrs.pairs)[:, :int(nbrs.count)]
    return set(zip(p[0].tolist(), p[1].tolist(), strict=True))


def _close(nbrs, x, h):
    """The listed pairs closer than h at ``x``."""
    x = np.asarray(x, np.float64)
    return {(i, j) for i, j in _listed(nbrs) if np.linalg.norm(x[i] - x[j]) < h}


@pytest.mark.parametrize("cells", [False, True])
def test_list_holds_every_pair_within_the_cutoff(cells):
    """On a cloud and on an 8-layer stack the build (all pairs, and the cell search) lists
    exactly the brute force's pairs within h + skin, with no overflow."""
    rng = np.random.default_rng(1)
    cloud = rng.uniform(0.0, 0.15, size=(128, 3))
    cl = _stack_cloth()
    cfg = c.ClothConfig(thickness=H, self_capacity=64.0, self_candidates=128)
    r = H + sc.skin(cfg)
    build = jax.jit(sc._build, static_argnums=(0, 3))
    for x in (cloud, _layer_stack()):
        pairs, count, overflow = build(cfg, cl, jnp.asarray(x, jnp.float32), cells)
        nbrs = sc.NeighbourList(pairs, count, jnp.asarray(x), overflow, jnp.int32(1))
        want = _pairs_within(x, cl.rest_pos, r, H)
        assert len(want) > 20, f"expected a scene with contacts, got {len(want)} pairs"
        assert int(overflow) == 0, f"expected no overflow, got {int(overflow)}"
        got = _listed(nbrs)
        assert got == want, (f"expected the {len(want)} brute-force pairs, missing "
                             f"{len(want - got)}, extra {len(got - want)}")


def test_overflow_is_counted_and_is_what_loses_pairs():
    """The 8-layer stack (nearly every one of its 8128 pairs within h + skin) has more
    close pairs than 1 slot per vertex holds, and its cells hold more vertices than 8
    candidates: both are counted, and only then do pairs go missing."""
    x = jnp.asarray(_layer_stack(), jnp.float32)
    cl = _stack_cloth()
    want = _pairs_within(x, cl.rest_pos, H + 0.5 * H, H)
    for kw, cells, lost in ((dict(self_capacity=1.0), False, True),
                            (dict(self_capacity=64.0, self_candidates=8), True, True),
                            (dict(self_capacity=64.0), False, False)):
        cfg = c.ClothConfig(thickness=H, **kw)
        pairs, count, overflow = jax.jit(sc._build, static_argnums=(0, 3))(cfg, cl, x, cells)
        missing = len(want - _listed(sc.NeighbourList(pairs, count, x, overflow, 1)))
        assert (int(overflow) > 0) == lost and (missing > 0) == lost, (
            f"{kw}, cells={cells}: overflow {int(overflow)}, {missing} pairs missing")
    cfg = c.ClothConfig(thickness=H, self_capacity=1.0)
    st = c.ClothState.create(cl, x=x)
    assert int(c.self_collision_overflow(cfg, cl, st)) > 0, "expected the overflow reported"
    assert int(c.self_collision_overflow(dataclasses.replace(cfg, self_search="all"), cl,
                                         st)) == 0, "expected no overflow with all pairs"


def _brute_force_self_forces(x, v, rest, h, k, damping, friction, exclude):
    """float64 reference of the documented contact law over every vertex pair."""
    f = np.zeros_like(x)
    for i in range(len(x)):
        for j in range(len(x)):
            dvec = x[i] - x[j]
            d = np.linalg.norm(dvec)
            if i == j or d >= h or np.linalg.norm(rest[i] - rest[j]) <= exclude * h:
                continue
            n = dvec / d
            dv = v[i] - v[j]
            vn = dv @ n
            f[i] += k * (h - d) * n - damping * min(vn, 0.0) * n - friction * (dv - vn * n)
    return f


def test_list_and_all_pairs_give_the_contact_law():
    """On the 8-layer stack both searches give the float64 brute-force forces of the
    contact law, damping and friction included."""
    k, damping, friction = 0.5, 1e-3, 2e-3
    rng = np.random.default_rng(3)
    x = _layer_stack()
    v = rng.normal(0.0, 0.1, x.shape)
    cl = _stack_cloth()
    want = _brute_force_self_forces(x, v, np.asarray(cl.rest_pos, np.float64), H, k, damping,
                                    friction, 2.0)
    assert np.max(np.abs(want)) > 0, "the stack should be in contact"
    for search in ("list", "all"):
        cfg = c.ClothConfig(thickness=H, self_stiffness=k, self_damping=damping,
                            self_friction=friction, self_search=search, self_capacity=64.0)
        got = np.asarray(jax.jit(c.self_collision_forces, static_argnums=0)(
            cfg, cl, jnp.asarray(x, jnp.float32), jnp.asarray(v, jnp.float32)))
        err = np.max(np.abs(got - want)) / np.max(np.abs(want))
        assert err < 1e-5, f"{search}: expected the brute-force forces, rel. error {err}"



def test_force_tier_holds_every_stored_pair():
    """Whatever the stored count, the force's slot tier holds all stored pairs: at each tier
    size and one past it, the listed force equals the force of exactly the stored pairs.
    The tiers are multiples of 8, at most 2 apart, and end at the capacity."""
    P, V = 1024, 64
    sizes = sc._tier_sizes(P)
    assert list(sizes) == sorted(set(sizes)) and sizes[-1] == P
    assert all(s % 8 == 0 for s in sizes)
    assert all(b <= 2 * a for a, b in zip(sizes[:-1], sizes[1:], strict=True))
    rng = np.random.default_rng(5)
    xt = jnp.asarray(rng.uniform(0.0, 0.5 * H, (3, V)), jnp.float32)  # all in contact
    vt = jnp.asarray(rng.normal(0.0, 0.1, (3, V)), jnp.float32)
    i, j = np.triu_indices(V, 1)
    pairs = np.stack([i, j])[:, :P].astype(np.int32)
    cfg = c.ClothConfig(thickness=H, self_stiffness=0.5, self_damping=1e-3)
    listed = jax.jit(lambda n, p: sc._list_forces(cfg, sc.NeighbourList(
        pairs=p, count=n, x_ref=xt.T, overflow=jnp.zeros((), jnp.int32),
        builds=jnp.ones((), jnp.int32)), xt, vt))
    every_slot = jax.jit(lambda p: sc._listed_pairs_forces(cfg, p, xt, vt))
    for n in sorted({1, *sizes, *(s + 1 for s in sizes[:-1])}):
        stored = jnp.asarray(np.where(np.arange(P) < n, pairs, 0).astype(np.int32))
        want = np.asarray(every_slot(stored))  # the (0, 0) slots exert no force
        got = np.asarray(listed(jnp.int32(n), stored))
        assert np.max(np.abs(want)) > 0
        np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6 * np.max(np.abs(want)),
                                   err_msg=f"count {n}")

def _folded(n=8, size=0.2):
    """A square cloth folded once along its diagonal, the folded half one h above."""
    cl = c.square_cloth(n, size=(size, size), stretch=20.0, damping=0.01)
    x = np.asarray(cl.rest_pos).copy()
    upper = x[:, 0] + x[:, 1] > size
    x[upper, :2] = size - x[upper, 1::-1]
    x[upper, 2] = size / (n - 1)
    return cl, jnp.asarray(x, jnp.float32), size / (n - 1)


def test_list_is_rebuilt_after_half_the_skin_and_stays_exact_in_between():
    """A vertex moved by 0.8 skin (0.4 skin from the middle of all displacements) keeps the
    list (pairs within h still all listed); by 1.2 skin (0.6) the list is rebuilt; the
    whole cloth carried 10 skins keeps it; along a rollout the listed pairs within h are
    those of all pairs at every checked substep."""
    cl, x, h = _folded()
    cfg = c.ClothConfig(dt=2e-4, thickness=h, self_stiffness=5.0, self_friction=1e-3)
    nbrs = sc.neighbour_list(cfg, cl, x)
    update = jax.jit(sc.update_neighbours, static_argnums=0)
    skin = sc.skin(cfg)
    for frac, rebuilt in ((0.8, False), (1.2, True)):
        moved = x.at[5].add(jnp.asarray([frac * skin, 0.0, 0.0]))
        new = update(cfg, cl, nbrs, moved)
        assert int(new.builds) == 1 + rebuilt, f"moved {frac} skin: builds {int(new.builds)}"
        assert _close(new, moved, h) == _pairs_within(moved, cl.rest_pos, h, h)
    carried = x + jnp.asarray([10 * skin, -4 * skin, 3 * skin])
    assert int(update(cfg, cl, nbrs, carried).builds) == 1, "a carried cloth was rebuilt"
    st = c.ClothState.create(cl, x=x, cfg=cfg).replace(
        v=jnp.zeros_like(x).at[:, 2].set(-0.5))
    step = jax.jit(lambda s: c.rollout(cfg, cl, s, 25))
    for _ in range(8):
        st = step(st)
        nbrs = update(cfg, cl, st.neighbours, st.x)
        assert _close(nbrs, st.x, h) == _pairs_within(st.x, cl.rest_pos, h, h)
    assert int(st.neighbours.builds) > 2, "expected the falling layer to force rebuilds"


def test_batched_lists_equal_single_lists():
    """Under vmap a member that needs no rebuild keeps its list while another rebuilds,
    so each member's list (and state) is the one its single run has."""
    cl, x, h = _folded()
    cfg = c.ClothConfig(dt=2e-4, thickness=h, self_stiffness=5.0, gravity=(0.0, 0.0, 0.0))
    still = c.ClothState.create(cl, cfg=cfg)  # flat at rest, no gravity: nothing moves
    falling = c.ClothState.create(cl, x=x, v=jnp.zeros_like(x).at[:, 2].set(-2.0), cfg=cfg)
    run = jax.jit(lambda s: c.rollout(cfg, cl, s, 40))
    batch = jax.jit(jax.vmap(lambda s: c.rollout(cfg, cl, s, 40)))(
        jax.tree.map(lambda a, b: jnp.stack([a, b]), still, falling))
    for b, single in enumerate((run(still), run(falling))):
        for name in ("builds", "count", "pairs"):
            np.testing.assert_array_equal(getattr(batch.neighbours, name)[b],
                                          getattr(single.neighbours, name), err_msg=name)
        # positions: to float rounding (XLA fuses the batched substep differently)
        np.testing.assert_allclose(batch.neighbours.x_ref[b], single.neighbours.x_ref,
                                   rtol=0, atol=1e-6)
    assert int(batch.neighbours.builds[0]) == 1 < int(batch.neighbours.builds[1])


@pytest.mark.parametrize("batched_cloth", [False, True])
def test_batched_update_builds_the_lists_single_updates_build(batched_cloth):
    """vmap of ``update_neighbours`` over 16 members, of which 0, 1, 4, 5, 8, 9 or 16
    moved more than half the skin (each member tier of the batched rebuild at its edges):
    every member's list (pairs, count, positions, overflow, builds) equals its own
    update's, bit for bit, with the cloth shared or batched; a batch of 4 builds all."""
    cl, x, h = _folded()
    cfg = c.ClothConfig(thickness=h, self_stiffness=5.0)
    B = 16
    assert sc._member_tiers(B) == (4, 8, 16) and sc._member_tiers(4) == (4,)
    keys = jax.random.split(jax.random.PRNGKey(4), 2)
    x0 = x[None] + 0.05 * h * jax.random.normal(keys[0], (B,) + x.shape)
    # half the vertices of a member that moves shift by 1.2 skin: 0.6 skin from the middle
    shift = jnp.zeros(x.shape).at[: x.shape[0] // 2, 0].set(1.2 * sc.skin(cfg))
    jitter = 1e-3 * h * jax.random.normal(keys[1], (B,) + x.shape)
    single = jax.jit(sc.update_neighbours, static_argnums=0)
    cloths = jax.tree.map(lambda a: jnp.stack([a] * B), cl)
    batched = jax.jit(jax.vmap(sc.update_neighbours, in_axes=(
        None, 0 if batched_cloth else None, 0, 0)), static_argnums=0)
    old = jax.vmap(lambda y: sc.neighbour_list(cfg, cl, y))(x0)
    for movers in ((), (6,), (1, 4, 9, 15), (0, 2, 7, 8, 13), tuple(range(0, B, 2)),
                   tuple(range(9)), tuple(range(B))):
        mask = jnp.zeros((B, 1, 1)).at[jnp.asarray(movers, jnp.int32)].set(1.0)
        x1 = x0 + jitter + mask * shift
        new = batched(cfg, cloths if batched_cloth else cl, old, x1)
        for b in range(B):
            one = single(cfg, cl, jax.tree.map(lambda a, b=b: a[b], old), x1[b])
            for name in ("pairs", "count", "x_ref", "overflow", "builds"):
                np.testing.assert_array_equal(getattr(new, name)[b], getattr(one, name),
                                              err_msg=f"{name} of member {b}, {movers}")
        np.testing.assert_array_equal(new.builds, 1 + mask[:, 0, 0].astype(jnp.int32))


def test_force_gradient_with_the_list_held_matches_finite_differences():
    """float64: d (w . f) / d (x, v) of the listed pairs' forces, the list held constant,
    against central differences."""
    with jax.enable_x64(True):
        cl, x, h = _folded()
        cl = jax.tree.map(lambda a: a.astype(jnp.float64) if a.dtype == jnp.float32 else a,
                          cl)
        x = x.astype(jnp.float64) + 0.2 * h * jax.random.normal(jax.random.PRNGKey(0), x.shape)
        v = 0.1 * jax.random.normal(jax.random.PRNGKey(1), x.shape, jnp.float64)
        cfg = c.ClothConfig(thickness=h, self_stiffness=5.0, self_damping=1e-3,
                            self_friction=2e-3)
        nbrs = sc.neighbour_list(cfg, cl, x)
        w = jax.random.normal(jax.random.PRNGKey(2), x.shape, jnp.float64)

        def loss(x, v):
            return jnp.sum(w * c.self_collision_forces(cfg, cl, x, v, nbrs))
        assert float(jnp.abs(c.self_collision_forces(cfg, cl, x, v, nbrs)).max()) > 0
        gx, gv = jax.grad(loss, argnums=(0, 1))(x, v)
        eps = 1e-7
        rng = np.random.default_rng(0)
        for _ in range(6):
            i, k = int(rng.integers(len(x))), int(rng.integers(3))
            for arg, g in ((0, gx), (1, gv)):
                e = jnp.zeros_like(x).at[i, k].set(eps)
                a = [x, v]
                hi = loss(*[a[m] + e if m == arg else a[m] for m in range(2)])
                lo = loss(*[a[m] - e if m == arg else a[m] for m in range(2)])
                fd = float((hi - lo) / (2 * eps))
                assert abs(float(g[i, k]) - fd) <= 1e-5 * max(1.0, abs(fd)), (
                    f"d/d{'xv'[arg]}[{i},{k}]: FD {fd}, autodiff {float(g[i, k])}")


def test_written_reverse_pass_equals_autodiff_of_the_listed_pairs():
    """float64: the listed pairs' written-out VJP (in the stored pairs' slot tier) equals
    the autodiff of the plain pair sum, alone and under vmap over two lists of different
    tiers (the batch's largest tier, its unused slots inert)."""
    with jax.enable_x64(True):
        cl, x, h = _folded()
        cfg = c.ClothConfig(thickness=h, self_stiffness=5.0, self_damping=1e-3,
                            self_friction=2e-3)
        keys = jax.random.split(jax.random.PRNGKey(3), 4)
        xs = jnp.stack([x.astype(jnp.float64) + 0.2 * h * jax.random.normal(k, x.shape)
                        for k in keys[:2]])
        vs = 0.1 * jax.random.normal(keys[2], xs.shape, jnp.float64)
        ct = jax.random.normal(keys[3], (2, 3, x.shape[0]), jnp.float64)
        lists = [sc.neighbour_list(cfg, cl, xb) for xb in xs]
        # the second list: 8 of its touching pairs only, in a smaller slot tier
        touching = sorted(_close(lists[1], xs[1], h))[:8]
        pairs = np.zeros(lists[1].pairs.shape, np.int32)
        pairs[:, :len(touching)] = np.array(touching).T
        lists[1] = lists[1].replace(pairs=jnp.asarray(pairs),
                                    count=jnp.asarray(len(touching), jnp.int32))
        sizes = sc._tier_sizes(lists[0].pairs.shape[1])
        tiers = [int(np.searchsorted(sizes, int(n.count))) for n in lists]
        assert tiers[0] > tiers[1], (tiers, int(lists[0].count))

        def written(nbrs, xt, vt, ct):
            return jax.vjp(lambda a, b: sc._list_forces(cfg, nbrs, a, b), xt, vt)[1](ct)

        def autodiff(nbrs, xt, vt, ct):
            return jax.vjp(lambda a, b: sc._listed_pairs_forces(cfg, nbrs.pairs, a, b),
                           xt, vt)[1](ct)

        xt, vt = jnp.swapaxes(xs, 1, 2), jnp.swapaxes(vs, 1, 2)
        for b in range(2):
            got = written(lists[b], xt[b], vt[b], ct[b])
            want = autodiff(lists[b], xt[b], vt[b], ct[b])
            assert float(jnp.abs(want[0]).max()) > 0
            for g, w in zip(got, want, strict=True):
                np.testing.assert_allclose(g, w, rtol=1e-12, atol=1e-12)
        both = jax.tree.map(lambda a, b: jnp.stack([a, b]), *lists)
        got = jax.vmap(written)(both, xt, vt, ct)
        for b in range(2):
            want = autodiff(lists[b], xt[b], vt[b], ct[b])
            for g, w in zip(got, want, strict=True):
                np.testing.assert_allclose(g[b], w, rtol=1e-12, atol=1e-12)


def test_rollout_gradient_with_the_list_equals_all_pairs():
    """The gradient of a falling folded cloth's final heights is the same with the list
    (rebuilt along the way) as with all pairs: a rebuild changes which pairs are looked
    at, not the forces."""
    cl, x, h = _folded(6, 0.1)
    cfg = c.ClothConfig(dt=2e-4, thickness=h, self_stiffness=5.0, self_friction=1e-3)

    def loss(v0, search):
        cf = dataclasses.replace(cfg, self_search=search)
        st = c.ClothState.create(cl, x=x, v=jnp.zeros_like(x).at[:, 2].set(v0), cfg=cf)
        return jnp.sum(c.rollout(cf, cl, st, 200, segment=50).x[:, 2] ** 2)
    l1, g1 = jax.jit(jax.value_and_grad(lambda v: loss(v, "list")))(-0.5)
    l2, g2 = jax.jit(jax.value_and_grad(lambda v: loss(v, "all")))(-0.5)
    np.testing.assert_allclose(float(l1), float(l2), rtol=1e-5)
    np.testing.assert_allclose(float(g1), float(g2), rtol=1e-4)
    assert abs(float(g1)) > 0, "expected a non-zero gradient"


def test_reverse_memory_grows_with_segments_not_substeps():
    """XLA's temporaries of a rollout's gradient with self-collision: without segments
    they grow with the substeps; checkpointed in segments of 20 they stay well below and
    grow far less when the substeps double."""
    cl, x, h = _folded(6, 0.1)
    cfg = c.ClothConfig(dt=2e-4, thickness=h, self_stiffness=5.0, self_friction=1e-3)
    st = c.ClothState.create(cl, x=x, cfg=cfg)

    def temp(n, seg):
        def loss(v0):
            s = st.replace(v=jnp.zeros_like(x).at[:, 2].set(v0))
            return jnp.sum(c.rollout(cfg, cl, s, n, segment=seg).x[:, 2] ** 2)
        mem = jax.jit(jax.grad(loss)).lower(-0.5).compile().memory_analysis()
        return mem.temp_size_in_bytes
    plain = temp(400, None), temp(800, None)
    seg = temp(400, 20), temp(800, 20)
    assert plain[1] - plain[0] > 0.5 * plain[0], f"expected plain growth, got {plain}"
    assert seg[1] < plain[0] / 4, f"expected checkpointed temporaries << plain: {seg}, {plain}"
    assert seg[1] - seg[0] < (plain[1] - plain[0]) / 10, f"growth {seg} against {plain}"
