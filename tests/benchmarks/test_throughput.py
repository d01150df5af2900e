"""The tracked throughput figure (issue 35): ``python -m benchmarks.tasks throughput``
writes one JSON document (keys and sanity here, never times), ``render_throughput_table``
prints its Markdown table, and the dax-tasks README holds that table as a generated block
(``benchmarks.tables``) whose file is a throughput document."""

import json

from benchmarks import tables
from benchmarks import tasks as bench

README = tables.ROOT / "packages" / "dax-tasks" / "README.md"


def test_throughput_document_and_its_table(tmp_path, capsys):
    out = tmp_path / "tp.json"
    # batch 2 would take over 1 ms per call: recorded as not measured, with the reason
    doc = bench.main(["throughput", "--tasks", "fold_cloth1", "--batch", "1,2", "--reps", "1",
                      "--max-call-s", "0.001", "--out", str(out)])
    assert json.loads(capsys.readouterr().out) == doc == json.loads(out.read_text())
    assert doc["bench"] == "throughput" and doc["resolution"] == "default"
    assert doc["batches"] == [1, 2] and doc["device"] and doc["command"].startswith(
        "python -m benchmarks.tasks throughput")
    (task,) = doc["tasks"]
    assert task["task"] == "fold_cloth1" and task["object_points"] == 121
    one, two = task["rows"]
    assert one["measured"] and one["batch"] == 1
    for key in ("step_s", "steps_per_s", "grad_s", "grad_steps_per_s", "compile_step_s",
                "compile_grad_s"):
        assert one[key] > 0, key
    assert one["steps_per_s"] == 1 / one["step_s"] and one["grad_finite"]
    assert len(one["load_1min"]) == 2
    assert not two["measured"] and "too heavy" in two["reason"]
    table = bench.render_throughput_table(out)
    lines = table.splitlines()
    assert lines[0].startswith("| task | default: points, substeps × dt | batch 1: ")
    row = lines[2].split(" | ")
    assert row[0] == "| fold_cloth1" and row[1] == "121, 700 × 1 ms"
    assert row[3] == "not measured [1] |"
    assert "[1] fold_cloth1 at batch 2: too heavy" in table and str(out) in table
    assert tables.main(["throughput", str(out)]) == 0
    assert capsys.readouterr().out == table


def test_jobs_compile_in_parallel_and_merge_in_task_order(tmp_path, capsys):
    out = tmp_path / "tp.json"
    doc = bench.main(["throughput", "--tasks", "whip_rope,fold_cloth1", "--batch", "1",
                      "--reps", "1", "--no-grad", "--jobs", "2", "--out", str(out)])
    capsys.readouterr()
    assert doc == json.loads(out.read_text()) and doc["jobs"] == 2
    assert [t["task"] for t in doc["tasks"]] == ["whip_rope", "fold_cloth1"]
    for task in doc["tasks"]:
        (row,) = task["rows"]
        assert row["measured"] and row["step_s"] > 0 and row["grad_s"] is None
    assert "--jobs 2" in doc["command"] and "--barrier" not in doc["command"]
    assert "compiled in 2 processes at once" in bench.render_throughput_table(out)


def test_skip_rule_scales_linearly_on_a_cpu_only():
    prev = {"measured": True, "batch": 1, "step_s": 0.5, "grad_s": 2.0}
    assert "scaled linearly" in bench._skip_reason(prev, 16, 30.0, True, linear=True)
    assert bench._skip_reason(prev, 16, 30.0, True, linear=False) is None
    assert "unscaled" in bench._skip_reason(prev, 16, 1.0, True, linear=False)
    assert bench._skip_reason(None, 16, 0.001, True) is None


def test_the_dax_tasks_readme_holds_generated_throughput_tables():
    blocks = [argv for _, argv in tables.blocks(README.read_text()) if argv[0] == "throughput"]
    assert blocks, "no generated throughput table"
    for _, path in blocks:
        doc = json.loads((tables.ROOT / path).read_text())
        assert doc["bench"] == "throughput" and doc["batches"] == [1, 16, 64]
        assert [t["task"] for t in doc["tasks"]] == list(bench.available()), path
    # the block is what the file renders now (test_readme_tables checks every block too)
    assert [a for a, _ in tables.stale_blocks(README) if a.startswith("throughput")] == []
