"""The runner with the RL methods: seeds trained one by one, rows, learning curves
(CSV + chart), policy files that load for their task and are refused for another, and
resuming."""

import dataclasses

import jax
import numpy as np
import pytest
from algos_helpers import cheap_cloth_overrides

import dax_tasks
from dax_algos import method, mlp_policy, registry
from dax_algos.bench import execute, learning, trained
from dax_algos.bench.grid import run_grid

TASK = "fold_cloth1"
METHODS = "ppo,apg,shac"
TINY = {"ppo": dict(total_env_steps=48, num_envs=8, unroll_length=2, minibatches=2,
                    n_eval=2, policy_hidden=(16,), value_hidden=(16,)),
        "apg": dict(total_env_steps=8, num_envs=2, n_eval=2, policy_hidden=(16,)),
        "shac": dict(total_env_steps=8, num_envs=2, critic_minibatches=2, n_eval=2,
                     actor_hidden=(16,), critic_hidden=(16,), critic_iterations=2)}


def _run(out, seeds=2):
    return run_grid(TASK, METHODS, seeds=seeds, out=out, quick=True,
                          task_overrides={TASK: cheap_cloth_overrides(horizon=2)},
                          method_overrides=TINY, cache_goal=False, progress=False)


@pytest.fixture(scope="module")
def grid(tmp_path_factory):
    out = tmp_path_factory.mktemp("bench_rl")
    return out, _run(out)


def test_rl_rows_curves_and_charts(grid):
    out, rows = grid
    assert sorted((r["method"], r["seed"]) for r in rows) == sorted(
        (m, s) for m in METHODS.split(",") for s in ("0", "1"))
    for r in rows:
        assert r["status"] == "ok", r
        assert 0.0 <= float(r["score"]) <= 1.0
        if r["method"] == "ppo":
            assert int(r["backprop_steps"]) == 0
        else:
            assert int(r["backprop_steps"]) == 8 and 0 < float(r["grad_norm"]) < np.inf, r
    curves = learning.read_curves(learning.learning_path(out, TASK))
    runs = {(c["method"], c["seed"]) for c in curves}
    assert runs == {(m, s) for m in METHODS.split(",") for s in (0, 1)}
    ppo = sorted((c for c in curves if c["method"] == "ppo" and c["seed"] == 0),
                 key=lambda c: c["update"])
    assert [c["env_steps"] for c in ppo] == [16, 32, 48]
    assert (out / f"learning_{TASK}.png").stat().st_size > 1000
    md = (out / "results.md").read_text()
    assert "| ppo |" in md and "| ppo, untrained |" in md and "*untrained*" in md, md


def test_each_learner_row_scores_its_untrained_policy_on_the_same_starts(grid):
    """``untrained_score`` is the evaluation of the network at initialisation (drawn from
    ``fold_in(key, 2)``) on the trained policy's evaluation starts."""
    _, rows = grid
    env = dax_tasks.make(TASK, cache_goal=False, **cheap_cloth_overrides(horizon=2))
    m = registry.get("apg")
    config = m.config("quick", TASK, **TINY["apg"])
    lrn = m.learner
    evaluate = lrn.make_evaluate(env, config, lrn.make_act(env, config))
    key = jax.random.PRNGKey(1)
    want = evaluate(lrn.untrained(env, config, jax.random.fold_in(key, 2)),
                    jax.random.fold_in(key, 0), env.default_params).score
    (row,) = [r for r in rows if r["method"] == "apg" and r["seed"] == "1"]
    assert float(row["untrained_score"]) == pytest.approx(float(want), abs=1e-6)
    assert all(0.0 <= float(r["untrained_score"]) <= 1.0 for r in rows)


def test_seeds_differ(grid):
    _, rows = grid
    apg = [float(r["score"]) for r in rows if r["method"] == "apg"]
    curves = learning.read_curves(learning.learning_path(grid[0], TASK))
    a = [c["score"] for c in curves if c["method"] == "ppo" and c["seed"] == 0]
    b = [c["score"] for c in curves if c["method"] == "ppo" and c["seed"] == 1]
    assert len(apg) == 2 and a != b


def test_policy_file_reloads_and_is_refused_for_another_task(grid):
    out, _ = grid
    path = out / "policies" / TASK / "ppo" / "seed0.msgpack"
    env = dax_tasks.make(TASK, cache_goal=False, **cheap_cloth_overrides(horizon=2))
    act, policy = trained.load_trained(path, env, "ppo")
    obs, state = env.reset(jax.random.PRNGKey(0))
    z = act(policy, mlp_policy.features(obs, state.t, env.horizon))
    assert z.shape == (env.spec.action_dim,) and np.all(np.abs(np.asarray(z)) <= 1)
    other = dax_tasks.make(TASK, cache_goal=False, **cheap_cloth_overrides(horizon=3))
    with pytest.raises(ValueError, match="task_fingerprint"):
        trained.load_trained(path, other, "ppo")
    with pytest.raises(ValueError, match="method="):
        trained.load_trained(path, env, "apg")
    from dax_algos import registry
    cfg = registry.get("ppo").config("quick", TASK, **{**TINY["ppo"], "learning_rate": 0.1})
    with pytest.raises(ValueError, match="learning_rate"):
        trained.load_trained(path, env, "ppo", cfg)


def test_resume_runs_nothing_twice(grid, monkeypatch):
    out, rows = grid
    before = (out / "results.csv").read_text()
    curves_before = learning.learning_path(out, TASK).read_text()
    calls = []
    monkeypatch.setattr(execute, "learner_result", lambda *a, **k: calls.append(a[2]))
    again = _run(out)
    assert calls == [] and len(again) == len(rows)
    assert (out / "results.csv").read_text() == before
    assert learning.learning_path(out, TASK).read_text() == curves_before


def test_budgets_are_stated_in_env_steps():
    from dax_algos import registry

    env = dax_tasks.make(TASK, cache_goal=False, **cheap_cloth_overrides(horizon=2))
    for name in ("ppo", "apg", "shac"):
        m = registry.get(name)
        quick, full = m.config("quick", TASK), m.config("full", TASK)
        assert quick.total_env_steps < full.total_env_steps
        r = m.build(env, dataclasses.replace(quick))
        assert isinstance(r, method.LearnerRunnable)
        assert 0 < r.train_env_steps <= quick.total_env_steps
