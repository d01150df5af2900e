"""The runner under faults and odd input (issue 37): failed runs retried on resume with
their history kept, names checked before they become paths, every results row validated
on read, seeds bounded and enumerated lazily, the precision recorded and a resume across
precisions refused, results.md escaping what it copies, a failed run failing the command,
and a time-bounded grid that resumes."""

import functools
import json
import re

import pytest
from algos_helpers import cheap_cloth_overrides, register_nan_planner

from dax_algos import registry
from dax_algos.bench import episodes, grid, provenance, rundir, runner
from dax_algos.bench.grid import Plan, run_grid
from dax_algos.bench.rows import (
    COLUMNS,
    OLD_COLUMNS,
    PROVENANCE_COLUMNS,
    UNTRAINED_COLUMNS,
    append_row,
    latest,
    make_row,
    read_rows,
    upgrade,
)

TASK = "fold_cloth1"


def _run(out, methods="random", seeds=2, **kw):
    return run_grid(TASK, methods, seeds=seeds, out=out, quick=True,
                    task_overrides={TASK: cheap_cloth_overrides(horizon=2)},
                    cache_goal=False, progress=False, **kw)


def _cli(capsys, *argv):
    code = runner.main([*argv])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def _row(**values):
    base = dict(task=TASK, method="random", seed=0, budget="quick", status="ok", score=0.5,
                wall_s=1.0, compile_s=1.0, env_steps=2, backprop_steps=0)
    return make_row(**{**base, **values})


def _raise(err):
    def fail(*a, **k):
        raise err

    return fail


def _write(path, rows, header=COLUMNS):
    path.write_text(",".join(header) + "\n")
    for r in rows:
        append_row(path, r)


# ----------------------------------------------------------------------- retried on resume

def test_failed_runs_are_retried_on_resume_with_their_errors_kept(tmp_path, monkeypatch):
    """A transient fault (the disk full while recording) fails the rows; the next run of the
    same grid runs them again, keeps the error in the new rows' history and the failed
    rows in the file, where they no longer count."""
    with monkeypatch.context() as m:
        m.setattr(episodes, "save_episode", _raise(OSError(28, "No space left on device")))
        first = _run(tmp_path)
    assert [r["status"] for r in first] == ["failed", "failed"], first
    assert all("No space left on device" in r["error"] for r in first)
    again = _run(tmp_path)
    assert [r["status"] for r in again] == ["ok", "ok"], again
    for r in again:
        assert json.loads(r["previous_errors"]) == [first[0]["error"]], r
    log = read_rows(tmp_path / "results.csv")
    assert [r["status"] for r in log] == ["failed", "failed", "ok", "ok"]
    assert latest(log) == list(again)
    md = (tmp_path / "results.md").read_text()
    assert "Failed runs" not in md and re.search(r"\| random \| [0-9.]+ ± [0-9.]+ \|", md), md


def test_no_retry_failed_leaves_failed_runs_alone(tmp_path, monkeypatch):
    with monkeypatch.context() as m:
        m.setattr(episodes, "save_episode", _raise(OSError(30, "Read-only file system")))
        _run(tmp_path, seeds=1)
    rows = _run(tmp_path, seeds=1, retry_failed=False)
    assert [r["status"] for r in rows] == ["failed"]
    assert len(read_rows(tmp_path / "results.csv")) == 1


# ----------------------------------------------------------------------- names and paths

def test_a_task_name_that_leaves_out_is_refused_before_any_file_is_written(tmp_path,
                                                                          capsys):
    out = tmp_path / "out"
    out.mkdir()
    _write(out / "results.csv", [_row(task="../../escaped")])
    code, _, err = _cli(capsys, "report", "--out", str(out))
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert f"{out / 'results.csv'}, line 2: task name '../../escaped' is not allowed" in err
    assert [p.name for p in tmp_path.iterdir()] == ["out"]
    assert {p.name for p in out.iterdir()} <= {".results.csv.lock", "results.csv"}
    with pytest.raises(ValueError, match="task name '../x' is not allowed"):
        episodes.episode_path(out, "../x", "random", 0)
    with pytest.raises(ValueError, match="method name 'a/b' is not allowed"):
        grid.resolve_methods("a/b")


# ----------------------------------------------------------------------- rows validated on read

