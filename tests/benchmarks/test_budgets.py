"""The budget table (``benchmarks/budgets.py``) on a grid written for the test: the fifths
difference of each learning curve, its verdict against the evaluation SE and the curve's
own noise, and the budget read off the curve (env steps, updates, training wall time)."""

import math

import pytest

from benchmarks import budgets
from dax_algos.bench import learning
from dax_algos.bench.rows import append_row, make_row


def _grid(tmp_path, curves, scores):
    """``curves``: {(method, seed): [score per update]} on fold_cloth1 (12 env steps and 2
    s per update); ``scores``: {method: [evaluation score per seed]}."""
    for (method, seed), ys in curves.items():
        learning.append_curve(learning.learning_path(tmp_path, "fold_cloth1"), [
            dict(task="fold_cloth1", method=method, seed=seed, budget="full", update=u,
                 env_steps=12.0 * (u + 1), wall_s=2.0 * (u + 1), score=y)
            for u, y in enumerate(ys)])
    for method, values in scores.items():
        for seed, v in enumerate(values):
            append_row(tmp_path / "results.csv",
                       make_row("fold_cloth1", method, seed, "full", status="ok", score=v,
                                wall_s=5.0, untrained_score=0.3))
    return tmp_path


def test_each_curve_is_judged_by_its_last_fifth_against_the_evaluation_se(tmp_path):
    flat = [0.3] * 5 + [0.4] * 15                     # risen early, then flat: Δ = 0
    rising = [0.3 + 0.01 * u for u in range(20)]      # still rising: Δ = +0.04
    noisy_a = [0.4, 0.5] * 10                          # Δ = 0 on seed 0 ...
    noisy_b = [0.4] * 16 + [0.6] * 4                   # ... +0.2 on seed 1: Δ = 0.1 ± 0.1
    grid = _grid(tmp_path, {
        ("apg", 0): flat, ("apg", 1): flat,
        ("ild", 0): rising, ("ild", 1): [y + 0.01 for y in rising],
        ("shac", 0): noisy_a, ("shac", 1): noisy_b,
        ("ppo", 0): [0.4] * 6, ("ppo", 1): [0.4] * 6,
        ("transporter_rgb", 0): [float("nan")] * 12,  # (a curve with no score in it)
    }, {"apg": [0.40, 0.42], "ild": [0.50, 0.52], "shac": [0.40, 0.42], "ppo": [0.4, 0.41],
        "transporter": [0.6, 0.62], "transporter_rgb": [0.5], "random": [0.3, 0.3]})
    rows, budget, stale = budgets.curve_budgets(grid, include_stale=True)
    out = {r["method"]: r for r in rows}
    assert budget == "full" and "rows are stale" in stale and "random" not in out
    assert out["apg"]["verdict"] == "flat" and out["apg"]["delta"] == pytest.approx(0.0)
    assert out["ild"]["verdict"] == "rising"
    assert out["ild"]["delta"] == pytest.approx(0.04) and out["ild"]["eval_se"] < 0.04
    assert out["shac"]["verdict"] == "noisy"
    assert out["shac"]["delta"] == pytest.approx(0.1) and out["shac"]["delta_se"] == (
        pytest.approx(0.1))
    assert out["ppo"]["verdict"] == "too short" and math.isnan(out["ppo"]["delta"])
    # what reading PPO's curve would take: at this row's 12 env steps per update (fewer
    # than one per env of PPO's registry envs: a fraction of the updates end an episode)
    # 10 episode ends per env over the horizon, at its 2 s per update
    import dax_tasks
    from dax_algos import registry
    num_envs = registry.get("ppo").config("full", "fold_cloth1").num_envs
    updates = math.ceil(10 * dax_tasks.get_spec("fold_cloth1").horizon * num_envs / 12)
    steps = 12 * updates
    assert out["ppo"]["to_read"] == steps
    assert out["ppo"]["to_read_wall_s"] == pytest.approx(2.0 * updates)
    # an update longer than the episode ends one in every env: 10 updates read
    assert budgets.steps_to_read("fold_cloth1", "ppo", "full", 1000.0 * num_envs) == (
        10_000 * num_envs)
    assert out["apg"]["to_read"] is None and out["transporter"]["to_read"] is None
    assert out["transporter_rgb"]["to_read"] is None  # (trains without envs)
    assert out["transporter"]["verdict"] == "no curve"
    assert out["transporter_rgb"]["verdict"] == "no episode ended"
    assert out["transporter"]["wall_s"] == pytest.approx(5.0)
    assert (out["apg"]["env_steps"], out["apg"]["updates"], out["apg"]["wall_s"]) == (
        240, 20, 40.0)
    table = budgets.render_table(grid, include_stale=True)
    assert "| fold_cloth1 | ild | 2 | 240 | 20 | 40 | +0.040 ± 0.000 |" in table, table
    assert f"| too short | {steps:,} ({2.0 * updates:,.0f}) |" in table, table
    assert "rising" in table and "Seeds: the row's training seeds" in table


