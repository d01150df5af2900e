"""Mass-spring cloth: meshes, springs, stability, contact, friction, self-collision."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import dax_physics.cloth as c
from dax_physics.colliders import ColliderSpec, ColliderState


def test_unstable_dt_is_refused_with_largest_stable_dt():
    cl = c.square_cloth(6, size=(0.2, 0.2), stretch=100.0)
    dtmax = c.max_stable_dt(c.ClothConfig(), cl)
    cfg = c.ClothConfig(dt=2 * dtmax)
    with pytest.raises(ValueError, match=f"exceeds the largest stable dt {dtmax:.3g} s"):
        c.check_params(cfg, cl)
    c.check_params(c.ClothConfig(dt=dtmax), cl)  # the bound itself is accepted
    # the bound is real: at the bound a perturbed cloth stays bounded, far above it explodes
    rng = np.random.default_rng(0)
    x = cl.rest_pos + 1e-3 * jnp.asarray(rng.normal(size=cl.rest_pos.shape), jnp.float32)

    def run(dt):
        cfg = c.ClothConfig(dt=dt, gravity=(0, 0, 0), table_height=None)
        st = c.ClothState.create(cl, x=x)
        step = jax.jit(lambda s: c.step(cfg, cl, s))
        for _ in range(2000):
            st = step(st)
        d = st.x[cl.pairs[:, 1]] - st.x[cl.pairs[:, 0]]
        return float(jnp.max(jnp.abs(jnp.linalg.norm(d, axis=1) / cl.rest_length - 1)))
    ok, bad = run(dtmax), run(4 * dtmax)
    assert ok < 0.1, f"expected bounded strain at dt = dtmax, got max strain {ok}"
    assert not bad < 10.0, f"expected dt = 4 dtmax to blow up, got max strain {bad}"


def _curtain(n):
    v, f = c.square_mesh(n, size=(0.3, 0.3))
    v = np.stack([v[:, 0], np.zeros(len(v)), v[:, 1]], 1)  # vertical sheet, top edge z=0.3
    cl = c.make_cloth(v, f, density=0.2, stretch=20.0, bend=0.5)
    cfg = c.ClothConfig(dt=c.max_stable_dt(c.ClothConfig(air_drag=2.0), cl), air_drag=2.0,
                        table_height=None)
    st = c.ClothState.create(cl, n_grippers=2)
    top = np.flatnonzero(np.isclose(v[:, 2], 0.3))
    st = c.grasp(st, 0, v[top[0]], 0.0501)
    st = c.grasp(st, 1, v[top[-1]], 0.0501)
    return cfg, cl, st, top[len(top) // 2]


def test_pinned_cloth_sag_is_static_converges_and_energy_does_not_grow():
    sags = []
    for n in (7, 13, 25):
        cfg, cl, st, mid = _curtain(n)
        k = int(0.25 / cfg.dt)
        run = jax.jit(lambda s, cfg=cfg, cl=cl, k=k: c.rollout(cfg, cl, s, k))
        energies = [float(c.energy(cfg, cl, st))]
        for _ in range(8):  # 2 s
            st = run(st)
            energies.append(float(c.energy(cfg, cl, st)))
        s1 = 0.3 - float(st.x[mid, 2])
        s2 = 0.3 - float(run(run(st)).x[mid, 2])
        assert abs(s2 - s1) < 0.01 * s1, f"n={n}: expected a static sag, got {s1} then {s2}"
        growth = max(b - a for a, b in zip(energies, energies[1:], strict=False))
        assert growth <= 1e-7, f"n={n}: expected energy not to grow, got +{growth} J"
        sags.append(s1)
    d1, d2 = abs(sags[1] - sags[0]), abs(sags[2] - sags[1])
    assert d2 < d1, f"expected the sag to converge under refinement, got sags {sags}"
    assert d2 < 0.05 * sags[2], f"expected n=13 and n=25 sags within 5 %, got {sags}"


def test_dropped_cloth_comes_to_rest_flat_on_table():
    cl = c.square_cloth(10, size=(0.3, 0.3), height=0.05, stretch=50.0, damping=0.02)
    cfg = c.ClothConfig(dt=2e-4, friction_static=0.5, air_drag=0.5)
    out = jax.jit(lambda s: c.rollout(cfg, cl, s, 5000))(c.ClothState.create(cl))
    z = np.asarray(out.x[:, 2])
    vmax = float(jnp.max(jnp.abs(out.v)))
    assert z.min() >= 0.0 and z.max() < 1e-4, f"expected z in [0, 1e-4] m, got [{z.min()}, " \
                                               f"{z.max()}]"
    assert vmax < 1e-3, f"expected rest (|v| < 1e-3 m/s), got {vmax}"
    span = np.ptp(np.asarray(out.x[:, 0]))
    assert abs(span - 0.3) < 0.01, f"expected a flat 0.3 m wide cloth, got width {span}"


@pytest.mark.parametrize("ratio", [0.8, 1.2])
def test_table_friction_holds_below_and_slides_above_threshold(ratio):
    mu_s, mu_d, g = 0.5, 0.4, 9.81
    ax = ratio * mu_s * g  # horizontal load as a tilted gravity
    cl = c.square_cloth(6, size=(0.2, 0.2), stretch=50.0)
    cfg = c.ClothConfig(dt=2e-4, gravity=(ax, 0.0, -g), friction_static=mu_s,
                        friction_dynamic=mu_d)
    T = 0.5
    out = jax.jit(lambda s: c.rollout(cfg, cl, s, int(T / cfg.dt)))(c.ClothState.create(cl))
    dx = float(jnp.mean(out.x[:, 0] - cl.rest_pos[:, 0]))
    if ratio < 1:
        assert abs(dx) < 1e-6, f"expected the cloth to stick (dx = 0), got dx = {dx} m"
    else:
        want = 0.5 * (ax - mu_d * g) * T ** 2
        assert abs(dx - want) < 0.02 * want, f"expected sliding dx = {want} m, got {dx} m"


def test_spatial_hash_finds_every_close_pair():
    rng = np.random.default_rng(1)
    x = jnp.asarray(rng.uniform(0, 0.1, size=(300, 3)), jnp.float32)
    cfg = c.ClothConfig(thickness=0.012, self_candidates=16, self_search="hash")
    idx, valid = c.self_collision_candidates(cfg, x)
    found = {(i, int(j)) for i in range(300) for j, ok in zip(np.asarray(idx[i]),
                                                               np.asarray(valid[i]),
                                                               strict=True) if ok}
    d = np.linalg.norm(np.asarray(x)[:, None] - np.asarray(x)[None], axis=-1)
    want = {(i, j) for i, j in zip(*np.nonzero(d < 0.012), strict=True) if i != j}
    missing = want - found
    assert not missing, f"expected all {len(want)} pairs within h, missing {len(missing)}"


def test_spatial_hash_overflow_is_counted_and_is_what_loses_pairs():
    """A stack of 8 layers of a 4x4 grid inside one hash cell: 128 vertices in one bucket.
    With 16 slots 112 are dropped and pairs go missing; with 128 none are, every pair
    within h is found."""
    h = 0.03
    g = np.stack(np.meshgrid(np.arange(4), np.arange(4), indexing="ij"), -1).reshape(-1, 2)
    layers = [np.c_[0.001 + 0.01 * g, np.full(16, 0.001 + 0.007 * k)] for k in range(8)]
    x = jnp.asarray(np.concatenate(layers), jnp.float32)  # all inside the cell [0, 2h)^3
    d = np.linalg.norm(np.asarray(x)[:, None] - np.asarray(x)[None], axis=-1)
    want = {(i, j) for i, j in zip(*np.nonzero(d < h), strict=True) if i != j}
    for slots, dropped in ((16, 112), (128, 0)):
        cfg = c.ClothConfig(thickness=h, self_candidates=slots, self_search="hash")
        assert int(jax.jit(c.self_collision_overflow, static_argnums=0)(cfg, x)) == dropped
        idx, valid = c.self_collision_candidates(cfg, x)
        found = {(i, int(j)) for i in range(len(x))
                 for j, ok in zip(np.asarray(idx[i]), np.asarray(valid[i]), strict=True) if ok}
        missing = len(want - found)
        assert (missing > 0) == (dropped > 0), (
            f"{slots} slots: {dropped} dropped vertices but {missing} pairs missing")


def _layer_stack(h=0.03):
    """8 layers of a 4x4 grid inside one hash cell of side 2h: 128 vertices."""
    g = np.stack(np.meshgrid(np.arange(4), np.arange(4), indexing="ij"), -1).reshape(-1, 2)
    layers = [np.c_[0.001 + 0.01 * g, np.full(16, 0.001 + 0.007 * k)] for k in range(8)]
    return np.concatenate(layers)


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


def test_all_pairs_self_collision_is_exact_where_the_hash_drops_contacts():
    """On the 8-layer stack (the hash's 16 slots drop 112 of 128 vertices) the all-pairs
    search gives the float64 brute-force forces of the contact law, damping and friction
    included, and the 16-slot hash does not; on a scattered cloud the hash drops nothing
    and both searches agree. ``"auto"`` picks all pairs at this size."""
    h, k, damping, friction = 0.03, 0.5, 1e-3, 2e-3
    rng = np.random.default_rng(3)
    x = _layer_stack(h)
    v = rng.normal(0.0, 0.1, x.shape)
    cl = c.square_cloth(16, 8, size=(0.3, 0.15))
    rest = np.asarray(cl.rest_pos, np.float64)
    want = _brute_force_self_forces(x, v, rest, h, k, damping, friction, 2.0)
    kw = dict(thickness=h, self_stiffness=k, self_damping=damping, self_friction=friction)

    def forces(search, pts, vel):
        cfg = c.ClothConfig(self_search=search, self_candidates=16, **kw)
        return np.asarray(jax.jit(c.self_collision_forces, static_argnums=0)(
            cfg, cl, jnp.asarray(pts, jnp.float32), jnp.asarray(vel, jnp.float32)))
    scale = np.max(np.abs(want))
    assert scale > 0, "the stack should be in contact"
    assert c.self_search_mode(c.ClothConfig(**kw), len(x)) == "all"
    err_all = np.max(np.abs(forces("all", x, v) - want)) / scale
    err_hash = np.max(np.abs(forces("hash", x, v) - want)) / scale
    assert err_all < 1e-5, f"all pairs should match the brute force, rel. error {err_all}"
    assert err_hash > 0.1, f"the overflowing hash should miss contacts, rel. error {err_hash}"
    assert int(c.self_collision_overflow(c.ClothConfig(self_search="all", **kw),
                                         jnp.asarray(x))) == 0
    cloud = rng.uniform(0.0, 0.3, size=(128, 3))
    assert int(c.self_collision_overflow(c.ClothConfig(self_search="hash", self_candidates=16,
                                                       **kw), jnp.asarray(cloud))) == 0
    f_cloud = forces("all", cloud, v)
    assert np.count_nonzero(np.abs(f_cloud).sum(1)) > 10, "the cloud should have contacts"
    np.testing.assert_allclose(f_cloud, forces("hash", cloud, v), rtol=1e-5, atol=1e-9)


def test_unknown_self_search_is_refused():
    with pytest.raises(ValueError, match="self_search"):
        c.ClothConfig(thickness=0.01, self_search="octree")


def test_strain_limit_bounds_structural_stretch():
    cl = c.square_cloth(8, size=(0.2, 0.2), stretch=20.0)
    i, j = np.asarray(cl.pairs).T
    struct = np.asarray(cl.kind) == 0

    def max_strain(limit):
        cfg = c.ClothConfig(dt=2e-4, strain_limit=limit, table_height=None)
        st = c.grasp(c.ClothState.create(cl), 0, (0.0, 0.0, 0.0), 0.01)
        out = jax.jit(lambda s: c.move_gripper(cfg, cl, s, 0, (-0.1, -0.1, 0.05), 1500))(st)
        x = np.asarray(out.x)
        ln = np.linalg.norm(x[j] - x[i], axis=1)
        return float(np.max(ln[struct] / np.asarray(cl.rest_length)[struct] - 1))
    free, limited = max_strain(None), max_strain(0.1)
    assert free > 0.15, f"expected the unlimited pull to stretch > 15 %, got {free}"
    assert limited < 0.115, f"expected strain <= 0.1 (+tol) with the limit, got {limited}"


def test_cloth_drapes_over_sphere_collider():
    cl = c.square_cloth(12, size=(0.4, 0.4), origin=(-0.2, -0.2), height=0.12, stretch=50.0)
    spec = ColliderSpec("sphere", (0.08,), mode="separate", friction=0.5)
    cfg = c.ClothConfig(dt=2e-4, colliders=(spec,), air_drag=0.5)
    st = c.ClothState.create(cl, colliders=ColliderState.create([0.0, 0.0, 0.0]))
    out = jax.jit(lambda s: c.rollout(cfg, cl, s, 3000))(st)
    r = np.linalg.norm(np.asarray(out.x), axis=1)
    zc = float(out.x[np.argmin(np.linalg.norm(np.asarray(out.x[:, :2]), axis=1)), 2])
    assert r.min() > 0.08 - 0.005, f"expected no vertex deep inside the sphere, got r {r.min()}"
    assert abs(zc - 0.08) < 0.01, f"expected the centre resting on top (0.08 m), got {zc}"
    assert float(out.x[:, 2].min()) < 0.05, "expected the edges to hang below the top, got " \
                                            f"min z {float(out.x[:, 2].min())}"


def test_tshirt_mesh_is_valid_with_sleeves_and_simulates():
    v, f = c.tshirt_mesh(spacing=0.03)
    c.validate_mesh(v, f)
    body = c.tshirt_outline()
    width = np.ptp(v[:, 0])
    assert width > 0.5 + 0.3, f"expected sleeves to widen the shirt beyond 0.8 m, got {width}"
    assert np.ptp(body[:, 0]) - width < 0.05, f"expected the mesh to span the outline, got " \
                                              f"{width} vs {np.ptp(body[:, 0])}"
    cl = c.tshirt_cloth(spacing=0.03, height=0.02, stretch=50.0)
    cfg = c.ClothConfig(dt=2e-4)
    out = jax.jit(lambda s: c.rollout(cfg, cl, s, 500))(c.ClothState.create(cl))
    assert bool(jnp.all(jnp.isfinite(out.x))), "expected finite positions, got NaN/inf"


def test_meshio_roundtrip(tmp_path):
    meshio = pytest.importorskip("meshio")
    v, f = c.square_mesh(5, size=(0.2, 0.3))
    path = tmp_path / "cloth.obj"
    meshio.write_points_cells(str(path), v, [("triangle", f)])
    cl = c.mesh_cloth(path)
    ref = c.make_cloth(v, f)
    assert cl.n_vertices == 25, f"expected 25 vertices, got {cl.n_vertices}"
    np.testing.assert_allclose(np.sort(np.asarray(cl.stiffness)),
                               np.sort(np.asarray(ref.stiffness)), rtol=1e-5,
                               err_msg="expected the same springs after the roundtrip")


def test_degenerate_and_non_manifold_meshes_are_rejected():
    v, f = c.square_mesh(3)
    bad = v.copy()
    tri = f[0]
    bad[tri[2]] = 0.5 * (bad[tri[0]] + bad[tri[1]])  # third vertex on the opposite edge
    with pytest.raises(c.MeshError, match="degenerate triangle"):
        c.make_cloth(bad, f)
    with pytest.raises(c.MeshError, match="repeated vertex"):
        c.make_cloth(v, np.array([[0, 1, 1]]))
    v2 = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1.0]])
    f2 = np.array([[0, 1, 2], [0, 1, 3], [0, 1, 4]])
    with pytest.raises(c.MeshError, match="non-manifold"):
        c.make_cloth(v2, f2)


def test_nan_pick_point_raises_eagerly_and_is_a_noop_under_jit():
    cl = c.square_cloth(5, size=(0.2, 0.2))
    st = c.ClothState.create(cl)
    with pytest.raises(ValueError, match="finite"):
        c.grasp(st, 0, (np.nan, 0.0, 0.0), 0.05)
    out = jax.jit(lambda p: c.grasp(st, 0, p, 0.05, snap=True))(jnp.array([jnp.nan, 0.0, 0.0]))
    assert float(out.grip.sum()) == 0.0, f"expected no grasp, got {float(out.grip.sum())}"
    assert bool(jnp.all(jnp.isfinite(out.gripper_pos))), f"expected finite gripper, got " \
                                                         f"{out.gripper_pos}"


def test_pick_with_nothing_in_reach_is_a_noop_and_snap_always_grasps():
    cl = c.square_cloth(5, size=(0.2, 0.2), stretch=50.0)
    cfg = c.ClothConfig(dt=2e-4)
    st = c.ClothState.create(cl)
    sc = c.PickPlace(approach_steps=20, lift_steps=50, move_steps=50, lower_steps=50,
                     settle_steps=20, radius=0.01, snap=False)
    far = jnp.array([0.5, 0.5, 0.0])
    out = c.pick_and_place(cfg, cl, st, far, jnp.array([0.1, 0.1, 0.0]), sc)
    ref = c.rollout(cfg, cl, st, sc.n_steps)
    diff = float(jnp.max(jnp.abs(out.x - ref.x)))
    assert diff == 0.0, f"expected an untouched cloth (diff 0), got {diff}"
    snapped = c.grasp(st, 0, far, 0.01, snap=True)
    assert float(snapped.grip.sum()) == 1.0, f"expected 1 vertex grasped, got " \
                                             f"{float(snapped.grip.sum())}"


def test_several_grippers_hold_different_vertices():
    cl = c.square_cloth(5, size=(0.2, 0.2), stretch=50.0)
    cfg = c.ClothConfig(dt=2e-4, table_height=None)
    st = c.ClothState.create(cl, n_grippers=2)
    st = c.grasp(st, 0, (0.0, 0.0, 0.0), 0.01)
    st = c.grasp(st, 1, (0.2, 0.0, 0.0), 0.01)
    st = st.replace(gripper_vel=jnp.array([[0.0, 0.0, 0.1], [0.0, 0.0, -0.1]]))
    out = c.rollout(cfg, cl, st, 1000)
    got = (float(out.x[0, 2]), float(out.x[20, 2]))
    assert abs(got[0] - 0.02) < 1e-5 and abs(got[1] + 0.02) < 1e-5, \
        f"expected held corners at z = (0.02, -0.02) m, got {got}"


def test_config_is_hashable_and_state_is_a_pytree():
    cfg = c.ClothConfig(colliders=(ColliderSpec("sphere", (0.1,)),))
    assert hash(cfg) == hash(dataclasses.replace(cfg)), "expected equal hashes"
    cl = c.square_cloth(3)
    st = c.ClothState.create(cl)
    leaves = jax.tree_util.tree_leaves(st)
    assert len(leaves) == 10, f"expected 10 array leaves in ClothState, got {len(leaves)}"


@pytest.mark.parametrize("shape", ["square", "tshirt"])
def test_stencil_spring_sum_equals_the_scatter_with_gradients(shape):
    """The stencil sum (make_cloth's spring layout) gives the forces of the per-spring
    scatter, and its reverse pass their gradients with respect to positions, velocities,
    stiffness, rest lengths and dashpots (float64: agreement to rounding). The T-shirt
    mesh also has springs in no offset class (summed by the scatter)."""
    with jax.enable_x64(True):
        if shape == "square":
            cl = c.square_cloth(6, size=(0.1, 0.1), stretch=10.0, damping=0.01,
                                dtype=jnp.float64)
        else:
            cl = c.tshirt_cloth(0.05, stretch=10.0, damping=0.01, dtype=jnp.float64,
                                outline=dict(width=0.2, length=0.25, sleeve=0.08,
                                             sleeve_width=0.08, neck=0.08, neck_depth=0.02))
        assert cl.offsets, "expected the mesh's springs sorted into offset classes"
        if shape == "tshirt":
            assert 0 < cl.residual.shape[0] < cl.pairs.shape[0], "expected a residual"
        plain = cl.replace(offsets=(), stencil_edge=None, residual=None)
        keys = jax.random.split(jax.random.PRNGKey(0), 3)
        x = cl.rest_pos + 0.01 * jax.random.normal(keys[0], cl.rest_pos.shape, jnp.float64)
        v = 0.1 * jax.random.normal(keys[1], x.shape, jnp.float64)
        w = jax.random.normal(keys[2], x.shape, jnp.float64)

        def loss(k, L, damp, x, v, base):
            f = c.spring_forces(base.replace(stiffness=k, rest_length=L, damping=damp), x, v)
            return jnp.sum(w * f ** 2)

        args = (cl.stiffness, cl.rest_length, cl.damping, x, v)
        f_s, f_p = c.spring_forces(cl, x, v), c.spring_forces(plain, x, v)
        np.testing.assert_allclose(f_s, f_p, rtol=1e-12, atol=1e-12 * float(jnp.abs(f_p).max()),
                                   err_msg="expected the stencil forces equal to the scatter's")
        g_s = jax.grad(loss, argnums=(0, 1, 2, 3, 4))(*args, cl)
        g_p = jax.grad(loss, argnums=(0, 1, 2, 3, 4))(*args, plain)
        for name, a, b in zip(("stiffness", "rest length", "damping", "x", "v"), g_s, g_p,
                              strict=True):
            np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-10 * float(jnp.abs(b).max()),
                                       err_msg=f"d loss / d {name}: stencil vs scatter")
