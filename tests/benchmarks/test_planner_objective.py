"""``benchmarks/planner_objective.py``: the grid's planner episode re-run with its per-step
record, and diff-CEM-MPC's first plan never worse than CEM-MPC's by the planning objective
(the same state and the same CEM keys: the refinement keeps CEM's plan unless it beats it)."""

import dataclasses
import json

import pytest

import dax_tasks
from benchmarks import planner_objective

TASK = "fold_cloth1"


@pytest.fixture(scope="module")
def env():
    spec = dax_tasks.get_spec(TASK)
    scene = dataclasses.replace(spec.scene, n=6, settle_substeps=200, thickness=0.0)
    return dax_tasks.make(TASK, scene=scene, substeps=400, horizon=2, cache_goal=False)


@pytest.fixture(scope="module")
def records(env):
    out = {}
    for method in planner_objective.METHODS:
        compiled = None
        for seed in (0, 1):
            out[(method, seed)], compiled = planner_objective.measure(
                env, TASK, method, seed, "quick", compiled=compiled)
    return out


def test_a_record_holds_the_episode_step_by_step(records, env):
    for rec in records.values():
        assert len(rec["objective"]) == len(rec["reward"]) == len(rec["r_gt"]) == env.horizon
        assert rec["score"] == pytest.approx(rec["r_gt"][-1], abs=1e-7)
        assert rec["reward_mean"] == pytest.approx(sum(rec["reward"]) / env.horizon)
        assert all(0.0 <= r <= 1.0 for r in rec["r_gt"])


def test_diff_cem_plans_at_least_as_well_as_cem_from_the_same_first_state(records):
    for seed in (0, 1):
        cem = records[("cem_mpc", seed)]["objective"][0]
        diff = records[("diff_cem_mpc", seed)]["objective"][0]
        assert diff >= cem, (seed, cem, diff)


def test_same_seed_same_record_and_the_table_pairs_by_seed(records, env, tmp_path):
    again, _ = planner_objective.measure(env, TASK, "cem_mpc", 1, "quick")
    for k in ("score", "objective", "reward", "r_gt"):
        assert again[k] == records[("cem_mpc", 1)][k]
    path = tmp_path / "2026-01-01-planner-objective.jsonl"
    path.write_text("".join(json.dumps(r) + "\n" for r in records.values()))
    table = planner_objective.render_table(path)
    assert "| fold_cloth1 | diff_cem_mpc | 2 |" in table
    assert "diff_cem_mpc − cem_mpc (2 seeds): score" in table