@pytest.mark.parametrize("lines, problem", [
    (lambda: [_row(score=5.0)], "line 2: score '5.0' is not in [0, 1]"),
    (lambda: [_row(score="notanumber")], "line 2: score 'notanumber' is not a number"),
    (lambda: [_row(), _row(seed=1, status="great")], "line 3: status 'great' is not one of"),
    (lambda: [_row(), _row(seed=1), _row()], "line 4: a second row for fold_cloth1 / random "
                                              "/ seed 0 / quick (line 2)"),
    (lambda: [_row(wall_s=-1.0)], "line 2: wall_s '-1.0' is not a time >= 0"),
    (lambda: [_row(budget="huge")], "line 2: budget 'huge' is not one of"),
])
def test_an_invalid_row_is_exit_2_naming_the_file_and_line(tmp_path, capsys, lines, problem):
    _write(tmp_path / "results.csv", lines())
    code, _, err = _cli(capsys, "report", "--out", str(tmp_path))
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert f"dax-bench: error: {tmp_path / 'results.csv'}, {problem}" in err, err


def test_a_truncated_row_inside_the_file_is_exit_2_an_unfinished_last_line_is_not(tmp_path,
                                                                                   capsys):
    path = tmp_path / "results.csv"
    _write(path, [_row(), _row(seed=1)])
    text = path.read_text().splitlines()
    path.write_text("\n".join([text[0], text[1][:30], text[2]]) + "\n")
    code, _, err = _cli(capsys, "report", "--out", str(tmp_path))
    assert code == 2 and f"{path}, line 2: " in err and "truncated" in err, err
    _write(path, [_row()])
    with open(path, "a") as f:
        f.write("fold_cloth1,random,1,qu")  # a killed writer's half line: dropped
    assert len(read_rows(path)) == 1


def test_a_retry_row_is_valid_only_after_a_failed_row(tmp_path):
    path = tmp_path / "results.csv"
    _write(path, [_row(status="failed", score="", error="E: boom"),
                  _row(previous_errors=json.dumps(["E: boom"]))])
    assert [r["status"] for r in latest(read_rows(path))] == ["ok"]
    _write(path, [_row(status="failed", score="", error="E: boom"), _row()])
    with pytest.raises(ValueError, match="line 3: a second row"):
        read_rows(path)


def test_a_second_row_measured_on_other_code_or_config_is_valid_and_counts(tmp_path):
    """``--rerun-stale`` appends the run again beside its stale row: valid when the two
    rows' task fingerprints or config digests differ, and the new one counts."""
    path = tmp_path / "results.csv"
    old = dict(task_fingerprint="aaaaaaaaaaaa", config_digest="cccccccccccc")
    _write(path, [_row(score=0.2, **old),
                  _row(score=0.7, **{**old, "task_fingerprint": "bbbbbbbbbbbb"})])
    assert [float(r["score"]) for r in latest(read_rows(path))] == [0.7]
    _write(path, [_row(score=0.2, **old), _row(score=0.7, **old)])
    with pytest.raises(ValueError, match="line 3: a second row"):
        read_rows(path)


# ----------------------------------------------------------------------- seeds bounded, lazily

def test_seeds_are_a_count_or_a_range():
    assert grid.parse_seeds("5") == range(5) and grid.parse_seeds("3-4") == range(3, 5)
    assert grid.seeds_text(range(3, 5)) == "3-4" and grid.seeds_text(5) == "5"
    assert grid.seeds_text(grid.parse_seeds("2-2")) == "2-2"
    for bad in ("4-2", "a", "-1", "0", "1-x", str(2**32) + "-" + str(2**32)):
        with pytest.raises(ValueError, match=f"seeds|{bad}"):
            grid.parse_seeds(bad)


def test_a_piece_of_the_seeds_runs_those_seeds_as_the_whole_grid_does(tmp_path):
    """``--seeds 1-1`` runs seed 1 alone, recorded as such, with the row the whole grid's
    seed 1 has (each seed computed the same whichever seeds run with it), so that pieces
    run in separate processes merge into the grid."""
    whole = {r["seed"]: r for r in _run(tmp_path / "whole", seeds=2)}
    (piece,) = _run(tmp_path / "piece", seeds=range(1, 2))
    assert piece["seed"] == "1" and piece["score"] == whole["1"]["score"]
    assert piece["final_distance"] == whole["1"]["final_distance"]
    (inv,) = json.loads((tmp_path / "piece" / rundir.RUN_FILE).read_text())["invocations"]
    assert "--seeds 1-1" in inv["command"]


