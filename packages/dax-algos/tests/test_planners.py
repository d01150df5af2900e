"""The planners' pure cores and episodes: CEM beats random, gradient refinement helps on a
smooth landscape, contact adjustment gives gradients, clipping tames huge gradients."""

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from algos_helpers import ToyTask, cheap_cloth_overrides

import dax_algos
from dax_algos import actions
from dax_algos.planning import cem_mpc, diff_cem_mpc, diff_mpc, reference
from dax_algos.planning.planner import episode_env_steps, make_episode, make_objective


@pytest.fixture
def toy():
    return ToyTask()


@pytest.fixture(scope="module")
def cheap_fold():
    import dax_tasks

    return dax_tasks.make("fold_cloth1", cache_goal=False, **cheap_cloth_overrides())


def _scores(task, planner, seeds):
    episode = jax.jit(make_episode(task, planner))
    params = task.default_params
    return np.asarray([float(episode(jax.random.PRNGKey(s), params).score) for s in seeds])


def test_cem_mpc_beats_random_on_cheap_cloth(cheap_fold):
    seeds = (0, 1)
    cfg = dax_algos.CEMConfig(population=12, elites=3, iterations=2, horizon=1)
    cem = _scores(cheap_fold, cem_mpc.make_planner(cheap_fold, cfg), seeds)
    rnd = _scores(cheap_fold, reference.make_random(cheap_fold, reference.RandomConfig()),
                  seeds)
    assert cem.mean() > rnd.mean() + 0.1, (
        f"expected CEM-MPC to beat random by > 0.1, got CEM {cem} vs random {rnd}")


def test_diff_cem_mpc_not_worse_than_cem_mpc_on_smooth_landscape(toy):
    cem_cfg = dax_algos.CEMConfig(population=8, elites=2, iterations=1, horizon=2)
    both = dax_algos.DiffCEMConfig(cem=cem_cfg, diff=dax_algos.DiffMPCConfig(
        steps=20, learning_rate=0.05))
    seeds = range(4)
    cem = _scores(toy, cem_mpc.make_planner(toy, cem_cfg), seeds)
    dcem = _scores(toy, diff_cem_mpc.make_planner(toy, both), seeds)
    assert np.all(dcem >= cem - 1e-6), f"expected diff-CEM >= CEM per seed, got {dcem} vs {cem}"
    assert dcem.mean() > cem.mean() + 0.01, (
        f"expected gradient refinement to improve on a smooth landscape: {dcem} vs {cem}")


def test_cem_optimise_finds_the_optimum_of_a_quadratic():
    target = jnp.asarray([[0.3, -0.6]])
    cfg = dax_algos.CEMConfig(population=64, elites=8, iterations=8, horizon=1)
    z, v = cem_mpc.cem_optimise(lambda z: -jnp.sum((z - target) ** 2), jnp.zeros((1, 2)),
                                jax.random.PRNGKey(0), cfg)
    assert float(jnp.max(jnp.abs(z - target))) < 0.05, f"expected ~{target}, got {z}"
    assert float(v) == pytest.approx(-float(jnp.sum((z - target) ** 2)))


def _missing_pick(task):
    """A normalised action whose pick is at the corner of the action box, off the cloth."""
    z = jax.random.uniform(jax.random.PRNGKey(3), (1, task.spec.action_dim), minval=-1.0,
                           maxval=1.0)
    return z.at[0, :3].set(jnp.asarray([-1.0, -1.0, -1.0]))


@pytest.mark.parametrize("contact_adjustment", [False, True])
def test_diff_mpc_gradient_needs_contact_adjustment(contact_adjustment):
    import dax_tasks

    task = dax_tasks.make("fold_cloth1", cache_goal=False, **cheap_cloth_overrides(
        contact_adjustment=contact_adjustment))
    _, state = jax.jit(task.reset)(jax.random.PRNGKey(0))
    value = make_objective(task, "final")
    params = task.default_params
    z0 = _missing_pick(task)
    pick = actions.to_action(task, z0[0])[:2]
    assert float(jnp.min(jnp.linalg.norm(state.physics.x[:, :2] - pick, axis=1))) > 0.03
    cfg = dax_algos.DiffMPCConfig(steps=1, horizon=1)
    _, _, stats = jax.jit(lambda z: diff_mpc.gradient_refine(
        lambda zz: value(state, zz, params), z, cfg))(z0)
    norm = float(stats.grad_norm_max)
    if contact_adjustment:
        assert norm > 1e-4, f"expected a non-zero gradient with contact adjustment, got {norm}"
    else:
        assert norm == 0.0, f"expected an exactly zero gradient for a missed pick, got {norm}"


