"""The regular-grid cloth of the cloth-drop benchmark (``benchmarks.cloth_grid``): it agrees
with the Taichi and Warp references and with the library's mesh cloth, its hand-written
reverse mode with autodiff and finite differences, and it refuses an unstable substep."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import dax_physics.cloth as c
from benchmarks import cloth_grid as grid

# Mean height after 1000 substeps of the standard cloth-drop scene, from the independent
# Taichi and Warp reference implementations (they agree to 5e-8).
PEERS_MEAN_HEIGHT = 0.008108


def test_grid_cloth_drop_matches_the_peer_reference():
    cfg, cloth, state = grid.cloth_drop_scene(64)
    out = jax.jit(lambda c, s: grid.grid_rollout(cfg, c, s, 1000))(cloth, state)
    got = float(np.asarray(out.x[2]).mean())
    assert abs(got - PEERS_MEAN_HEIGHT) < 1e-4, f"expected {PEERS_MEAN_HEIGHT}, got {got}"
    assert float(np.asarray(out.x[2]).min()) >= 0.0, "a vertex went below the ground clamp"


def test_grid_cloth_refuses_an_unstable_substep_and_names_the_limit():
    cfg = grid.GridClothConfig(n=16, m=16, dt=1e-2)
    with pytest.raises(ValueError, match=r"largest stable dt") as err:
        cfg.check_stable()
    assert f"{cfg.max_stable_dt():.4g}" in str(err.value)


def _peers_like_cloth(n, dtype=jnp.float32):
    """A general-mesh Cloth with the grid scene's 12-neighbour springs (for comparison)."""
    cfg, gcloth, gstate = grid.cloth_drop_scene(n)
    x0 = np.asarray(grid.to_vertices(gstate.x))
    pairs, rest, k = [], [], []
    for (di, dj, fam), _r in zip(grid.GRID_DIRECTIONS, gcloth.rest, strict=True):
        a, b = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
        a2, b2 = a + di, b + dj
        ok = (a2 < n) & (b2 >= 0) & (b2 < n)
        pairs.append(np.stack([(a * n + b)[ok], (a2 * n + b2)[ok]], 1))
        rest.append(np.linalg.norm(x0[pairs[-1][:, 1]] - x0[pairs[-1][:, 0]], axis=1))
        k.append(np.full(ok.sum(), cfg.stiffness(fam)))
    pairs = np.concatenate(pairs)
    V = n * n
    cl = c.Cloth(rest_pos=jnp.asarray(x0, dtype), mass=jnp.full((V,), cfg.mass, dtype),
                 area=jnp.full((V,), 1.0 / V, dtype), pairs=jnp.asarray(pairs, jnp.int32),
                 kind=jnp.zeros(len(pairs), jnp.int8),
                 rest_length=jnp.asarray(np.concatenate(rest), dtype),
                 stiffness=jnp.asarray(np.concatenate(k), dtype),
                 damping=jnp.full((len(pairs),), cfg.damping, dtype),
                 faces=jnp.zeros((1, 3), jnp.int32))
    return cfg, gcloth, gstate, cl


def test_grid_stencil_path_matches_general_mesh_solver():
    n, steps = 12, 400
    gcfg, gcloth, gstate, cl = _peers_like_cloth(n)
    cfg = c.ClothConfig(dt=gcfg.dt, gravity=gcfg.gravity, table_height=0.0)
    st = c.ClothState.create(cl)
    got = jax.jit(lambda s: c.rollout(cfg, cl, s, steps))(st).x
    want = grid.to_vertices(jax.jit(lambda s: grid.grid_rollout(gcfg, gcloth, s, steps))(
        gstate).x)
    err = float(jnp.max(jnp.abs(got - want)))
    assert err < 2e-6, f"expected grid and mesh solvers to agree to 2e-6 m, got max diff {err}"


