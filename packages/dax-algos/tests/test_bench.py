"""The benchmark runner: files, failure recording, resuming, name errors, the CLI."""

import csv
import sys

import pytest
from algos_helpers import cheap_cloth_overrides, register_nan_planner

from dax_algos import method, registry
from dax_algos.bench import execute, runner
from dax_algos.bench.grid import resolve_methods, resolve_tasks, run_grid
from dax_algos.bench.rows import COLUMNS, append_row, read_rows

TASK = "fold_cloth1"
METHODS = "random,expert,nan_actions,cem_mpc,diff_mpc"


def _run(out, seeds=2, **kw):
    return run_grid(
        TASK, METHODS, seeds=seeds, out=out, quick=True,
        task_overrides={TASK: cheap_cloth_overrides(horizon=2)},
        method_overrides={"cem_mpc": dict(population=6, elites=2, iterations=1),
                          "diff_mpc": dict(steps=2)},
        cache_goal=False, progress=False, **kw)


@pytest.fixture(scope="module")
def grid(tmp_path_factory):
    register_nan_planner()
    out = tmp_path_factory.mktemp("bench")
    try:
        yield out, _run(out)
    finally:
        registry.unregister("nan_actions")


def test_runner_writes_csv_markdown_and_charts(grid):
    out, rows = grid
    with open(out / "results.csv") as f:
        header = next(csv.reader(f))
    assert tuple(header) == COLUMNS
    assert len(rows) == 10, rows
    md = (out / "results.md").read_text()
    assert f"| method | {TASK} |" in md, md
    for m in ("random", "expert", "cem_mpc", "diff_mpc"):
        assert f"| {m} | " in md and "±" in md, md
    assert "final" in md  # the score definition is stated
    assert "Seeds 0-1. Budget: quick." in md, md
    assert (out / f"chart_{TASK}.png").stat().st_size > 1000


def test_failed_run_is_recorded_and_the_grid_continues(grid):
    _, rows = grid
    nan_rows = [r for r in rows if r["method"] == "nan_actions"]
    assert [r["status"] for r in nan_rows] == ["failed", "failed"], nan_rows
    assert all("non-finite" in r["error"] for r in nan_rows), nan_rows
    later = [r for r in rows if r["method"] in ("cem_mpc", "diff_mpc")]
    assert len(later) == 4 and all(r["status"] == "ok" for r in later), later


def test_expert_reference_row_beats_random(grid):
    _, rows = grid
    score = {m: [float(r["score"]) for r in rows if r["method"] == m and r["status"] == "ok"]
             for m in ("random", "expert")}
    assert len(score["expert"]) == 2 and min(score["expert"]) > max(score["random"]), score


def test_cem_rows_count_planning_rollouts_and_diff_rows_report_gradient_norms(grid):
    _, rows = grid
    cem = [r for r in rows if r["method"] == "cem_mpc"]
    assert all(int(r["env_steps"]) == 2 * (6 * 1 * 1 + 1) for r in cem), cem
    diff = [r for r in rows if r["method"] == "diff_mpc"]
    for r in diff:
        g = float(r["grad_norm"])
        assert 0.0 < g < float("inf"), r
        assert int(r["nonfinite_grads"]) == 0 and int(r["backprop_steps"]) == 2 * 2, r
    for r in rows:
        assert 0.0 <= float(r["score"]) <= 1.0 or r["status"] == "failed", r


def test_second_invocation_skips_finished_rows(grid, monkeypatch):
    out, rows = grid
    before = (out / "results.csv").read_text()
    calls = []
    original = execute.run_method
    monkeypatch.setattr(execute, "run_method",
                        lambda *a, **k: calls.append((a[2], list(a[3])))
                        or original(a[0], a[1], a[2], iter(calls[-1][1]), *a[4:], **k))
    register_nan_planner(overwrite=True)
    again = _run(out, retry_failed=False)  # the failed nan_actions rows too
    assert calls == [] and len(again) == len(rows)
    assert (out / "results.csv").read_text() == before
    # one more seed: only seed 2 of each method runs, appended after the old rows
    more = _run(out, seeds=3, retry_failed=False)
    assert sorted(calls) == sorted((m, [2]) for m in METHODS.split(","))
    assert len(more) == 15 and (out / "results.csv").read_text().startswith(before)