def test_gradient_clipping_keeps_a_huge_gradient_finite_and_bounded():
    g = jnp.full((3, 4), 1e15, jnp.float32)
    z = jnp.zeros((3, 4))
    clipped = diff_mpc.make_optimiser(dax_algos.DiffMPCConfig(
        optimiser="sgd", learning_rate=0.1, max_grad_norm=1.0))
    raw = diff_mpc.make_optimiser(dax_algos.DiffMPCConfig(
        optimiser="sgd", learning_rate=0.1, max_grad_norm=None))
    u_clip, _ = clipped.update(g, clipped.init(z), z)
    u_raw, _ = raw.update(g, raw.init(z), z)
    assert bool(jnp.all(jnp.isfinite(u_clip)))
    assert float(optax.tree.norm(u_clip)) == pytest.approx(0.1, rel=1e-4)
    assert float(optax.tree.norm(u_raw)) > 1e13
    # through the planner core: the huge raw norm is reported, the step stays bounded
    cfg = dax_algos.DiffMPCConfig(steps=1, optimiser="sgd", learning_rate=0.1)
    best, _, stats = diff_mpc.gradient_refine(lambda zz: 1e15 * jnp.sum(zz), z, cfg)
    assert float(stats.grad_norm_max) == pytest.approx(1e15 * np.sqrt(12), rel=1e-3)
    assert int(stats.nonfinite_grads) == 0
    assert bool(jnp.all(jnp.isfinite(best)))
    assert float(optax.tree.norm(best - z)) == pytest.approx(0.1, rel=1e-3)


def test_nan_gradient_is_counted_and_zero_nans_option_removes_it():
    def bad(z):
        return jnp.sum(jnp.sqrt(z - 2.0))  # NaN value and gradient inside the box

    z = jnp.zeros((1, 2))
    _, _, stats = diff_mpc.gradient_refine(bad, z, dax_algos.DiffMPCConfig(steps=3))
    assert int(stats.nonfinite_grads) == 3, stats
    _, _, stats = diff_mpc.gradient_refine(bad, z, dax_algos.DiffMPCConfig(
        steps=3, zero_nans=True))
    assert int(stats.nonfinite_grads) == 3  # still measured (raw norm) ...
    assert np.isinf(float(stats.grad_norm_max))


def test_configs_reject_bad_values():
    with pytest.raises(ValueError, match="elites"):
        dax_algos.CEMConfig(population=4, elites=5)
    with pytest.raises(ValueError, match="objective"):
        dax_algos.CEMConfig(objective="best")
    with pytest.raises(ValueError, match="optimiser"):
        dax_algos.DiffMPCConfig(optimiser="lbfgs")
    with pytest.raises(ValueError, match="learning_rate"):
        dax_algos.DiffMPCConfig(learning_rate=float("nan"))


def test_env_step_counts_include_planning_rollouts(toy):
    cfg = dax_algos.CEMConfig(population=8, elites=2, iterations=3, horizon=2)
    planner = cem_mpc.make_planner(toy, cfg)
    assert episode_env_steps(toy, planner) == (toy.horizon * (3 * 8 * 2 + 1), 0)
    d = diff_mpc.make_planner(toy, dax_algos.DiffMPCConfig(steps=5, horizon=2))
    assert episode_env_steps(toy, d) == (toy.horizon * (6 * 2 + 1), toy.horizon * 10)


def test_episode_is_deterministic_and_vmaps_over_seeds(toy):
    cfg = dax_algos.DiffCEMConfig(cem=dax_algos.CEMConfig(population=4, elites=2,
                                                          iterations=1, horizon=2),
                                  diff=dax_algos.DiffMPCConfig(steps=2))
    episode = make_episode(toy, diff_cem_mpc.make_planner(toy, cfg))
    keys = jnp.stack([jax.random.PRNGKey(s) for s in (0, 1, 0)])
    batched = jax.jit(jax.vmap(episode, in_axes=(0, None)))(keys, toy.default_params)
    np.testing.assert_array_equal(np.asarray(batched.actions[0]), np.asarray(batched.actions[2]))
    assert not np.allclose(np.asarray(batched.actions[0]), np.asarray(batched.actions[1]))
    single = jax.jit(episode)(keys[1], toy.default_params)
    np.testing.assert_allclose(np.asarray(single.score), np.asarray(batched.score[1]),
                               rtol=1e-5)
