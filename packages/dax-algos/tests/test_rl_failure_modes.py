"""Failure modes of the gradient-based RL methods that the literature reports, pinned:

* a policy whose picks miss the cloth gets an *exactly* zero simulator gradient when the
  task's contact adjustment is off (with it on, the same action has a gradient);
* on a long low-level task (Whip-Rope) the gradient of the return grows with the
  backpropagation horizon, and so does the first action's share of it.
"""


import jax
import jax.numpy as jnp
import numpy as np
import pytest
from algos_helpers import cheap_cloth_overrides

import dax_tasks
from dax_algos import actions, mlp_policy
from dax_algos.rl import apg, training
from dax_tasks.core.wrappers import training_env


def _missing_pick(env, points):
    """An action picking 1 cm inside the corner of the action box that is farthest from
    every one of ``points`` (the cloth lies anywhere on the table at any heading)."""
    lo, hi = np.asarray(env.spec.action_low), np.asarray(env.spec.action_high)
    mid = 0.5 * (lo + hi)
    xy = np.asarray(points).reshape(-1, 3)[:, :2]
    corners = [(x, y) for x in (lo[0] + 0.01, hi[0] - 0.01) for y in (lo[1] + 0.01, hi[1] - 0.01)]
    far = max(corners, key=lambda c: np.min(np.linalg.norm(xy - np.asarray(c), axis=1)))
    return jnp.asarray([*far, *mid[2:]], jnp.float32)


@pytest.fixture(scope="module", params=[False, True], ids=["no_adjustment", "adjustment"])
def cloth(request):
    return dax_tasks.make("fold_cloth1", cache_goal=False,
                          **cheap_cloth_overrides(horizon=2, contact_adjustment=request.param))


def test_missed_pick_has_exactly_zero_simulator_gradient(cloth):
    _, state = cloth.reset(jax.random.PRNGKey(0))
    pts = np.asarray(cloth.object_points(state.physics))
    action = _missing_pick(cloth, pts)
    gap = float(np.min(np.linalg.norm(pts[:, :2] - np.asarray(action[:2]), axis=1)))
    assert gap > 0.05, f"the pick is only {gap:.3f} m from the cloth"
    grad = np.asarray(jax.jit(jax.grad(
        lambda a: cloth.step(state, a)[4]["r_gt"]))(action))
    if cloth.spec.contact_adjustment:
        assert np.linalg.norm(grad) > 1e-3, grad  # the pick is moved onto the cloth
    else:
        assert np.all(grad == 0.0), grad


def test_apg_policy_gradient_is_exactly_zero_when_its_picks_miss(cloth):
    if cloth.spec.contact_adjustment:
        pytest.skip("the failure needs contact adjustment off")
    config = apg.APGConfig(num_envs=2, policy_hidden=(16,), aux_weight=0.0)
    pnet = apg.network(cloth, config)
    policy = pnet.init(jax.random.PRNGKey(0))
    venv = training_env(cloth, config.num_envs)
    rollout = apg.make_rollout(cloth, venv, pnet, config, cloth.horizon)
    params = training.training_params(cloth.default_params, config.aux_weight)
    obs, state = venv.reset(jax.random.PRNGKey(1), params)
    # bias the output layer so that the policy's action is a pick that misses both cloths
    z = actions.to_normalised(cloth, _missing_pick(cloth, state.physics.x))
    last = policy["mean"]["layers"][len(config.policy_hidden)]
    last["bias"][...] = jnp.arctanh(jnp.clip(z, -0.999, 0.999))
    norm = mlp_policy.ObsNorm.create(mlp_policy.feature_dim(cloth))
    grads = jax.jit(jax.grad(lambda p: rollout(p, norm, obs, state, jax.random.PRNGKey(2),
                                               params)[0]))(policy)
    leaves = jax.tree_util.tree_leaves(grads)
    assert all(np.all(np.asarray(g) == 0.0) for g in leaves)
    # the auxiliary (contact) reward is what gives such a policy a gradient
    params_aux = training.training_params(cloth.default_params, 1.0)
    grads_aux = jax.jit(jax.grad(lambda p: rollout(p, norm, obs, state, jax.random.PRNGKey(2),
                                                   params_aux)[0]))(policy)
    assert max(float(jnp.max(jnp.abs(g))) for g in jax.tree_util.tree_leaves(grads_aux)) > 0


def test_whip_gradient_grows_with_the_backpropagation_horizon():
    env = dax_tasks.make("whip_rope", substeps=8, horizon=16, cache_goal=False)
    _, start = env.reset(jax.random.PRNGKey(0))
    t = jnp.arange(env.horizon)
    actions = 0.5 * jnp.stack([jnp.sin(t / 3.0), jnp.cos(t / 4.0), 0.3 * jnp.sin(t / 5.0)],
                              -1).astype(jnp.float32)

    def rewards(a):
        def body(s, a):
            _, s, _, _, info = env.step(s, a)
            return s, info["r_gt"]

        return jax.lax.scan(body, start, a)[1]

    @jax.jit
    def window_gradient(a, mask):  # d(sum of the first h rewards)/d(actions), one compile
        return jax.vjp(rewards, a)[1](mask)[0]

    norms, first = [], []
    for h in (1, 4, 16):
        g = np.asarray(window_gradient(actions, (t < h).astype(jnp.float32)))
        assert np.all(np.isfinite(g))
        norms.append(np.linalg.norm(g))
        first.append(np.linalg.norm(g[0]))
    assert norms[0] < norms[1] < norms[2] and norms[2] > 20 * norms[0], norms
    assert first[0] < first[1] < first[2] and first[2] > 10 * first[0], first
