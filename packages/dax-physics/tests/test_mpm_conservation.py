"""MPM validation: conservation of mass and momentum, free fall, a fluid at rest, a bounce.

Every scene is tiny (12^3 to 16^3 cells, a few hundred particles) and shared through
module-scoped fixtures, so each distinct configuration compiles once.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dax_physics import materials, mpm, sampling

# the library's rollout is not jitted: the caller jits it (cfg and the count static)
_rollout = jax.jit(mpm.rollout, static_argnums=(0, 3))

G = 9.81


@functools.partial(jax.jit, static_argnums=(0, 3, 4))
def trace(cfg, params, state, n, probe):
    """Run ``n`` substeps; return the final state and ``probe(cfg, params, state)`` after
    every substep (stacked along axis 0)."""

    def body(s, _):
        s = mpm.step(cfg, params, s)
        return s, probe(cfg, params, s)

    return jax.lax.scan(body, state, None, length=n)


def p2g_mass(x, m, dx, shape):
    """Grid mass after P2G with the solver's quadratic B-spline stencil (float64 NumPy):
    base node floor(x/dx - 0.5), per-axis weights 0.5 (1.5 - f)^2, 0.75 - (f - 1)^2,
    0.5 (f - 0.5)^2 with f = x/dx - base. Returns (grid mass, per-particle weight sums)."""
    X = np.asarray(x, np.float64) / dx
    base = np.floor(X - 0.5).astype(int)
    f = X - base
    w = [0.5 * (1.5 - f) ** 2, 0.75 - (f - 1.0) ** 2, 0.5 * (f - 0.5) ** 2]
    grid = np.zeros(shape)
    wsum = np.zeros(len(X))
    for i in range(3):
        for j in range(3):
            for k in range(3):
                wt = w[i][:, 0] * w[j][:, 1] * w[k][:, 2]
                wsum += wt
                idx = base + np.array([i, j, k])
                np.add.at(grid, (idx[:, 0], idx[:, 1], idx[:, 2]), m * wt)
    return grid, wsum


# ----------------------------------------------------------------- float64 block, no walls

N_BLOCK_STEPS = 50


@pytest.fixture(scope="module")
def block64():
    """An elastic block in a 16^3 domain without walls or gravity (float64). Returns a
    function running it from given initial velocities; all results are NumPy."""
    with jax.enable_x64(True):
        dx = 1.0 / 16
        mat = materials.tofu()
        cfg = mpm.MPMConfig(materials=(mat,), dx=dx, dt=2e-3, domain=(16, 16, 16),
                            walls="none", gravity=(0.0, 0.0, 0.0), max_speed=1.0)
        x, vol = sampling.box((6 * dx,) * 3, (10 * dx,) * 3, dx, ppc=8, seed=1)
        params = mpm.MaterialParams.from_materials(cfg.materials, dtype=jnp.float64)

    def run(v):
        with jax.enable_x64(True):
            s0 = mpm.init_state(cfg, x, v=v, vol=vol, dtype=jnp.float64)
            s1 = _rollout(cfg, params, s0, N_BLOCK_STEPS)
            out = {}
            for name, s in (("s0", s0), ("s1", s1)):
                out[name] = jax.tree.map(np.asarray, s)
                out[name + "_momentum"] = np.asarray(mpm.momentum(params, s))
                out[name + "_mass"] = float(mpm.total_mass(params, s))
            out["m"] = np.asarray(s0.vol * params.density[s0.mat])
            return out

    return cfg, x, run


def test_mass_is_conserved_exactly(block64):
    cfg, x, run = block64
    v = np.random.default_rng(2).normal(0.0, 0.2, x.shape) + np.array([0.5, 0.0, 0.0])
    r = run(v)
    assert r["s1_mass"] == r["s0_mass"], (
        f"particle mass changed: {r['s0_mass']!r} kg -> {r['s1_mass']!r} kg")
    np.testing.assert_array_equal(r["s1"].vol, r["s0"].vol, err_msg="particle volumes changed")
    np.testing.assert_array_equal(r["s1"].mat, r["s0"].mat, err_msg="material ids changed")
    moved = np.abs(r["s1"].x - r["s0"].x).max()
    assert moved > 0.5 * cfg.dx, f"the block barely moved ({moved} m): the test is vacuous"
    # P2G of the moved particles puts exactly the particle mass on the grid.
    grid, wsum = p2g_mass(r["s1"].x, r["m"], cfg.dx, cfg.domain)
    np.testing.assert_allclose(wsum, 1.0, rtol=0, atol=1e-12,
                               err_msg="B-spline weights do not sum to 1")
    assert grid.sum() == pytest.approx(r["s0_mass"], rel=1e-12), "grid mass after P2G"


def test_uniform_translation_is_exact(block64):
    """A stress-free block moving uniformly stays a rigid translation: the solver's P2G/G2P
    weights sum to one and have zero first moment (else v, C or F would change)."""
    cfg, x, run = block64
    v0 = np.array([0.3, -0.2, 0.1])
    r = run(np.broadcast_to(v0, x.shape))
    s0, s1 = r["s0"], r["s1"]
    t = N_BLOCK_STEPS * cfg.dt
    np.testing.assert_allclose(s1.v, np.broadcast_to(v0, x.shape), rtol=0, atol=1e-12,
                               err_msg="velocity of a uniform translation changed")
    np.testing.assert_allclose(s1.C, 0.0, rtol=0, atol=1e-9, err_msg="affine velocity C")
    np.testing.assert_allclose(s1.F, s0.F, rtol=0, atol=1e-12,
                               err_msg="deformation gradient of a rigid translation")
    np.testing.assert_allclose(s1.x, s0.x + v0 * t, rtol=0, atol=1e-12, err_msg="positions")


def test_linear_momentum_is_conserved_without_gravity_and_walls(block64):
    cfg, x, run = block64
    v = np.random.default_rng(3).normal(0.0, 0.3, x.shape)
    r = run(v)
    assert not r["s1"].escaped and r["s1"].finite, "scene left the domain or went non-finite"
    # the internal forces were active: the block deformed.
    strain = np.abs(r["s1"].F - np.eye(3)).max()
    assert strain > 1e-3, f"the block did not deform (max |F - I| = {strain})"
    p0, p1 = r["s0_momentum"], r["s1_momentum"]
    scale = float(np.sum(r["m"] * np.linalg.norm(v, axis=1)))  # sum_p m_p |v_p|
    err = float(np.abs(p1 - p0).max())
    assert err <= 1e-10 * scale, (
        f"momentum changed from {p0} to {p1} kg m/s (|dP| = {err:.3g}, allowed "
        f"{1e-10 * scale:.3g})")


# ----------------------------------------------------------------- elastic drop on the floor

DROP_STEPS = 400


def _drop_probe(cfg, params, s):
    return jnp.concatenate([
        jnp.stack([mpm.kinetic_energy(params, s), mpm.potential_energy(cfg, params, s),
                   jnp.min(s.x[:, 2])]),
        jnp.mean(s.x, axis=0), jnp.mean(s.v, axis=0)])


@pytest.fixture(scope="module")
def drop():
    """A 4^3-cell elastic block (nu = 0.3) falling 5 cells onto the slip floor of a 16^3
    box, traced every substep: [KE, PE + strain, min z, com (3), mean velocity (3)]."""
    dx = 1.0 / 16
    mat = materials.Material("elastic", 1000.0, youngs_modulus=5e4, poisson_ratio=0.3)
    cfg = mpm.MPMConfig(materials=(mat,), dx=dx, dt=2e-3, domain=(16, 16, 16), walls="slip",
                        max_speed=3.0)
    x, vol = sampling.box((6 * dx, 6 * dx, 8 * dx), (10 * dx, 10 * dx, 12 * dx), dx, ppc=8)
    params = cfg.params
    s0 = mpm.init_state(cfg, x, vol=vol)
    s1, tr = trace(cfg, params, s0, DROP_STEPS, _drop_probe)
    mpm.check_state(s1)
    e0 = float(mpm.kinetic_energy(params, s0) + mpm.potential_energy(cfg, params, s0))
    return dict(cfg=cfg, tr=np.asarray(tr, np.float64), x0=np.asarray(s0.x), e0=e0,
                mass=float(mpm.total_mass(params, s0)))


def test_free_fall_matches_half_g_t_squared_before_contact(drop):
    cfg, tr = drop["cfg"], drop["tr"]
    dt, dx = cfg.dt, cfg.dx
    # The floor acts on a particle once its stencil reaches a wall node (index <=
    # wall_cells): z < (wall_cells + 1.5) dx.
    free = tr[:, 2] > (cfg.wall_cells + 2.0) * dx
    n_free = int(np.argmin(free))  # first substep with contact
    assert n_free >= 80, f"only {n_free} substeps of free fall: scene too short"
    n = np.arange(1, n_free + 1)
    t = n * dt
    com0 = drop["x0"].mean(axis=0)
    drop_z = com0[2] - tr[:n_free, 5]
    # Symplectic Euler gives v_n = -g t_n, z_n = z_0 - g t_n^2 / 2 - g t_n dt / 2: the
    # continuous answer holds up to the first-order term g t dt / 2.
    np.testing.assert_allclose(drop_z, 0.5 * G * t ** 2, rtol=0,
                               atol=0.5 * G * t[-1] * dt + 1e-5,
                               err_msg="free-fall drop vs g t^2 / 2 [m]")
    np.testing.assert_allclose(drop_z, 0.5 * G * t ** 2 + 0.5 * G * t * dt, rtol=1e-4,
                               atol=1e-5, err_msg="free-fall drop vs the symplectic Euler drop")
    np.testing.assert_allclose(tr[:n_free, 8], -G * t, rtol=1e-4, atol=1e-5,
                               err_msg="free-fall velocity vs -g t [m/s]")
    np.testing.assert_allclose(tr[:n_free, 3:5], np.broadcast_to(com0[:2], (n_free, 2)),
                               rtol=0, atol=1e-5, err_msg="horizontal drift in free fall")


def test_elastic_block_bounces_and_energy_does_not_grow(drop):
    tr, cfg = drop["tr"], drop["cfg"]
    vz = tr[:, 8]
    i_min = int(np.argmin(vz))
    assert vz[i_min] < -2.0, f"impact speed {vz[i_min]} m/s, expected a fall faster than 2 m/s"
    rebound = float(vz[i_min:].max())
    assert rebound > 0.25 * abs(vz[i_min]), (
        f"no bounce: the centre-of-mass velocity went from {vz[i_min]:.3f} m/s to at most "
        f"{rebound:.3f} m/s after impact (expected > {0.25 * abs(vz[i_min]):.3f})")
    energy = tr[:, 0] + tr[:, 1]
    floor = cfg.wall_cells * cfg.dx
    scale = drop["mass"] * G * (drop["x0"][:, 2].mean() - floor)  # available drop energy
    growth = float(energy.max() - drop["e0"])
    assert growth <= 1e-3 * scale, (
        f"total energy grew by {growth:.4g} J above its initial {drop['e0']:.4g} J "
        f"(allowed {1e-3 * scale:.3g} J)")


# ----------------------------------------------------------------- fluid at rest in a box

FLUID_CHUNK = 1000


def _fluid_probe(cfg, params, s):
    return jnp.stack([mpm.kinetic_energy(params, s) + mpm.potential_energy(cfg, params, s),
                      jnp.max(jnp.linalg.norm(s.v, axis=1))])


def test_fluid_at_rest_stays_at_rest_and_energy_does_not_grow():
    """A 3-cell water layer filling a 12^3 box. It first settles (1000 substeps: the layer
    compresses under its weight and sinks into the slip walls' band, as in the usual MPM
    reference scenes); then, over 2000 more substeps, it must stay at rest and its total
    energy (kinetic + gravitational + compression) must not grow."""
    dx = 1.0 / 16
    cfg = mpm.MPMConfig(materials=(materials.water(),), dx=dx, dt=2e-3, domain=(12, 12, 12))
    lo, hi, h = 3 * dx, 9 * dx, 3 * dx
    x, vol = sampling.box((lo, lo, lo), (hi, hi, lo + h), dx, ppc=8)
    params = cfg.params
    s = mpm.init_state(cfg, x, vol=vol)
    s, _ = trace(cfg, params, s, FLUID_CHUNK, _fluid_probe)  # settle
    e_start = float(mpm.kinetic_energy(params, s) + mpm.potential_energy(cfg, params, s))
    com_start = np.asarray(s.x).mean(axis=0)
    traces = []
    for _ in range(2):
        s, tr = trace(cfg, params, s, FLUID_CHUNK, _fluid_probe)
        traces.append(np.asarray(tr, np.float64))
    mpm.check_state(s)
    tr = np.concatenate(traces)
    energy, speed = tr[:, 0], tr[:, 1]

    v_scale = np.sqrt(G * h)  # speed scale of a column of height h
    assert speed.max() <= 0.05 * v_scale, (
        f"the fluid did not stay at rest: max particle speed {speed.max():.4f} m/s over 2000 "
        f"substeps (allowed {0.05 * v_scale:.4f} m/s)")
    scale = float(mpm.total_mass(params, s)) * G * h / 2
    growth = float(energy.max() - e_start)
    assert growth <= 1e-3 * scale, (
        f"energy grew by {growth:.4g} J above {e_start:.4g} J (allowed {1e-3 * scale:.3g} J)")
    rise = float(np.max(energy - np.minimum.accumulate(energy)))
    assert rise <= 1e-3 * scale, (
        f"energy rose by {rise:.4g} J above an earlier value (allowed {1e-3 * scale:.3g} J)")
    drift = np.abs(np.asarray(s.x).mean(axis=0)[:2] - com_start[:2]).max()
    assert drift <= 0.05 * dx, f"the fluid drifted sideways by {drift:.3g} m"


# ----------------------------------------------------------------- energy used above

def test_strain_energy_is_consistent_with_the_documented_stress():
    """The energy tests above use ``mpm.potential_energy``; its stored-energy density psi
    must be the potential of the stress the solver applies (materials.py): the Kirchhoff
    stress is tau = (d psi / d F) F^T for F, tau = J psi'(J) for the fluids' J and
    tau = 2 (d psi / d b) b for the plastic b_e."""
    with jax.enable_x64(True):
        mats = (materials.water(), materials.tofu(), materials.dough())
        cfg = mpm.MPMConfig(materials=mats, dx=0.05, dt=1e-4, domain=(8, 8, 8))
        params = mpm.MaterialParams.from_materials(mats, dtype=jnp.float64)
        rng = np.random.default_rng(5)
        n = 6
        s = mpm.init_state(cfg, np.full((n, 3), 0.2), mat=np.repeat([0, 1, 2], 2),
                           dtype=jnp.float64)
        A = np.eye(3) + 0.15 * rng.normal(size=(n, 3, 3))
        F = A.copy()
        F[4:] = A[4:] @ A[4:].transpose(0, 2, 1)  # plastic slot: b_e, symmetric positive
        J = np.array([0.8, 1.15, 1.0, 1.0, 1.0, 1.0])
        eye = jnp.eye(3, dtype=jnp.float64)
        s = s.replace(H=jnp.asarray(F) - eye, J=jnp.asarray(J))

        def psi_total(F, J):
            return jnp.sum(s.vol * mpm.strain_energy_density(
                cfg, params, s.replace(H=F - eye, J=J)))

        dF, dJ = jax.grad(psi_total, argnums=(0, 1))(s.F, s.J)
        vol = np.asarray(s.vol)
        dF, dJ = np.asarray(dF) / vol[:, None, None], np.asarray(dJ) / vol

    K = mats[0].bulk_modulus
    np.testing.assert_allclose(J[:2] * dJ[:2], K * J[:2] * (J[:2] - 1.0), rtol=1e-9,
                               err_msg="fluid: J psi'(J) vs tau = K J (J - 1)")
    for i in (2, 3):  # fixed-corotated
        mu, lam = mats[1].lame
        U, _, Vt = np.linalg.svd(F[i])
        R = U @ Vt
        det = np.linalg.det(F[i])
        tau = 2 * mu * (F[i] - R) @ F[i].T + lam * det * (det - 1) * np.eye(3)
        np.testing.assert_allclose(dF[i] @ F[i].T, tau, rtol=1e-6, atol=1e-6 * np.abs(tau).max(),
                                   err_msg="elastic: (d psi / d F) F^T vs tau")
    for i in (4, 5):  # von Mises on b_e (inside the yield surface: elastic response)
        mu, lam = mats[2].lame
        kappa = lam + 2 * mu / 3
        b = F[i]
        j2 = np.linalg.det(b)
        bbar = j2 ** (-1 / 3) * b
        tau = 0.5 * kappa * (j2 - 1) * np.eye(3) + mu * (bbar - np.trace(bbar) / 3 * np.eye(3))
        sym = 0.5 * (dF[i] + dF[i].T)
        np.testing.assert_allclose(2 * sym @ b, tau, rtol=1e-6, atol=1e-6 * np.abs(tau).max(),
                                   err_msg="plastic: 2 (d psi / d b) b vs tau")
