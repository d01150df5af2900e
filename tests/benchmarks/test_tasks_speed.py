"""The task benchmark runs and reports what it promises (keys and sanity, never times)."""

import json

import pytest

from benchmarks import tasks as bench


def test_bench_reports_every_figure(capsys):
    records = bench.main(["--json", "--tasks", "fold_cloth1", "--batch", "1,2", "--reps", "1"])
    lines = [json.loads(line) for line in capsys.readouterr().out.splitlines() if line]
    assert lines == records and len(records) == 1
    rec = records[0]
    assert rec["task"] == "fold_cloth1" and rec["object_points"] == 121
    assert rec["substeps"] == 700 and rec["scene_dt"] == 1e-3
    assert rec["sim_time_per_step_s"] == 0.7
    assert [b["batch"] for b in rec["batches"]] == [1, 2]
    for b in rec["batches"]:
        for key in ("reset_s", "step_s", "per_env_step_s", "step_grad_s", "compile_reset_s",
                    "compile_step_s", "compile_grad_s"):
            assert b[key] > 0, key
        assert b["grad_finite"] and b["grad_norm"] > 0


def test_bench_unknown_task_exits_2(capsys):
    with pytest.raises(SystemExit) as exc:
        bench.main(["--tasks", "fold_origami"])
    assert exc.value.code == 2
    assert "valid names" in capsys.readouterr().err


def test_bench_unknown_resolution_exits_2(capsys):
    with pytest.raises(SystemExit) as exc:
        bench.main(["--tasks", "fold_cloth1", "--resolution", "default,fine"])
    assert exc.value.code == 2
    assert "default, reference" in capsys.readouterr().err