def _grid_forces_per_spring(cfg, cloth, x, v):
    """The grid cloth's forces evaluated once per spring and padded back to both ends:
    the plain formulation, differentiated by JAX, as the reference for the hand-written
    reverse mode of ``grid_forces``."""
    n, m = cfg.n, cfg.m
    f = jnp.zeros_like(x)
    for (di, dj, fam), rest in zip(grid.GRID_DIRECTIONS, cloth.rest, strict=True):
        a, b = grid._pair_slices(n, m, di, dj)
        sa, sb = (slice(None),) + a, (slice(None),) + b
        d, dv = x[sb] - x[sa], v[sb] - v[sa]
        ln = jnp.sqrt(jnp.sum(d * d, axis=0))
        s = cfg.stiffness(fam) * (ln - rest) + cfg.damping * jnp.sum(dv * d, axis=0) / ln
        fa = (s / ln)[None] * d
        f = f + jnp.pad(fa, ((0, 0), (0, di), (max(0, -dj), max(0, dj)))) - jnp.pad(
            fa, ((0, 0), (di, 0), (max(0, dj), max(0, -dj))))
    return f


def test_grid_forces_and_their_reverse_mode_match_the_per_spring_sum():
    """float64, a jittered 7x9 sheet (every spring family, both diagonals, the edges):
    forces and the cotangents of rest lengths, positions and velocities agree with autodiff
    of the per-spring formulation to rounding."""
    with jax.enable_x64(True):
        cfg = grid.GridClothConfig(n=7, m=9, mass=1e-3)
        rng = np.random.default_rng(0)
        u, w = np.meshgrid(np.linspace(0, 0.3, 7), np.linspace(0, 0.4, 9), indexing="ij")
        x0 = np.stack([u, w, 0.1 + 0.05 * u], -1).reshape(-1, 3)
        cloth = grid.grid_rest_lengths(x0, 7, 9)
        x = grid.from_vertices(x0 + 0.01 * rng.standard_normal(x0.shape), 7, 9)
        v = jnp.asarray(0.2 * rng.standard_normal(x.shape))
        cot = jnp.asarray(rng.standard_normal(x.shape))
        got, vjp_got = jax.vjp(lambda cl, x, v: grid.grid_forces(cfg, cl, x, v), cloth, x, v)
        want, vjp_want = jax.vjp(lambda cl, x, v: _grid_forces_per_spring(cfg, cl, x, v),
                                 cloth, x, v)
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-12 * float(jnp.abs(want).max()))
        for name, g, e in zip(("rest", "x", "v"), vjp_got(cot), vjp_want(cot), strict=True):
            for gl, el in zip(jax.tree.leaves(g), jax.tree.leaves(e), strict=True):
                np.testing.assert_allclose(gl, el, rtol=0,
                                           atol=1e-12 * float(jnp.abs(el).max()),
                                           err_msg=f"cotangent of {name}")


def test_grid_rollout_gradient_through_ground_contact_matches_finite_differences():
    """float64, a 5x6 sheet thrown at the ground: the rollout's reverse-mode gradient (the
    hand-written force VJP, the ground clamp's masks, the scan) agrees with central
    differences along a random direction, with vertices hitting the ground on the way."""
    with jax.enable_x64(True):
        n, m = 5, 6
        cfg = grid.GridClothConfig(n=n, m=m, mass=1e-3)
        cfg = dataclasses.replace(cfg, dt=0.5 * cfg.max_stable_dt())
        u, w = np.meshgrid(np.linspace(0, 0.2, n), np.linspace(0, 0.25, m), indexing="ij")
        x0 = np.stack([u, w, 0.002 + 0.02 * u], -1).reshape(-1, 3)
        cloth = grid.grid_rest_lengths(x0, n, m)
        rng = np.random.default_rng(3)
        x = grid.from_vertices(x0 + 1e-3 * rng.standard_normal(x0.shape), n, m)
        v0 = jnp.asarray(0.1 * rng.standard_normal(x.shape)).at[2].add(-1.0)
        wx, wv, dirn = (jnp.asarray(rng.standard_normal(x.shape)) for _ in range(3))
        steps = 40

        def loss(v):
            out = grid.grid_rollout(cfg, cloth, grid.GridState(x, v), steps)
            return jnp.sum(wx * out.x) + 1e-2 * jnp.sum(wv * out.v)

        out = grid.grid_rollout(cfg, cloth, grid.GridState(x, v0), steps)
        assert float(jnp.min(out.x[2])) == 0.0, "the sheet should rest on the ground"
        g = jax.jit(jax.grad(loss))(v0)
        eps = 1e-7
        fd = (loss(v0 + eps * dirn) - loss(v0 - eps * dirn)) / (2 * eps)
        np.testing.assert_allclose(float(jnp.vdot(g, dirn)), float(fd), rtol=1e-6)
