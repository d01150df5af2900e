"""Bad output locations for ``dax-bench run`` (issue 17): each refused before any work, in
one line naming the path, with exit 2; a second writer of the same results is refused;
results made with other overrides are not silently returned for a new run."""

import os

import pytest
from algos_helpers import cheap_cloth_overrides

import dax_tasks
from dax_algos.bench import rundir, runner
from dax_algos.bench.grid import run_grid
from dax_algos.bench.rows import COLUMNS
from dax_tasks import io

TASK = "fold_cloth1"


@pytest.fixture
def no_work(monkeypatch):
    """Any task built means the runner started working."""
    def boom(*a, **k):
        raise AssertionError("the runner started work before refusing its output")

    monkeypatch.setattr(dax_tasks, "make", boom)


def one_line_error(capsys, out, *needles):
    code = runner.main(["run", "--tasks", TASK, "--methods", "random", "--out", str(out),
                       "--no-progress"])
    err = capsys.readouterr().err
    assert code == 2, f"expected exit 2, got {code}: {err}"
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    assert lines[0].startswith("dax-bench: error: "), lines
    for needle in needles:
        assert needle in lines[0], f"expected {needle!r} in {lines[0]!r}"
    return lines[0]


def test_out_that_is_a_file_is_refused(tmp_path, capsys, no_work):
    out = tmp_path / "results"
    out.write_text("not a directory")
    one_line_error(capsys, out, str(out), "is not a directory")


def test_results_csv_that_is_a_directory_is_refused(tmp_path, capsys, no_work):
    (tmp_path / "results.csv").mkdir()
    one_line_error(capsys, tmp_path, str(tmp_path / "results.csv"), "is not a file")


def test_unwritable_directory_is_refused_before_the_first_episode(tmp_path, capsys, no_work):
    if os.geteuid() == 0:  # root writes anywhere a mode allows none: sysfs refuses it too
        out = "/sys/kernel"
    else:
        out = tmp_path / "ro"
        out.mkdir()
        out.chmod(0o500)
    one_line_error(capsys, out, f"{out}: cannot write in the output directory")


@pytest.mark.parametrize("content, where, problem", [
    (b"\xff\xfe\x00garbage\n", ": not a dax-bench results file", "not UTF-8 text"),
    (b"a,b,c\n1,2,3\n", ": not a dax-bench results file", "columns ['a', 'b', 'c']"),
    (",".join(COLUMNS).encode() + b"\n" + b"fold_cloth1,random,x,quick,ok"
     + b"," * (len(COLUMNS) - 5) + b"\n", ", line 2:", "seed 'x' is not an integer"),
])
def test_garbled_results_file_is_refused_naming_it_and_left_alone(tmp_path, capsys, no_work,
                                                                   content, where, problem):
    path = tmp_path / "results.csv"
    path.write_bytes(content + b"half a line")
    one_line_error(capsys, tmp_path, f"{path}{where}", problem)
    assert path.read_bytes() == content + b"half a line", "the refused file was changed"


def test_a_second_runner_on_the_same_results_is_refused(tmp_path, capsys, no_work):
    with io.exclusive(tmp_path / "results.csv", program="dax-bench run (first)"):
        one_line_error(capsys, tmp_path, str(tmp_path / "results.csv"),
                       "another process is writing it", "dax-bench run (first)")


def test_a_waiting_runner_says_who_holds_the_lock_and_gives_up(tmp_path, capsys, no_work):
    """``--lock-timeout S``: one line saying who holds the results, then after S seconds
    the one-line error."""
    csv = tmp_path / "results.csv"
    with io.exclusive(csv, program="dax-bench run (first)"):
        code = runner.main(["run", "--tasks", TASK, "--methods", "random", "--out",
                            str(tmp_path), "--no-progress", "--lock-timeout", "0.3"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 2, err
    assert err[0].startswith(f"{csv}: waiting for another process") and \
        "dax-bench run (first)" in err[0] and "up to 0.3 s" in err[0], err
    assert err[1].startswith("dax-bench: error: ") and "waited 0.3 s" in err[1], err


def test_other_overrides_on_the_same_out_are_refused_not_answered_with_old_rows(tmp_path):
    small = cheap_cloth_overrides(horizon=2)
    kw = dict(seeds=1, out=tmp_path, quick=True, cache_goal=False, progress=False)
    rows = run_grid(TASK, "random", task_overrides={TASK: small}, **kw)
    assert [r["status"] for r in rows] == ["ok"], rows
    assert run_grid(TASK, "random", task_overrides={TASK: small}, **kw) == rows
    other = dict(small, horizon=3)
    with pytest.raises(ValueError, match=f"{tmp_path}: holds results made with other task "
                                         f"overrides .*horizon.*2.*horizon.*3"):
        run_grid(TASK, "random", task_overrides={TASK: other}, **kw)
    with pytest.raises(ValueError, match="other method overrides"):
        run_grid(TASK, "random", task_overrides={TASK: small},
                       method_overrides={"random": {"x": 1}}, **kw)
    # a results directory from before run files holds runs without overrides
    (tmp_path / rundir.RUN_FILE).unlink()
    with pytest.raises(ValueError, match="other task overrides"):
        run_grid(TASK, "random", task_overrides={TASK: small}, **kw)