def test_a_grid_without_learner_rows_is_refused(tmp_path):
    _grid(tmp_path, {}, {"random": [0.3, 0.3]})
    with pytest.raises(ValueError, match="no learner rows"):
        budgets.render_table(tmp_path, include_stale=True)


def test_training_throughput_sets_each_learner_against_the_env_at_its_batch(tmp_path):
    import json

    grid = _grid(tmp_path, {("apg", 0): [0.3] * 20, ("ppo", 0): [0.3] * 20},
                 {"apg": [0.4], "ppo": [0.4]})
    doc = tmp_path / "throughput.json"
    doc.write_text(json.dumps({"bench": "throughput", "tasks": [{"task": "fold_cloth1", "rows": [
        {"batch": 1, "measured": True, "steps_per_s": 5.0, "grad_steps_per_s": 10.0},
        {"batch": 16, "measured": True, "steps_per_s": 50.0, "grad_steps_per_s": 40.0},
        {"batch": 64, "measured": False, "reason": "out of time"}]}]}))
    out = {r["method"]: r for r in budgets.training_throughput(grid, doc, include_stale=True)}
    # APG trains 4 envs through the gradient: the env's rate at 4 lies halfway between 1
    # and 16 in log-log (sqrt(10 * 40) = 20); training ran 240 steps in 40 s
    apg = out["apg"]
    assert (apg["batch"], apg["grad"]) == (4, True)
    assert apg["env_rate"] == pytest.approx(20.0) and apg["share"] == pytest.approx(0.3)
    # PPO's 64 envs: beyond the measured batches, the nearest one (16), forward
    assert out["ppo"]["grad"] is False and out["ppo"]["env_rate"] == pytest.approx(50.0)
    table = budgets.render_throughput(grid, doc, include_stale=True)
    assert "| fold_cloth1 | apg | 4 | 6.0 | 20.0 (grad) | 30 % |" in table, table


def test_a_budget_read_judges_its_curve_and_keeps_the_budget_unless_it_is_beaten(
        tmp_path):
    """A read (a variant changing only ``total_env_steps``, longer or shorter) is judged on
    its own curve and evaluation SE; the budget stays unless the read beats it by more than
    2 paired SE (then longer or shorter is better);
    variants that change anything else are not reads."""
    from benchmarks import ablate

    def rec(variant, seed, score, curve, changes):
        return {"method": "ppo", "task": "fold_cloth1", "budget": "full",
                "variant": variant, "changes": changes, "seed": seed, "status": "ok",
                "score": score, "untrained": 0.3, "env_steps_per_s": 5.0, "curve": curve}

    flat = [None, 0.3] + [0.4] * 18            # a None update (no episode ended) skipped
    rising = [0.3 + 0.01 * u for u in range(20)]
    records = []
    for seed, base in enumerate((0.40, 0.42, 0.44)):
        records += [rec("baseline", seed, base, [0.4] * 6, {}),
                    rec("to_read", seed, base + 0.001 * seed, flat,
                        {"total_env_steps": 1000}),
                    rec("steps_2000", seed, base + 0.10 + 0.001 * seed, rising,
                        {"total_env_steps": 2000}),
                    rec("half", seed, base + 0.05 + 0.001 * seed, [0.4] * 3,
                        {"total_env_steps": 250}),
                    rec("lr_low", seed, base, rising, {"learning_rate": 1e-4})]
    path = tmp_path / "read.jsonl"
    ablate.write(path, records)
    table = budgets.render_reads(path)
    assert "| fold_cloth1 | ppo | `to_read` | 6 → 20 | 1,000 | 3 | +0.000 ± 0.000 | " \
           "0.012 | flat | 0.420 → 0.421 | +0.001 ± 0.001 | stays |" in table, table
    assert "| `steps_2000` | 6 → 20 | 2,000 | 3 | +0.040 ± 0.000 | 0.012 | rising | " \
           "0.420 → 0.521 | +0.101 ± 0.001 | **longer is better** |" in table, table
    assert "| `half` | 6 → 3 | 250 | 3 | — | 0.012 | too short | 0.420 → 0.471 | " \
           "+0.051 ± 0.001 | **shorter is better** |" in table, table
    assert "lr_low" not in table
