"""The hand-written reverse modes of the MPM substep (dax_physics._transfer and
mpm.polar_rotation) against JAX's own differentiation of the same forward code."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dax_physics import _transfer, mpm
from dax_physics.mpm import algebra, constitutive

WINDOW = (6, 6, 6)


@pytest.fixture(scope="module")
def stencil():
    """12 particles in a 6^3 window: block corners, B-spline weights, four channels."""
    rng = np.random.default_rng(0)
    n, c = 12, 4
    x = rng.uniform(1.6, 4.4, (n, 3)).astype(np.float32)  # in cells
    base = np.floor(x - 0.5).astype(np.int32)
    fx = x - base
    w = np.stack([0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2],
                 axis=1).astype(np.float32)
    R = rng.standard_normal((n, 4, c)).astype(np.float32)
    grid = rng.standard_normal(WINDOW + (c,)).astype(np.float32)
    return jnp.asarray(base), jnp.asarray(w), jnp.asarray(R), jnp.asarray(grid)


def _vjps(f_custom, f_plain, args, cot):
    _, vjp_c = jax.vjp(f_custom, *args)
    _, vjp_p = jax.vjp(f_plain, *args)
    return vjp_c(cot), vjp_p(cot)


def test_spread_reverse_mode_matches_autodiff(stencil):
    base, w, R, _ = stencil
    cot = jax.random.normal(jax.random.PRNGKey(1), WINDOW + (R.shape[-1],))
    got, want = _vjps(lambda w, R: _transfer.spread(WINDOW, base, w, R),
                      lambda w, R: _transfer._spread(WINDOW, base, w, R), (w, R), cot)
    for g, e, name in zip(got, want, ("w", "R"), strict=True):
        np.testing.assert_allclose(g, e, rtol=2e-5, atol=2e-5 * float(jnp.abs(e).max()),
                                   err_msg=f"spread cotangent of {name}")


def test_collect_reverse_mode_matches_autodiff(stencil):
    base, w, R, grid = stencil
    cot = jax.random.normal(jax.random.PRNGKey(2), R.shape)
    got, want = _vjps(lambda g, w: _transfer.collect(g, base, w),
                      lambda g, w: _transfer._collect(g, base, w), (grid, w), cot)
    for g, e, name in zip(got, want, ("grid", "w"), strict=True):
        np.testing.assert_allclose(g, e, rtol=2e-5, atol=2e-5 * float(jnp.abs(e).max()),
                                   err_msg=f"collect cotangent of {name}")


def test_spread_and_collect_are_adjoint(stencil):
    """<spread(R), g> = <R, collect(g)> for fixed weights: the identity both reverse modes
    rest on."""
    base, w, R, grid = stencil
    lhs = jnp.vdot(_transfer.spread(WINDOW, base, w, R), grid)
    rhs = jnp.vdot(R, _transfer.collect(grid, base, w))
    np.testing.assert_allclose(lhs, rhs, rtol=1e-5)


def test_polar_rotation_gradient_matches_the_converged_iteration():
    """The closed-form differential of the polar factor against autodiff through many
    more Newton steps than the forward takes (converged), for moderate deformations."""
    rng = np.random.default_rng(3)
    F = jnp.asarray(np.eye(3) + 0.15 * rng.standard_normal((32, 3, 3)), jnp.float32)
    Rbar = jnp.asarray(rng.standard_normal((32, 3, 3)), jnp.float32)

    def loss(rot):
        return lambda F: jnp.sum(algebra.stack3(rot(algebra.mat3(F))) * Rbar)

    def converged(Fm):
        R = Fm
        for _ in range(4):
            R = constitutive._polar_newton(R)
        return R

    got = jax.grad(loss(mpm.polar_rotation))(F)
    want = jax.grad(loss(converged))(F)
    np.testing.assert_allclose(got, want, atol=1e-4 * float(jnp.abs(want).max()))
    # and the rotation it differentiates is orthogonal
    R = algebra.stack3(mpm.polar_rotation(algebra.mat3(F)))
    np.testing.assert_allclose(jnp.einsum("nki,nkj->nij", R, R),
                               np.broadcast_to(np.eye(3), R.shape), atol=1e-5)
