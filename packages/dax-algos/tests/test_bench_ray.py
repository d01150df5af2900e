"""``--backend ray``: the grid run as one Ray task per (task, method, seed) on a local Ray
instance gives the rows, recordings, curves and policies of the local backend (only the
timings differ), resumes without running a finished row again, and keeps every row
recorded before the driver was killed. Needs Ray (``pip install 'dax-algos[ray]'``; the
``ray`` nox session); the error without it is tested in test_bench.py."""

import csv

import numpy as np
import pytest
from algos_helpers import cheap_cloth_overrides

from dax_algos.bench import backends, episodes, grid, learning, policy_io
from dax_algos.bench.rows import COLUMNS

ray = pytest.importorskip("ray", reason="needs Ray: pip install 'dax-algos[ray]' "
                                        "(nox -s ray runs these tests)")

TASK = "fold_cloth1"
METHODS = "random,ppo"  # a planner and a learner
PPO = dict(total_env_steps=48, num_envs=8, unroll_length=2, minibatches=2, n_eval=2,
           policy_hidden=(16,), value_hidden=(16,))
#: the columns that are measured, not computed: they may differ between any two runs
TIMINGS = ("wall_s", "compile_s")


def _run(out, backend, seeds=2):
    return grid.run_grid(TASK, METHODS, seeds=seeds, out=out, quick=True,
                          task_overrides={TASK: cheap_cloth_overrides(horizon=2)},
                          method_overrides={"ppo": PPO}, cache_goal=False, progress=False,
                          backend=backend)


def _by_run(rows):
    return {(r["task"], r["method"], r["seed"], r["budget"]): r for r in rows}


@pytest.fixture(scope="module")
def ray_instance():
    ray.init(num_cpus=2, include_dashboard=False)
    try:
        yield
    finally:
        ray.shutdown()


@pytest.fixture(scope="module")
def grids(ray_instance, tmp_path_factory):
    local, remote = tmp_path_factory.mktemp("local"), tmp_path_factory.mktemp("ray")
    return (local, _run(local, "local")), (remote, _run(remote, "ray"))


def test_ray_rows_equal_local_rows_but_for_timings(grids):
    (_, local), (_, remote) = grids
    assert len(local) == len(remote) == 4
    local, remote = _by_run(local), _by_run(remote)
    assert local.keys() == remote.keys()
    for key, row in local.items():
        assert row["status"] == "ok", row
        for col in COLUMNS:
            if col not in TIMINGS:
                assert remote[key][col] == row[col], (key, col, row[col], remote[key][col])
        assert float(remote[key]["wall_s"]) > 0 and float(remote[key]["compile_s"]) > 0


def test_ray_recordings_curves_policies_and_page_equal_local(grids):
    (local, _), (remote, _) = grids
    for m in METHODS.split(","):
        for s in (0, 1):
            a = episodes.load_episode(episodes.episode_path(local, TASK, m, s))
            b = episodes.load_episode(episodes.episode_path(remote, TASK, m, s))
            np.testing.assert_array_equal(a.actions, b.actions)
            np.testing.assert_array_equal(a.reset_key, b.reset_key)
            assert a.score == b.score
    for s in (0, 1):
        path = f"policies/{TASK}/ppo/seed{s}.msgpack"
        (pa, ma), (pb, mb) = (policy_io.load_policy(d / path) for d in (local, remote))
        assert ma == mb
        for x, y in zip(_leaves(pa), _leaves(pb), strict=True):
            np.testing.assert_array_equal(x, y)

    def curves(out):
        return sorted((c["method"], c["seed"], c["update"], c["env_steps"], c["score"])
                      for c in learning.read_curves(learning.learning_path(out, TASK)))

    assert curves(local) == curves(remote) and curves(local)
    for out in (local, remote):
        assert (out / "index.html").stat().st_size > 1000
        assert (out / "results.md").is_file()


def _leaves(tree):
    if isinstance(tree, dict):
        return [x for k in sorted(tree) for x in _leaves(tree[k])]
    return [np.asarray(tree)]


def test_ray_resume_runs_only_the_missing_seeds(grids, monkeypatch):
    _, (out, rows) = grids
    before = (out / "results.csv").read_text()
    todos = []
    original = backends.run_ray
    monkeypatch.setattr(backends, "run_ray",  # the runs are enumerated lazily: list them
                        lambda todo, *a, **k: todos.append(list(todo))
                        or original(iter(todos[-1]), *a, **k))
    again = _run(out, "ray")
    assert todos == [[]] and (out / "results.csv").read_text() == before
    assert _by_run(again).keys() == _by_run(rows).keys()
    more = _run(out, "ray", seeds=3)
    assert todos[1] == [(TASK, m, 2) for m in METHODS.split(",")]
    assert len(more) == 6 and (out / "results.csv").read_text().startswith(before)


def test_killed_ray_driver_keeps_finished_rows_and_resumes(grids, tmp_path, monkeypatch):
    (_, local), _ = grids
    recorded = []
    original = grid.record

    def record_then_die(out, result):  # the driver is killed after its second row
        original(out, result)
        recorded.append(result.row)
        if len(recorded) == 2:
            raise KeyboardInterrupt

    monkeypatch.setattr(grid, "record", record_then_die)
    with pytest.raises(KeyboardInterrupt):
        _run(tmp_path, "ray")
    with open(tmp_path / "results.csv") as f:
        kept = list(csv.DictReader(f))
    assert len(kept) == 2
    monkeypatch.setattr(grid, "record", original)
    rows = _run(tmp_path, "ray")  # the lock was released; the rest runs
    assert _by_run(rows).keys() == _by_run(local).keys()
    assert rows[:2] == kept
