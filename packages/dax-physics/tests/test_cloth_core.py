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


def _small_tshirt(**kwargs):
    """The 42-vertex T-shirt (spacing 5 cm) of the spring-layout tests: its row-by-row
    numbering leaves springs outside the offset classes."""
    return c.tshirt_cloth(0.05, stretch=10.0, damping=0.01, **kwargs,
                          outline=dict(width=0.2, length=0.25, sleeve=0.08, sleeve_width=0.08,
                                       neck=0.08, neck_depth=0.02))


def test_spring_layout_adds_a_class_group_only_when_it_holds_enough_springs():
    """Past the first CLASS_GROUP offset classes, a further group is laid out only when it
    takes at least ``group_springs`` springs off the scatter: the small T-shirt keeps one
    group by default, gets a second when the floor is lowered, and every spring is in
    exactly one class or the residual either way."""
    cl = _small_tshirt()
    pairs, V = np.asarray(cl.pairs), cl.n_vertices
    one = c.spring_layout(pairs, V)
    two = c.spring_layout(pairs, V, group_springs=1)
    assert len(one[0]) // 2 == c.CLASS_GROUP, "expected one full group by default"
    assert len(two[0]) // 2 > c.CLASS_GROUP, "expected a second group below the floor"
    floor = len(one[2]) - len(two[2])  # springs the second group takes off the scatter
    assert len(c.spring_layout(pairs, V, group_springs=floor)[0]) == len(two[0])
    assert len(c.spring_layout(pairs, V, group_springs=floor + 1)[0]) == len(one[0])
    for _, table, residual in (one, two):
        in_slots = table[0::2][table[0::2] < len(pairs)]
        assert np.array_equal(np.sort(np.concatenate([in_slots, residual])),
                              np.arange(len(pairs))), "each spring once, in a class or not"


@pytest.mark.parametrize("shape", ["square", "tshirt", "tshirt-groups"])
def test_stencil_spring_sum_equals_the_scatter_with_gradients(shape):
    """The stencil sum (make_cloth's spring layout) gives the forces of the per-spring
    scatter, and its reverse pass their gradients with respect to positions, velocities,
    stiffness, rest lengths and dashpots (float64: agreement to rounding). The T-shirt
    mesh also has springs in no offset class (summed by the scatter); ``tshirt-groups``
    lays it out with every class of at least 1 spring in groups of ``CLASS_GROUP``
    (13 classes: two groups, each summed by loops of its own, as large meshes have)."""
    with jax.enable_x64(True):
        if shape == "square":
            cl = c.square_cloth(6, size=(0.1, 0.1), stretch=10.0, damping=0.01,
                                dtype=jnp.float64)
        else:
            cl = _small_tshirt(dtype=jnp.float64)
        if shape == "tshirt-groups":
            offsets, table, residual = c.spring_layout(cl.pairs, cl.n_vertices, min_share=0.02,
                                                       group_springs=1)
            assert len(offsets) // 2 > c.CLASS_GROUP, "expected a second group of classes"
            cl = cl.replace(offsets=offsets, stencil_edge=jnp.asarray(table, jnp.int32),
                            residual=jnp.asarray(residual, jnp.int32))
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
