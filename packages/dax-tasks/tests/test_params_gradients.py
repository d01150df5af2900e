"""Gradients of an episode's return with respect to material parameters, through a task,
against central finite differences (float32, in log-space, step 5 %): the rope's Young's
modulus (Whip-Rope), the cloth's stretch modulus (Fold-Cloth-1) and the water's viscosity
(Pour-Water). The params are data: the same compiled function serves every value.

The same compiled gradient also gives the return's gradient with respect to the actions,
which must be finite and non-zero (the gradient-based planners and learners need it).

Each setup is chosen so that the return depends smoothly and measurably on the parameter:
the rope is pulled along its length (its stretch sets where it ends up), the cloth is carried
over a frictionless table (with Coulomb stick-slip on the table the return is not smooth on
the scale of a finite difference), and the water is ten times more viscous than honey
(at water's 1 mPa s the effect on two 25 ms steps is below float32 resolution).
Measured agreement: rope 0.1 %, cloth 2 % (1 % step, no self-collision), water 0.03 %.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import dax_tasks

H = 0.05  # central-difference step in log(parameter)


def _return(env, with_param):
    """``R(actions, x)``: the summed reward of ``actions`` from the episode of
    ``PRNGKey(0)`` with the parameter set by ``with_param(params, x)``."""
    params = env.default_params
    _, start = jax.jit(env.reset)(jax.random.PRNGKey(0), params)

    def total(actions, x):
        p = with_param(params, x)

        def body(s, a):
            _, s, r, _, _ = env.step(s, a, p)
            return s, r

        return jnp.sum(jax.lax.scan(body, start, actions)[1])

    return total


def _check(total, actions, x0, rtol, what, h=H):
    value, (g_actions, grad) = jax.jit(jax.value_and_grad(total, argnums=(0, 1)))(
        actions, x0)
    assert np.isfinite(float(value)) and np.isfinite(float(grad)), (value, grad)
    assert bool(jnp.all(jnp.isfinite(g_actions))), f"non-finite action gradient {g_actions}"
    assert float(jnp.max(jnp.abs(g_actions))) > 0.0, f"zero action gradient {g_actions}"
    f = jax.jit(total)
    fd = (float(f(actions, x0 + h)) - float(f(actions, x0 - h))) / (2 * h)
    # the difference of the two returns must span many float32 ulps of the return
    ulps = abs(fd) * 2 * h / (np.finfo(np.float32).eps * abs(float(value)))
    assert ulps > 50, (f"{what}: the return hardly depends on it (the central difference "
                       f"spans {ulps:.0f} ulps); the test would prove nothing")
    assert float(grad) == pytest.approx(fd, rel=rtol), (
        f"d return / d log({what}): autodiff {float(grad):.6g}, central FD {fd:.6g}")


def test_gradients_wrt_the_ropes_youngs_modulus_and_the_actions():
    from dax_tasks.tasks import whip_rope as wr
    scene = dataclasses.replace(wr.WHIP_ROPE.scene, throw=((0, 8, -0.015, 0.0, 0.005),))
    env = dax_tasks.make("whip_rope", substeps=8, horizon=8, scene=scene, cache_goal=False)
    pull = jnp.asarray([[-0.75, 0.0, 0.0]] * 6)  # along the rope, away from it

    def with_e(params, log_e):
        return params.replace(physics=params.physics.with_youngs_modulus(
            0, jnp.exp(log_e), wr.ROPE.poisson_ratio))

    _check(_return(env, with_e), pull, float(np.log(wr.ROPE.youngs_modulus)), 0.01,
           "Young's modulus")


def test_gradients_wrt_the_cloths_stretch_modulus_and_the_actions():
    """Without table friction and self-collision: both switch on and off within the
    central difference's step (contact onset), and the autodiff slope of such a switch says
    little about the return a step away (with self-collision on: autodiff -0.099, central
    FD -0.081, -0.062, -0.050 at steps 5 %, 1 %, 0.3 %). Step 1 %: the return aligns the
    goal to the cloth, which curves it in log(stretch) (FD 0.0563 at 5 %, 0.0438 at 1 %;
    autodiff 0.0447)."""
    spec = dax_tasks.get_spec("fold_cloth1")
    env = dax_tasks.make("fold_cloth1", cache_goal=False,
                         scene=dataclasses.replace(spec.scene, thickness=0.0))
    params = env.default_params
    _, start = jax.jit(env.reset)(jax.random.PRNGKey(0), params)
    fold = jax.jit(env.expert_action)(start, params)[None]

    def with_stretch(params, log_k):
        return params.replace(physics=params.physics.replace(
            stretch=jnp.exp(log_k), friction_static=0.0, friction_dynamic=0.0))

    _check(_return(env, with_stretch), fold, float(np.log(10.0)), 0.05, "stretch", h=0.01)


def test_gradients_wrt_the_fluids_viscosity_and_the_actions():
    env = dax_tasks.make("pour_water", cache_goal=False)
    tilt = jnp.asarray([[0.2, 0.0, 0.0, 3.0]] * 3)  # move towards the target and tilt

    def with_viscosity(params, log_eta):
        material = params.physics
        return params.replace(physics=material.replace(
            viscosity=material.viscosity.at[0].set(jnp.exp(log_eta))))

    _check(_return(env, with_viscosity), tilt, float(np.log(1.0)), 0.01, "viscosity")
