"""``dax-bench merge``: pieces of one grid, run apart, gathered into one output directory
hold what one run of the whole grid holds."""

import json
import shutil

import pytest
from algos_helpers import cheap_cloth_overrides

from dax_algos.bench import learning, runner
from dax_algos.bench.grid import run_grid
from dax_algos.bench.merge import merge_dirs
from dax_algos.bench.rows import key, read_rows

TASK = "fold_cloth1"


def _run(out, methods, seeds):
    return run_grid(TASK, methods, seeds=seeds, out=out, quick=True,
                    task_overrides={TASK: cheap_cloth_overrides(horizon=2)},
                    cache_goal=False, progress=False)


@pytest.fixture(scope="module")
def pieces(tmp_path_factory):
    root = tmp_path_factory.mktemp("merge")
    _run(root / "whole", "random,expert", 2)
    _run(root / "a", "random", 1)
    _run(root / "b", "random,expert", 2)
    # a learner's curve travels with its run: one written beside expert seed 1's row
    curve = [dict(task=TASK, method="expert", seed=1, budget="quick", update=u,
                  env_steps=4.0 * (u + 1), wall_s=0.5 * (u + 1), score=0.1 * u)
             for u in range(3)]
    learning.append_curve(learning.learning_path(root / "b", TASK), curve)
    return root, curve


def _by_key(out):
    return {key(r): r for r in read_rows(out / "results.csv")}


def test_merged_pieces_hold_the_rows_and_files_of_the_whole_run(pieces):
    root, curve = pieces
    a, b, whole = root / "a", root / "b", root / "whole"
    before = _by_key(a)
    done = merge_dirs(a, [b])
    assert sorted(done.added) == [(TASK, "expert", 0, "quick"), (TASK, "expert", 1, "quick"),
                                  (TASK, "random", 1, "quick")]
    assert done.skipped == [(TASK, "random", 0, "quick")]
    merged, reference = _by_key(a), _by_key(whole)
    assert set(merged) == set(reference)
    # the run a already had keeps a's row; the others are b's, as b recorded them
    assert merged[(TASK, "random", 0, "quick")] == before[(TASK, "random", 0, "quick")]
    b_rows = _by_key(b)
    for k in done.added:
        assert merged[k] == b_rows[k]
    # same seed, same numbers on CPU: the merged grid scores as the whole one did
    assert {k: r["score"] for k, r in merged.items()} == \
        {k: r["score"] for k, r in reference.items()}
    for task, method, seed, _ in merged:
        assert (a / "episodes" / task / method / f"seed{seed}.npz").is_file()
    got = learning.read_curves(learning.learning_path(a, TASK))
    assert got == curve
    invocations = json.loads((a / "run.json").read_text())["invocations"]
    assert [i["command"].split("--methods ")[1].split()[0] for i in invocations] == \
        ["random", "random,expert"]
    assert all("machine" in i and "versions" in i for i in invocations)


def test_merging_again_adds_nothing_and_the_cli_says_so(pieces, capsys):
    root, _ = pieces
    a, b = root / "a", root / "b"
    merge_dirs(a, [b])  # the first test may not have run (-k): merge once here
    text = (a / "results.csv").read_text()
    curves = learning.learning_path(a, TASK).read_text()
    assert runner.main(["merge", "--into", str(a), str(b)]) == 0
    out = capsys.readouterr().out
    assert out.startswith("0 runs merged") and "4 already there" in out, out
    assert (a / "results.csv").read_text() == text
    assert learning.learning_path(a, TASK).read_text() == curves
    assert (a / "results.md").is_file() and (a / "index.html").is_file()


def test_pieces_of_another_grid_are_refused_before_anything_is_written(pieces, tmp_path,
                                                                      capsys):
    root, _ = pieces
    other = tmp_path / "other"
    shutil.copytree(root / "b", other)
    run = json.loads((other / "run.json").read_text())
    run["task_overrides"][TASK]["horizon"] = 3
    (other / "run.json").write_text(json.dumps(run))
    into = tmp_path / "into"
    shutil.copytree(root / "whole", into)
    text = (into / "results.csv").read_text()
    with pytest.raises(ValueError, match="other task overrides"):
        merge_dirs(into, [other])
    assert runner.main(["merge", "--into", str(into), str(tmp_path / "missing")]) == 2
    assert "has no results.csv" in capsys.readouterr().err
    assert (into / "results.csv").read_text() == text


def test_a_run_that_failed_in_into_is_retried_by_the_source(pieces, tmp_path):
    root, _ = pieces
    into, b = tmp_path / "into", root / "b"
    shutil.copytree(root / "whole", into)
    # into's expert seed 1 failed (as a run killed out of memory would); b ran it
    csv_path = into / "results.csv"
    lines = csv_path.read_text().splitlines(keepends=True)
    header = lines[0].rstrip("\n").split(",")
    i = next(n for n, line in enumerate(lines)
             if line.startswith(f"{TASK},expert,1,"))
    fields = lines[i].rstrip("\n").split(",")
    fields[header.index("status")] = "failed"
    fields[header.index("score")] = ""
    fields[header.index("error")] = "RESOURCE_EXHAUSTED"
    lines[i] = ",".join(fields) + "\n"
    csv_path.write_text("".join(lines))
    k = (TASK, "expert", 1, "quick")
    done = merge_dirs(into, [b])
    assert done.added == [k]
    assert (TASK, "expert", 0, "quick") in done.skipped
    rows = [r for r in read_rows(csv_path) if key(r) == k]
    assert [r["status"] for r in rows] == ["failed", "ok"]
    assert json.loads(rows[1]["previous_errors"]) == ["RESOURCE_EXHAUSTED"]
    assert rows[1]["score"] == _by_key(b)[k]["score"]
    # the retry counts now: merging again adds nothing
    assert merge_dirs(into, [b]).added == []


def test_a_stale_run_in_into_is_replaced_by_the_sources_fresh_one(pieces, tmp_path):
    root, _ = pieces
    into, b = tmp_path / "into", root / "b"
    shutil.copytree(root / "whole", into)
    # into's expert seed 1 was measured on other code (its fingerprint is not today's)
    csv_path = into / "results.csv"
    lines = csv_path.read_text().splitlines(keepends=True)
    header = lines[0].rstrip("\n").split(",")
    i = next(n for n, line in enumerate(lines)
             if line.startswith(f"{TASK},expert,1,"))
    fields = lines[i].rstrip("\n").split(",")
    fields[header.index("task_fingerprint")] = "000000000000"
    lines[i] = ",".join(fields) + "\n"
    csv_path.write_text("".join(lines))
    k = (TASK, "expert", 1, "quick")
    done = merge_dirs(into, [b])
    # only the stale run: the fresh rows of into stay, those of b are skipped
    assert done.added == [k]
    assert (TASK, "expert", 0, "quick") in done.skipped
    rows = [r for r in read_rows(csv_path) if key(r) == k]
    assert len(rows) == 2
    assert rows[0]["task_fingerprint"] == "000000000000"
    assert rows[1]["task_fingerprint"] == _by_key(b)[k]["task_fingerprint"]
    assert rows[1]["score"] == _by_key(b)[k]["score"]
    # the fresh row counts now: merging again adds nothing
    assert merge_dirs(into, [b]).added == []