def test_seeds_are_bounded_and_the_grid_is_enumerated_lazily(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_:  # an argument error, before any work
        runner.main(["run", "--tasks", TASK, "--methods", "random", "--seeds",
                     "99999999999999", "--out", str(tmp_path)])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and "--seeds: seeds must be an int K in 1 .. 4294967296" in err
    assert not (tmp_path / "results.csv").exists()
    with pytest.raises(ValueError, match="seeds must be an int K in 1 .. 4294967296"):
        run_grid(TASK, "random", seeds=2**32 + 1, out=tmp_path)
    done = [make_row(TASK, "random", 1, "quick", status="ok")]
    plan = Plan([TASK, "fold_cloth3"], ["random", "expert"], grid.MAX_SEEDS, "quick", done,
                True, None)
    assert plan.total == 4 * grid.MAX_SEEDS - 1  # counted, not listed
    runs = iter(plan)
    assert [next(runs) for _ in range(3)] == [(TASK, "random", 0), (TASK, "random", 2),
                                              (TASK, "random", 3)]


# ----------------------------------------------------------------------- precision

def test_rows_record_their_precision_and_a_resume_in_another_is_refused(tmp_path, capsys):
    rows = _run(tmp_path, seeds=1)
    assert rows[0]["precision"] == provenance.precision() == "float32"
    path = tmp_path / "results.csv"
    append_row(path, {**rows[0], "seed": 1, "precision": "float64"})
    code, _, err = _cli(capsys, "run", "--tasks", TASK, "--methods", "random", "--quick",
                        "--out", str(tmp_path), "--no-progress")
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert f"{path}: holds float64 results and this run computes in float32" in err, err


# ----------------------------------------------------------------------- escaping

def test_results_md_and_the_page_escape_what_they_copy_from_the_csv(tmp_path):
    path = tmp_path / "results.csv"
    evil = "<script>alert(1)</script> | <img src=x onerror=alert(2)>"
    _write(path, [_row(status="failed", score="", error=evil)])
    runner.main(["report", "--out", str(tmp_path)])
    for name in ("results.md", "index.html"):
        text = (tmp_path / name).read_text()
        assert "<script>alert" not in text and "<img src=x" not in text, name
        assert "&lt;script&gt;alert(1)&lt;/script&gt;" in text, name


# ----------------------------------------------------------------------- failing loudly

def test_a_failed_run_makes_the_command_exit_1_with_one_line_saying_why(tmp_path, capsys,
                                                                        monkeypatch):
    register_nan_planner(overwrite=True)
    monkeypatch.setattr(grid, "run_grid", functools.partial(
        run_grid, task_overrides={TASK: cheap_cloth_overrides(horizon=2)}, cache_goal=False))
    try:
        code, out, err = _cli(capsys, "run", "--tasks", TASK, "--methods",
                              "random,nan_actions", "--seeds", "1", "--quick", "--out",
                              str(tmp_path), "--no-progress")
    finally:
        registry.unregister("nan_actions")
    assert code == 1, (out, err)
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("dax-bench: 1 of 2 runs failed: fold_cloth1 / nan_actions "
                               "seed 0: non-finite"), lines
    assert out.strip().splitlines()[-1].endswith("index.html")


# ----------------------------------------------------------------------- time-bounded chunks

def test_max_minutes_stops_between_runs_and_the_same_command_resumes(tmp_path, monkeypatch):
    with monkeypatch.context() as m:  # the time is up once one run has finished
        m.setattr(Plan, "time_is_up", lambda self: sum(self.finished.values()) >= 1)
        rows = _run(tmp_path, seeds=3, max_minutes=1)
    assert len(rows) == 1 and rows.left == 2 and rows.left_by_task == {TASK: 2}
    assert rows.left_text().startswith("2 runs left (fold_cloth1 2)")
    assert (tmp_path / "index.html").is_file()
    rows = _run(tmp_path, seeds=3, max_minutes=1)
    assert len(rows) == 3 and rows.left == 0 and rows.left_text() == ""


def test_the_page_is_rewritten_while_a_long_grid_runs(tmp_path, monkeypatch, capsys):
    """Every REFRESH_MINUTES (here 0: after every run) the reports are rewritten from the
    rows written so far, and once more at the end; a failure to write them mid-grid is a
    warning, not a lost grid."""
    from dax_algos.bench import summary

    seen = []
    write = summary.write_reports

    def spy(rows, out, *a, **k):
        seen.append(len(rows))
        if len(seen) == 1:
            raise OSError("disk full")
        return write(rows, out, *a, **k)

    monkeypatch.setattr(grid, "REFRESH_MINUTES", 0.0)
    monkeypatch.setattr(summary, "write_reports", spy)
    rows = _run(tmp_path, seeds=3)
    assert len(rows) == 3 and seen == [1, 2, 3, 3]
    assert "the reports were not rewritten: disk full" in capsys.readouterr().err
    assert (tmp_path / "index.html").is_file()


def test_the_cli_says_what_is_left_with_exit_3(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(Plan, "time_is_up", lambda self: True)
    code, _, err = _cli(capsys, "run", "--tasks", TASK, "--methods", "random,expert",
                        "--seeds", "2", "--quick", "--out", str(tmp_path), "--max-minutes",
                        "0.5", "--no-progress")
    assert code == 3, err
    assert err.strip() == ("dax-bench: stopped at the time limit: 4 runs left "
                           "(fold_cloth1 4); run the same command again to continue"), err


def test_the_paper_preset_is_every_task_and_method_at_full_budgets_five_seeds():
    args = runner._parser().parse_args(["run", "--preset", "paper"])
    assert runner._grid_args(args) == dict(tasks="all", methods="all", seeds=5,
                                           out="results_paper", quick=False,
                                           method_overrides={})
    args = runner._parser().parse_args(["run", "--preset", "paper", "--tasks", TASK,
                                        "--seeds", "2", "--quick"])
    assert runner._grid_args(args) == dict(tasks=TASK, methods="all", seeds=range(2),
                                           out="results_paper", quick=True,
                                           method_overrides={})


def test_the_demo_preset_gives_its_learner_a_config_that_builds():
    """The demo's method overrides reach the grid and make a valid config of the method
    they name (a misspelt field would fail only inside the demo's run)."""
    from dax_algos import registry

    args = runner._parser().parse_args(["run", "--preset", "demo"])
    g = runner._grid_args(args)
    assert set(g["method_overrides"]) <= set(g["methods"].split(","))
    for name, fields in g["method_overrides"].items():
        method = registry.get(name)
        config = method.config_cls(**{**method.budgets["quick"], **fields})
        for field, value in fields.items():
            assert getattr(config, field) == value, (name, field)


# ----------------------------------------------------------------------- old files

def test_a_results_file_from_before_untrained_scores_reads_and_is_upgraded(tmp_path):
    path = tmp_path / "results.csv"
    _write(path, [], header=PROVENANCE_COLUMNS)
    with open(path, "a") as f:
        f.write(",".join(["fold_cloth1", "ppo", "0", "quick", "ok", "0.5"]
                         + [""] * (len(PROVENANCE_COLUMNS) - 6)) + "\n")
    (old,) = read_rows(path)
    assert old["score"] == "0.5" and old["untrained_score"] == ""
    upgrade(path, [old])
    assert path.read_text().splitlines()[0] == ",".join(COLUMNS)
    assert read_rows(path) == [old]
    with open(path, "a") as f:  # an untrained score is a final-step r_gt too
        fields = dict.fromkeys(COLUMNS, "")
        fields.update(task="fold_cloth1", method="ppo", seed="1", budget="quick",
                      status="ok", score="0.5", untrained_score="1.5")
        f.write(",".join(fields.values()) + "\n")
    with pytest.raises(ValueError, match=r"line 3: untrained_score '1.5' is not in \[0, 1\]"):
        read_rows(path)


def test_a_results_file_from_before_the_machine_column_reads_and_is_upgraded(tmp_path):
    """Rows written before rows recorded their machine class read with it empty (an
    unknown class), and the file takes the new column on upgrade, values kept."""
    path = tmp_path / "results.csv"
    _write(path, [], header=UNTRAINED_COLUMNS)
    with open(path, "a") as f:
        f.write(",".join(["fold_cloth1", "ppo", "0", "quick", "ok", "0.5"]
                         + [""] * (len(UNTRAINED_COLUMNS) - 7) + ["0.25"]) + "\n")
    (old,) = read_rows(path)
    assert (old["untrained_score"], old["machine"]) == ("0.25", "")
    upgrade(path, [old])
    assert path.read_text().splitlines()[0] == ",".join(COLUMNS)
    assert read_rows(path) == [old]


def test_a_results_file_from_before_provenance_reads_as_stale_and_is_upgraded(tmp_path):
    path = tmp_path / "results.csv"
    _write(path, [], header=OLD_COLUMNS)
    with open(path, "a") as f:
        f.write("fold_cloth1,random,0,quick,ok,0.5,0.1,1.0,1.0,2,0,,,,\n")
    (old,) = read_rows(path)
    assert old["task_fingerprint"] == "" and not provenance.has_provenance(old)
    assert provenance.stale_reason(old, provenance.Today()) == provenance.UNKNOWN
    overrides = {TASK: cheap_cloth_overrides(horizon=2)}  # as the old run had them
    (tmp_path / rundir.RUN_FILE).write_text(json.dumps(
        {"task_overrides": rundir.canonical(overrides), "method_overrides": {}}))
    rows = _run(tmp_path, seeds=2)
    assert path.read_text().splitlines()[0] == ",".join(COLUMNS)
    assert [r["seed"] for r in rows] == ["0", "1"] and rows[0]["task_fingerprint"] == ""
    md = (tmp_path / "results.md").read_text()
    assert "## Stale rows" in md and "1 of 2 rows" in md and "provenance unknown" in md, md
    assert re.search(r"\| random \| [0-9.]+ \(n=1\) \|", md), md  # the old row left out