def test_incomplete_last_line_is_dropped(tmp_path):
    path = tmp_path / "results.csv"
    append_row(path, {"task": TASK, "method": "random", "seed": 0, "budget": "quick",
                            "status": "ok", "score": 0.5})
    with open(path, "a") as f:
        f.write("fold_cloth1,random,1,qu")  # an interrupted write
    rows = read_rows(path)
    assert [r["seed"] for r in rows] == ["0"]
    assert path.read_text().endswith("\n")


def test_unknown_names_raise_value_error_listing_valid_ones():
    with pytest.raises(ValueError, match="unknown task 'nope'.*push_rope"):
        resolve_tasks("push_rope,nope")
    with pytest.raises(ValueError, match="unknown method 'nope'.*cem_mpc"):
        resolve_methods("cem_mpc,nope")
    with pytest.raises(ValueError, match="seeds"):
        run_grid(TASK, "random", seeds=0)


def test_cli_unknown_name_is_a_one_line_error_with_exit_2(tmp_path, capsys):
    assert runner.main(["run", "--tasks", "nope", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("dax-bench: error: unknown task") and "\n" not in err, err
    assert runner.main(["run", "--methods", "all,nope", "--out", str(tmp_path)]) == 2
    assert not (tmp_path / "results.csv").exists()


def test_backend_ray_without_ray_is_a_one_line_error_with_exit_2(tmp_path, capsys,
                                                                  monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray raises ImportError
    assert runner.main(["run", "--tasks", TASK, "--methods", "random", "--backend", "ray",
                       "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("dax-bench: error: --backend ray needs Ray") and "\n" not in err
    assert "pip install 'dax-algos[ray]'" in err, err
    assert runner.main(["run", "--tasks", TASK, "--methods", "random", "--ray-address", "auto",
                       "--out", str(tmp_path)]) == 2  # an address, but the local backend
    assert "--ray-address is for --backend ray" in capsys.readouterr().err
    assert not (tmp_path / "results.csv").exists()


def test_budgets_quick_smaller_than_full_and_heavier_tasks_smaller_still():
    cem = registry.get("cem_mpc")
    full, quick = cem.config("full", TASK), cem.config("quick", TASK)
    heavy = cem.config("quick", "push_rope")
    cost = [c.population * c.iterations * c.horizon for c in (full, quick, heavy)]
    assert cost[0] > cost[1] > cost[2], cost
    nested = registry.get("diff_cem_mpc").config("quick", TASK, diff={"steps": 7})
    assert nested.diff.steps == 7 and nested.cem.population == quick.population
    with pytest.raises(ValueError, match="unknown CEMConfig option"):
        cem.config("quick", TASK, populaton=3)
    # the full planners on the MPM tasks are their own, smaller budget
    assert cem.config("full", "whip_rope").population < full.population


def test_a_budget_of_one_task_comes_before_the_heavy_and_the_general_one():
    m = method.LearnerMethod(
        name="probe", family="rl", config_cls=registry.get("ppo").config_cls,
        learner=registry.get("ppo").learner,
        budgets={"full": dict(num_envs=4), "full_heavy": dict(num_envs=8),
                 "full@whip_rope": dict(num_envs=16)})
    assert m.config("full", "fold_cloth1").num_envs == 4
    assert m.config("full", "pour_water").num_envs == 8
    assert m.config("full", "whip_rope").num_envs == 16
    assert m.config("quick", "whip_rope").num_envs == m.config_cls().num_envs
    assert m.config("full", "whip_rope", num_envs=32).num_envs == 32  # overrides still win
