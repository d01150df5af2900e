"""MPM validation: reverse-mode gradients through 50 substeps against central finite
differences (float64), and checkpointed rollouts giving the same gradients.

Scene: a 125-particle tofu cube with random initial velocities, hit by a sticky sphere
collider moving at 1 m/s (12^3 grid, no walls, gravity on). The loss is a smooth function
of the final positions (a fixed random weighting plus the mean x), so it depends on the
deformation (hence on E) as well as on the motion.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.ad_checkpoint import print_saved_residuals

from dax_physics import colliders, materials, mpm, sampling

N_STEPS = 50
SEGMENT = 10


@pytest.fixture(scope="module")
def scene():
    with jax.enable_x64(True):
        f64 = jnp.float64
        dx = 1.0 / 12
        mat = materials.tofu()
        sphere = colliders.ColliderSpec("sphere", (1.5 * dx,), mode="sticky")
        cfg = mpm.MPMConfig(materials=(mat,), dx=dx, dt=3e-3, domain=(12, 12, 12),
                            walls="none", colliders=(sphere,), max_speed=2.0)
        x, vol = sampling.box((0.4, 0.4, 0.4), (0.6, 0.6, 0.6), dx, ppc=8)
        rng = np.random.default_rng(0)
        v0 = jnp.asarray(rng.normal(0.0, 0.2, x.shape), f64)
        cs = colliders.ColliderState.create([[0.25, 0.5, 0.5]], dtype=f64)
        state = mpm.init_state(cfg, x, vol=vol, colliders=cs, dtype=f64)
        params = mpm.MaterialParams.from_materials(cfg.materials, dtype=f64)
        weights = jnp.asarray(rng.normal(size=x.shape), f64)
        vc0 = jnp.asarray([1.0, 0.0, 0.0], f64)
        E0 = jnp.asarray(mat.youngs_modulus, f64)

        def loss(v, vc, E, segment=None):
            s = mpm.set_collider_velocity(state.replace(v=v), 0, vc)
            p = params.with_youngs_modulus(0, E, mat.poisson_ratio)
            out = mpm.rollout(cfg, p, s, N_STEPS, segment=segment)
            return jnp.mean(out.x * weights) + jnp.mean(out.x[:, 0]), out

        def grads(segment):
            with jax.enable_x64(True):
                g = jax.grad(lambda v, vc, E: loss(v, vc, E, segment), argnums=(0, 1, 2),
                             has_aux=True)
                out, final = jax.jit(g)(v0, vc0, E0)
                out = tuple(np.asarray(a) for a in out)
            assert all(a.dtype == np.float64 for a in out), "gradients are not float64"
            return out, final

        plain, final = grads(None)
        forward = jax.jit(loss)

        def fd(direction_v=None, direction_vc=None, dE=None):
            """Central difference of the loss along one input direction."""
            def at(eps):
                with jax.enable_x64(True):
                    v = v0 if direction_v is None else v0 + eps * jnp.asarray(direction_v)
                    vc = vc0 if direction_vc is None else vc0 + eps * jnp.asarray(direction_vc)
                    E = E0 if dE is None else E0 + eps * dE
                    assert v.dtype == vc.dtype == E.dtype == jnp.float64
                    return float(forward(v, vc, E)[0])
            return (at(1.0) - at(-1.0)) / 2.0
    return dict(grads=grads, plain=plain, fd=fd, rng=rng, final=final, x=x, E0=float(E0))


def test_scene_is_finite_and_the_collider_hits_the_cube(scene):
    mpm.check_state(scene["final"])
    g_vc = scene["plain"][1]
    assert abs(g_vc[0]) > 1e-2, f"the collider barely affects the loss: dL/dv_c = {g_vc}"


def test_gradient_wrt_initial_velocity_matches_finite_differences(scene):
    d = scene["rng"].normal(size=scene["x"].shape)
    h = 1e-5  # [m/s] along a unit-variance direction; float64 keeps the rounding ~1e-10
    fd = scene["fd"](direction_v=h * d) / h
    ad = float(np.sum(scene["plain"][0] * d))
    assert abs(fd) > 1e-4, f"directional derivative too small to test: {fd}"
    assert ad == pytest.approx(fd, rel=0.01), f"dL/dv0 . d: autodiff {ad}, central FD {fd}"


def test_gradient_wrt_collider_velocity_matches_finite_differences(scene):
    d = np.array([1.0, 0.5, -0.7])
    h = 1e-5  # [m/s]
    fd = scene["fd"](direction_vc=h * d) / h
    ad = float(np.dot(scene["plain"][1], d))
    assert abs(fd) > 1e-3, f"directional derivative too small to test: {fd}"
    assert ad == pytest.approx(fd, rel=0.01), f"dL/dv_c . d: autodiff {ad}, central FD {fd}"


def test_gradient_wrt_youngs_modulus_matches_finite_differences(scene):
    E0 = scene["E0"]
    h = 1e-5 * E0  # [Pa]
    fd = scene["fd"](dE=h) / h
    ad = float(scene["plain"][2])
    assert abs(fd) * E0 > 1e-4, f"dL/dlog(E) = {fd * E0} too small to test"
    assert ad == pytest.approx(fd, rel=0.01), f"dL/dE: autodiff {ad}, central FD {fd} [1/Pa]"


def test_checkpointed_rollout_gives_the_same_gradients(scene):
    segmented, _ = scene["grads"](SEGMENT)
    for name, a, b in zip(("v0", "collider velocity", "E"), scene["plain"], segmented,
                          strict=True):
        # identical up to float64 rounding (XLA may fuse the recomputed segments differently)
        np.testing.assert_allclose(b, a, rtol=1e-12, atol=1e-12 * np.abs(a).max(),
                                   err_msg=f"gradient wrt {name}: segment={SEGMENT} vs none")


def test_a_mixture_with_plastic_has_finite_gradients_that_match_finite_differences():
    """Dough, water and tofu particles interleaved in one grid, thrown at each other. The
    non-plastic particles cannot yield (sigma_y = inf): the return map's limit / s_norm
    was inf for them, and its unselected derivative made every particle's gradient NaN
    after one substep. The dough's yield stress is low enough that it flows here (a run
    with it raised to infinity ends elsewhere)."""
    with jax.enable_x64(True):
        f64 = jnp.float64
        dx = 1.0 / 12
        mats = (materials.dough(yield_stress=20.0), materials.water(),
                materials.tofu())
        cfg = mpm.MPMConfig(materials=mats, dx=dx, dt=1e-3, domain=(12, 12, 12),
                            walls="slip", max_speed=2.0)
        x, vol = sampling.box((0.35, 0.35, 0.35), (0.65, 0.65, 0.65), dx, ppc=4)
        ids = np.arange(len(x)) % 3
        rng = np.random.default_rng(3)
        v0 = jnp.asarray(rng.normal(0.0, 0.5, x.shape), f64)
        weights = jnp.asarray(rng.normal(size=x.shape), f64)
        state = mpm.init_state(cfg, x, mat=ids, vol=vol, dtype=f64)

        def final(v, params):
            return mpm.rollout(cfg, params, state.replace(v=v), 20).x

        params = mpm.MaterialParams.from_materials(mats, dtype=f64)
        rigid = mpm.MaterialParams.from_materials(
            (materials.dough(yield_stress=np.inf),) + mats[1:], dtype=f64)
        flowed = float(jnp.max(jnp.abs(final(v0, params) - final(v0, rigid))))
        assert flowed > 1e-6, f"the dough never yields here: |dx| {flowed} m"

        def loss(v):
            return jnp.mean(final(v, params) * weights)

        g = np.asarray(jax.jit(jax.grad(loss))(v0))
        bad = ~np.isfinite(g).all(1)
        assert not bad.any(), (
            f"{bad.sum()} of {len(g)} particles' gradients are not finite (by material: "
            f"{[int(bad[ids == k].sum()) for k in range(3)]})")
        d = rng.normal(size=x.shape)
        h = 1e-6  # [m/s] along a unit-variance direction
        fd = (float(loss(v0 + h * d)) - float(loss(v0 - h * d))) / (2 * h)
        ad = float(np.sum(g * d))
        # (the loss is a mean over 3 N terms: its derivative is ~1e-5 m per m/s)
        assert abs(fd) > 1e-6, f"directional derivative too small to test: {fd}"
        assert ad == pytest.approx(fd, rel=1e-3), f"dL/dv0 . d: autodiff {ad}, central FD {fd}"


def test_a_substep_keeps_only_its_input_and_the_named_intermediates_for_reverse_mode(capsys):
    """mpm.step's reverse pass stores the substep's input state and the intermediates named
    in mpm.REVERSE_SAVED, nothing else (it recomputes the rest): a fluid substep kept 4.2 MB
    of 8192 particles' intermediates before, and first-touching them cost a sixth of a
    gradient's time."""
    mats = (materials.water(), materials.tofu(), materials.dough())
    dx = 1.0 / 12
    cfg = mpm.MPMConfig(materials=mats, dx=dx, dt=1e-3, domain=(12, 12, 12), walls="slip")
    x, vol = sampling.box((0.35, 0.35, 0.35), (0.65, 0.65, 0.65), dx, ppc=4)
    state = mpm.init_state(cfg, x, mat=np.arange(len(x)) % 3, vol=vol)
    capsys.readouterr()
    print_saved_residuals(lambda s: mpm.step(cfg, cfg.params, s), state)
    lines = capsys.readouterr().out.strip().splitlines()  # "<shape> <where from>"
    named = {line.split("'")[1] for line in lines if " named '" in line}
    other = [line for line in lines if not any(
        k in line for k in (" named '", " from the argument ", " from a constant",
                            " from a literal"))]
    assert lines and not other, f"unnamed intermediates kept: {other}"
    assert named == set(mpm.REVERSE_SAVED), named
